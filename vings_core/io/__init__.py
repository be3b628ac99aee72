"""Sensor-data I/O: one :class:`Source` interface over EuRoC/ASL, TUM RGB-D, KITTI, ROS 1/2 bags and
MCAP files (see docs/io.md).

    >>> src = open_source("data/V1_01_easy", SourceOptions(width=376, height=240))
    >>> for item in src.stream(): ...   # Frames (undistorted, working resolution) and ImuSamples
"""
from .base import Source, SourceOptions
from .bag import BagSource
from .calib_yaml import load_calibration_yaml, save_calibration_yaml
from .detect import FORMATS, detect_format, open_source
from .euroc import EurocSource
from .image_codec import decode_compressed, decode_image, encode_image
from .kitti import KittiSource
from .tum import TumSource
from .undistort import Undistorter, working_size
from .writers import calib_yaml_path, write_euroc, write_mcap

__all__ = ["Source", "SourceOptions", "open_source", "detect_format", "FORMATS", "EurocSource",
           "TumSource", "KittiSource", "BagSource", "write_mcap", "write_euroc", "calib_yaml_path",
           "load_calibration_yaml", "save_calibration_yaml", "decode_image", "encode_image",
           "decode_compressed", "Undistorter", "working_size"]
