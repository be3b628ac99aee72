"""Data contracts, geometry, config loading and TUM I/O."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import torch

from vings_core import geometry as G
from vings_core.config import ConfigError, config_from_dict, load_section, read_params_file
from vings_core.trajectory_io import read_tum, stamp_ns_to_str, str_to_stamp_ns, write_tum
from vings_core.types import CameraModel, Calibration, Frame, Keyframe, Trajectory
from vings_core.errors import InputError


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(n, 6)) * np.array([2, 2, 2, 1, 1, 1])
    return G.np_se3_exp(xi)


def test_se3_exp_log_round_trip_and_near_pi():
    xi = torch.randn(64, 6, dtype=torch.float64)
    n = xi[:, 3:].norm(dim=1, keepdim=True)
    xi[:, 3:] *= torch.clamp(3.0 / n, max=1.0)  # keep |phi| < pi: log returns the principal angle
    assert torch.allclose(G.se3_log(G.se3_exp(xi)), xi, atol=1e-10)
    small = torch.randn(8, 6, dtype=torch.float64) * 1e-9
    assert torch.allclose(G.se3_log(G.se3_exp(small)), small, atol=1e-15)
    axis = torch.tensor([0.3, -0.5, 0.81], dtype=torch.float64)
    phi = axis / axis.norm() * (np.pi - 1e-6)
    R = G.so3_exp(phi)
    back = G.so3_exp(G.so3_log(R))
    assert torch.allclose(back, R, atol=1e-9)


def test_so3_exp_is_rotation_and_matches_scipy():
    from scipy.spatial.transform import Rotation
    phi = np.random.default_rng(1).normal(size=(20, 3))
    R = G.np_so3_exp(phi)
    assert np.allclose(R, Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    q = G.np_rotmat_to_quat(R)
    qs = Rotation.from_matrix(R).as_quat()  # xyzw
    qs = np.where(qs[:, 3:4] < 0, -qs, qs)
    assert np.allclose(q, qs, atol=1e-12)
    assert np.allclose(G.np_quat_to_rotmat(q), R, atol=1e-12)


def test_pose_inverse_and_transform_points():
    T = torch.as_tensor(_random_poses(5))
    I = T @ G.pose_inverse(T)
    assert torch.allclose(I, torch.eye(4, dtype=torch.float64).expand_as(I), atol=1e-12)
    p = torch.randn(5, 3, dtype=torch.float64)
    q = G.transform_points(T, p)
    ref = (T[:, :3, :3] @ p[..., None])[..., 0] + T[:, :3, 3]
    assert torch.allclose(q, ref)


def test_se3_exp_left_jacobian_first_order():
    """exp(xi + d) ~ exp(J_l(phi) d-ish): check the derivative of se3_exp numerically is finite and
    that the translation of exp([rho, 0]) equals rho."""
    rho = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    T = G.se3_exp(torch.cat([rho, torch.zeros(3, dtype=torch.float64)]))
    assert torch.allclose(T[:3, 3], rho)
    assert torch.allclose(T[:3, :3], torch.eye(3, dtype=torch.float64))


def test_camera_scaled_pixel_centres():
    cam = CameraModel(752, 480, 458.654, 457.296, 367.215, 248.375, "radtan",
                      np.array([-0.28, 0.07, 1e-4, 1e-5]))
    half = cam.scaled(376, 240)
    assert half.fx == pytest.approx(cam.fx / 2)
    assert half.cx == pytest.approx((cam.cx + 0.5) / 2 - 0.5)
    assert np.array_equal(half.distortion, cam.distortion)
    assert CameraModel.from_dict(cam.to_dict()) == cam
    assert half != cam
    with pytest.raises(ValueError, match="distortion model"):
        CameraModel(10, 10, 1, 1, 5, 5, "fisheye-ish")
    with pytest.raises(ValueError, match="size"):
        CameraModel(0, 10, 1, 1, 5, 5)


def test_frame_gray_and_rgb():
    cam = CameraModel(4, 3, 1, 1, 2, 1.5)
    img = np.zeros((3, 4, 3), np.uint8)
    img[..., 0] = 255
    f = Frame(1, img, cam)
    assert f.is_color and f.gray()[0, 0] == 76
    g = Frame(2, np.full((3, 4), 9, np.uint8), cam)
    assert g.rgb().shape == (3, 4, 3) and int(g.rgb()[1, 1, 2]) == 9


def test_keyframe_shape_check():
    cam = CameraModel(8, 6, 5, 5, 4, 3)
    ok = dict(stamp_ns=5, image=torch.zeros(6, 8, 3), T_wc=np.eye(4), depth=torch.ones(6, 8),
              inv_depth_var=torch.ones(6, 8), valid=torch.ones(6, 8, dtype=torch.bool), camera=cam)
    kf = Keyframe(**ok)
    assert kf.T_wc.dtype == torch.float64
    bad = dict(ok, depth=torch.ones(5, 8))
    with pytest.raises(ValueError, match="depth"):
        Keyframe(**bad)


def test_calibration_dict_round_trip():
    cam = CameraModel(376, 240, 200, 201, 188, 120)
    T = _random_poses(1)[0]
    c = Calibration(cam, T_bc=T, has_imu=True)
    c2 = Calibration.from_dict(c.to_dict())
    assert np.allclose(c2.T_bc, T) and c2.has_imu and c2.camera.fx == 200


def test_stamp_strings_are_exact():
    for ns in [0, 1, 999_999_999, 1_403_715_273_262_142_976, 1_234_567_890_123_456_789]:
        assert str_to_stamp_ns(stamp_ns_to_str(ns)) == ns
    assert stamp_ns_to_str(1_403_715_273_262_142_976) == "1403715273.262142976"
    assert str_to_stamp_ns("1.5e-3") == 1_500_000


def test_tum_round_trip(tmp_path):
    stamps = np.array([1_403_715_273_262_142_976 + i * 50_000_000 for i in range(10)])
    traj = Trajectory(stamps, _random_poses(10))
    write_tum(tmp_path / "t.tum", traj)
    back = read_tum(tmp_path / "t.tum")
    assert np.array_equal(back.stamps_ns, traj.stamps_ns)
    assert np.allclose(back.poses, traj.poses, atol=1e-8)
    assert traj.path_length() > 0


def test_tum_bad_input(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_tum(tmp_path / "missing.tum")
    p = tmp_path / "bad.tum"
    p.write_text("1.0 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match=r"bad.tum:1: expected 8 columns"):
        read_tum(p)
    p.write_text("1.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="duplicated"):
        read_tum(p)
    p.write_text("1.0 0 0 0 0 0 0 0\n")
    with pytest.raises(InputError, match="zero quaternion"):
        read_tum(p)


@dataclass
class _Cfg:
    iters: int = 3
    lr: float = 0.1
    name: str = "a"
    on: bool = True

    def validate(self) -> None:
        if self.iters < 1:
            raise ValueError("iters must be >= 1")


def test_config_loading(tmp_path):
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    stage:\n      iters: 5\n"
                 "mapper_node:\n  ros__parameters:\n    stage:\n      lr: 2\n"
                 "rviz:\n  ros__parameters:\n    stage:\n      lr: 7\n")   # another node's block: not ours
    cfg = load_section(_Cfg, "stage", p, sections=("stage",))
    assert cfg == _Cfg(iters=5, lr=2.0)
    # the project's own sections: a misspelt one is an error, not silently ignored
    with pytest.raises(ConfigError, match="unknown parameter section.*'stage'"):
        load_section(_Cfg, "stage", p)
    assert isinstance(cfg.lr, float)
    assert load_section(_Cfg, "stage") == _Cfg()
    with pytest.raises(ConfigError, match="unknown parameter 'iterz'"):
        config_from_dict(_Cfg, {"iterz": 1})
    with pytest.raises(ConfigError, match="expected an integer"):
        config_from_dict(_Cfg, {"iters": "5"})
    with pytest.raises(ConfigError, match="iters must be >= 1"):
        config_from_dict(_Cfg, {"iters": 0})
    bad = tmp_path / "b.yaml"
    bad.write_text("node:\n  params:\n    x: 1\n")
    with pytest.raises(ConfigError, match="ros__parameters"):
        read_params_file(bad)
    with pytest.raises(ConfigError, match="not found"):
        read_params_file(tmp_path / "nope.yaml")


def test_params_file_dotted_names_and_bad_files(tmp_path):
    from vings_core.mapping import MapperConfig
    p = tmp_path / "p.yaml"
    # dotted names are valid ROS 2 params syntax: they join their section
    p.write_text("/**:\n  ros__parameters:\n    mapping.iters_per_keyframe: 5\n    mapping:\n"
                 "      window_size: 3\n")
    cfg = load_section(MapperConfig, "mapping", p)
    assert (cfg.iters_per_keyframe, cfg.window_size) == (5, 3)
    for text, msg in (("/**:\n  ros__parameters:\n    mappping: {window_size: 2}\n", "'mappping'"),
                      ("/**:\n  ros__parameters:\n    iters_per_keyframe: 7\n", "'iters_per_keyframe'"),
                      ("/**:\n  ros__parameters: 5\n", "must be a mapping"),
                      ("/**:\n  ros__parameters:\n    mapping: {a: [1, 2}\n", "line 3"),
                      ("/**:\n  ros__parameters:\n    mapping.window_size: 3\n    mapping: 4\n", "twice")):
        p.write_text(text)
        with pytest.raises(ConfigError, match=msg):
            load_section(MapperConfig, "mapping", p)
    p.write_bytes(b"# caf\xe9\n/**:\n  ros__parameters: {}\n")
    with pytest.raises(ConfigError, match="not UTF-8"):
        read_params_file(p)


def test_cli_help_lists_and_errors(capsys):
    from vings_ros.cli import main
    assert main([]) == 1
    out = capsys.readouterr().out
    assert "usage: vings" in out


def test_vings_run_checks_the_params_file_before_any_work(tmp_path, capsys):
    from vings_ros.cli import main
    bad = tmp_path / "p.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    ros: {queue_sise: 3}\n")
    rc = main(["run", str(tmp_path / "no_such_source"), "--out", str(tmp_path / "o"), "--params", str(bad)])
    err = capsys.readouterr()
    assert rc != 0 and "unknown parameter 'queue_sise'" in err.out + err.err
    assert not (tmp_path / "o").exists()
    # an empty --out wrote the outputs into the current folder
    for out in ("", "  "):
        assert main(["run", str(tmp_path / "no_such_source"), "--out", out]) == 2
        assert "--out: give an output folder" in capsys.readouterr().err


def test_se3_exp_gradient_finite_at_zero():
    xi = torch.zeros(6, dtype=torch.float64, requires_grad=True)
    T = G.se3_exp(xi)
    (T[:3, 3].sum() + T[:3, :3].sum()).backward()
    assert torch.all(torch.isfinite(xi.grad))
    assert torch.allclose(xi.grad[:3], torch.ones(3, dtype=torch.float64))


def test_np_pose_compose_stays_rigid_over_long_chains():
    """Composing many increments keeps the rotation orthonormal (det +1) and equals plain products."""
    from vings_core.geometry import np_pose_compose, np_se3_exp
    rng = np.random.default_rng(3)
    T = np.eye(4)
    P = np.eye(4)
    for _ in range(2000):
        C = np_se3_exp(rng.normal(scale=0.05, size=6))
        T = np_pose_compose(C, T)
        P = C @ P
    R = T[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12
    assert abs(np.linalg.det(R) - 1.0) < 1e-12
    np.testing.assert_allclose(T, P, atol=1e-9)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def test_launch_never_overwrites_a_recording(tmp_path):
    from vings_ros.launch import Launcher, LaunchOptions
    rec = tmp_path / "rec.mcap"
    rec.write_bytes(b"earlier recording")
    with pytest.raises(ConfigError, match="recordings are never overwritten"):
        Launcher(LaunchOptions(record=str(rec)))
    assert rec.read_bytes() == b"earlier recording"
    # a recording that could not be written is refused before any node starts
    with pytest.raises(ConfigError, match="--record .*cannot write"):
        Launcher(LaunchOptions(record="/proc/vings/out.mcap"))


def test_launch_reads_the_params_file_first_and_waits_for_the_mappers_drain(tmp_path):
    from vings_ros import registry
    from vings_ros.launch import SAVE_MARGIN_S, Launcher, LaunchOptions
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapper_node:\n      shutdown_timeout_s: 600.0\n")
    assert Launcher(LaunchOptions(params_file=str(p))).stop_timeout["mapper_node"] == 600 + SAVE_MARGIN_S
    defaults = Launcher(LaunchOptions()).stop_timeout
    assert defaults["frontend_node"] == registry.node_spec("frontend_node").stop_timeout_s
    assert defaults["mapper_node"] >= registry.node_spec("mapper_node").stop_timeout_s
    opt = LaunchOptions(params_file=str(p), extra_params={"mapper_node.shutdown_timeout_s": 1000.0})
    assert Launcher(opt).stop_timeout["mapper_node"] == 1000 + SAVE_MARGIN_S
    p.write_text("/**:\n  ros__parameters:\n    mapping: {background: [0, 1, 0.5]}\n")
    with pytest.raises(ConfigError, match="p.yaml: mapping.background"):
        Launcher(LaunchOptions(params_file=str(p)))


@pytest.mark.parametrize("theta", [1.01e-4, 2e-4, 1e-3, 5e-3, 0.3])
def test_se3_exp_is_accurate_in_float32_just_above_the_series_cutoff(theta):
    """(1 - cos t)/t^2 and (t - sin t)/t^3 cancel in float32 near t = 1e-4 (translation off by ~1000
    eps, the gradient by 2x before the half-angle form and the series for C)."""
    from vings_core.geometry import se3_exp
    xi64 = torch.tensor([0.3, -0.2, 0.5, 0.0, 0.0, theta], dtype=torch.float64, requires_grad=True)
    xi32 = xi64.detach().float().requires_grad_(True)
    T64, T32 = se3_exp(xi64), se3_exp(xi32)
    assert float((T32.double() - T64).abs().max()) < 2e-7
    T64[0, 3].backward()
    T32[0, 3].backward()
    assert torch.allclose(xi32.grad.double(), xi64.grad, atol=1e-5)


def test_camera_refuses_non_finite_distortion():
    with pytest.raises(ValueError, match="distortion coefficients must be finite"):
        CameraModel(64, 48, 50.0, 50.0, 31.5, 23.5, "radtan", np.array([float("nan"), 0, 0, 0]))


def test_rotation_angle_is_accurate_for_tiny_and_half_turn_angles():
    import numpy as np

    from vings_core.geometry import np_so3_exp, rotation_angle_deg
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    for a in (1e-10, 1e-8, 1e-4, 0.5, 3.0, np.pi):
        assert np.radians(rotation_angle_deg(np_so3_exp(axis * a))) == pytest.approx(a, rel=1e-9)


def test_kernel_warm_up_exercises_the_mapping_kernels():
    """`make install` compiles the numba kernels through this round (no stall in the first run)."""
    from vings_core.warmup import warm_kernels
    assert warm_kernels() > 0
