"""VINGS-ROS: installable both as a pip package and as an ament_python ROS 2 package."""
import importlib.util
import sys
from glob import glob
from pathlib import Path

from setuptools import find_packages, setup

PACKAGE = "vings_ros"


def _registry():
    """vings_ros/registry.py (plain data), loaded by path: the nodes' console scripts."""
    path = Path(__file__).resolve().parent / "vings_ros" / "registry.py"
    spec = importlib.util.spec_from_file_location("_vings_registry", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod        # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(include=["vings_core", "vings_core.*", "vings_ros", "vings_ros.*",
                                    "msg_adapters", "msg_adapters.*"]),
    package_data={"vings_ros": ["config/*.xml", "config/*.json"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/params", glob("params/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    python_requires=">=3.11,<3.12",
    install_requires=[],  # pinned set in requirements.txt (see README); ROS deps come from package.xml
    # optional CUDA route of the renderer (a CUDA torch build is needed too; JIT-compiles on first use)
    extras_require={"cuda": ["gsplat==1.5.3"], "viz": ["rerun-sdk==0.41.0"]},
    zip_safe=False,
    maintainer="VINGS-ROS developers",
    maintainer_email="vings-ros@example.org",
    description="Monocular visual-inertial 2D Gaussian-splatting SLAM as a ROS 2 node graph",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "vings = vings_ros.cli:main",
            *_registry().console_scripts(),
        ],
        # params sections and node blocks the library's params reader accepts besides its own
        "vings.params_sections": ["vings_ros = vings_ros.registry:params_sections"],
    },
)
