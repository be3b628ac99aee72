"""Simulator routes with real revisits (street loop retrace, room return) and the non-revisiting
control (room oneway): motion, smoothness across the lap end, views, sim.json keys, CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest

from vings_core.errors import ConfigError
from vings_core.geometry import rotation_angle_deg
from vings_core.sim import build_scene, default_camera, generate, make_scene, render_view_full


@pytest.fixture(scope="module")
def retraced():
    """A 50 m street loop at 10 Hz driven on for half a lap."""
    return build_scene("street", seed=2, loop=True, length_m=50.0, fps=10.0, retrace=0.5)


def _gt(out):
    """Body positions (N, 3) m and stamps (N,) ns of the ground truth, and the frame stamps (ns)."""
    rows = (out / "mav0" / "state_groundtruth_estimate0" / "data.csv").read_text().splitlines()[1:]
    gt = np.array([[float(x) for x in r.split(",")] for r in rows])
    cams = (out / "mav0" / "cam0" / "data.csv").read_text().splitlines()[1:]
    return gt[:, 1:4], gt[:, 0].astype(np.int64), np.array([int(r.split(",")[0]) for r in cams])


# ----------------------------------------------------------------------------- street retrace


def test_retrace_drives_the_same_lanes_again(retraced):
    m, r = retraced.motion, retraced.revisit
    P = r["first_pass_end_s"]
    assert r["first_pass_start_s"] == 0.0 and r["retrace_start_s"] == P == r["lap_s"]
    assert abs(P * 10 - round(P * 10)) < 1e-9, "the lap is a whole number of frames"
    assert r["retrace_end_s"] == pytest.approx(m.duration) and m.duration > P
    t = np.linspace(0.0, m.duration - P, 400)
    first, second = m.sample(t), m.sample(t + P)
    np.testing.assert_allclose(second.p, first.p, atol=1e-9)       # same lane, same direction
    np.testing.assert_allclose(second.v, first.v, atol=1e-9)
    np.testing.assert_allclose(second.R, first.R, atol=1e-9)
    # half of the loop's length driven again (arc length of the retrace from positions)
    s = m.sample(np.linspace(P, m.duration, 20000))
    retrace_len = np.linalg.norm(np.diff(s.p[:, :2], axis=0), axis=1).sum()
    assert retrace_len == pytest.approx(0.5 * r["loop_length_m"], rel=2e-3)
    assert retraced.info["route_length_m"] == pytest.approx(1.5 * r["loop_length_m"])


def test_retrace_is_smooth_across_the_end_of_the_lap(retraced):
    m = retraced.motion
    P = retraced.revisit["first_pass_end_s"]
    for h in (1e-4, 1e-6):          # the state just before and just after the lap end agree, O(h)
        a, b = m.sample(np.array([P - h])), m.sample(np.array([P + h]))
        for k in ("p", "v", "a", "w"):
            jump = np.abs(getattr(b, k) - getattr(a, k)).max()
            assert jump < 300 * h, (k, h, jump)
    # the analytic derivatives (what the IMU is made of) match finite differences across P
    t = np.linspace(P - 0.3, P + 0.3, 61)
    h = 1e-5
    s, sp, sm = m.sample(t), m.sample(t + h), m.sample(t - h)
    np.testing.assert_allclose((sp.p - sm.p) / (2 * h), s.v, atol=1e-6)
    np.testing.assert_allclose((sp.v - sm.v) / (2 * h), s.a, atol=1e-5)
    dR = np.einsum("nji,njk->nik", sm.R, sp.R)
    w_fd = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]],
                    -1) / (4 * h)
    np.testing.assert_allclose(w_fd, s.w, atol=1e-5)


def test_plain_loop_is_the_first_pass_of_the_retrace(retraced):
    plain = build_scene("street", seed=2, loop=True, length_m=50.0, fps=10.0)
    assert plain.revisit is None and plain.info["retrace"] is None
    assert plain.motion.duration == pytest.approx(retraced.revisit["lap_s"], abs=1e-12)
    t = np.linspace(0.0, plain.motion.duration, 300)
    np.testing.assert_allclose(retraced.motion.sample(t).p, plain.motion.sample(t).p, atol=1e-12)
    np.testing.assert_array_equal(plain.static.origin, retraced.static.origin)     # the same city


def test_retrace_after_a_slow_start_revisits_the_start_pose():
    scene = build_scene("street", seed=1, loop=True, length_m=50.0, fps=10.0, retrace=1.0,
                        slow_start_s=2.0)
    r = scene.revisit
    assert r["first_pass_end_s"] == pytest.approx(r["lap_s"] + 1.0)
    s = scene.motion.sample(np.array([0.0, r["first_pass_end_s"], scene.motion.duration]))
    assert np.linalg.norm(s.p[1] - s.p[0]) < 1e-6 and rotation_angle_deg(s.R[0].T @ s.R[1]) < 1e-6
    assert np.linalg.norm(s.p[2] - s.p[0]) < 1e-6, "a whole second lap ends at the start again"


def test_cli_retrace_summary_finds_the_first_revisiting_frame(tmp_path, capsys, retraced):
    from vings_ros.cli import main

    out = tmp_path / "retrace"
    rc = main(["sim", "--scene", "street", "--loop", "--retrace", "0.5", "--length-m", "50",
               "--fps", "10", "--seed", "2", "--width", "24", "--height", "16", "--no-mcap",
               "--out", str(out)])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["route"] == "loop" and summary["retrace"] == 0.5 and summary["loop"]
    r = summary["revisit"]
    D = summary["duration_s"]
    assert r["retrace_end_s"] == pytest.approx(D)
    k, lap = r["first_revisit_frame"], r["lap_frames"]
    assert k == lap == round(r["first_pass_end_s"] * 10)
    assert r["retrace_frames"] == summary["frames"] - 1 - k
    assert summary["frames"] == int(np.floor(retraced.motion.duration * 10 + 1e-6)) + 1, "the whole drive"
    p, ts, cams = _gt(out)
    idx = np.searchsorted(ts, cams)
    assert (ts[idx] == cams).all()
    pf = p[idx]
    np.testing.assert_allclose(pf[k:], pf[:len(pf) - k], atol=1e-6)     # frame i + lap at frame i
    assert summary["path_length_m"] == pytest.approx(1.5 * r["loop_length_m"], rel=0.02)
    assert json.loads((out / "sim.json").read_text())["revisit"] == r


def test_retrace_cut_by_frames_says_so(tmp_path, retraced):
    lap = round(retraced.revisit["lap_s"] * 10)
    out = generate("street", tmp_path / "cut", frames=lap + 3, width=16, height=12, seed=2,
                   loop=True, length_m=50.0, fps=10.0, retrace=0.5, mcap=False, noise=False)
    summary = json.loads((out / "sim.json").read_text())
    r = summary["revisit"]
    assert r["first_revisit_frame"] == lap and r["retrace_frames"] == 2
    assert r["retrace_end_s"] == pytest.approx((lap + 2) / 10)
    assert any("retrace is cut short" in n for n in summary["notes"])


# ----------------------------------------------------------------------------- room routes


def _heading_deg(T_wc: np.ndarray) -> np.ndarray:
    """(N,) yaw (deg) of the cameras' optical axes in the world's x-y plane."""
    z = T_wc[:, :3, 2]
    return np.degrees(np.arctan2(z[:, 1], z[:, 0]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_room_return_ends_at_its_start_pose_after_a_lap(seed):
    scene = build_scene("room", seed=seed, route="return", fps=20.0)     # 300 frames: 14.95 s
    T = scene.info["route_duration_s"]
    assert T == pytest.approx(299 / 20)
    t = np.arange(300) / 20.0
    T_wc = scene.T_wc(t)
    assert np.linalg.norm(T_wc[-1, :3, 3] - T_wc[0, :3, 3]) < 0.01
    assert rotation_angle_deg(T_wc[0, :3, :3].T @ T_wc[-1, :3, :3]) < 0.5
    s = scene.motion.sample(np.linspace(0.0, T, 3000))
    np.testing.assert_allclose(s.v[-1], s.v[0], atol=1e-9)      # a whole lap: smooth as well
    # it explores: halfway round it is across the room, looking the other way
    half = np.abs(t - T / 2).argmin()
    assert np.linalg.norm(T_wc[half, :2, 3] - T_wc[0, :2, 3]) > 1.0
    d = (_heading_deg(T_wc[half:half + 1]) - _heading_deg(T_wc[:1]) + 180) % 360 - 180
    assert abs(d[0]) > 120
    yaw = np.unwrap(np.radians(_heading_deg(T_wc)))
    assert abs(abs(yaw[-1] - yaw[0]) - 2 * np.pi) < 0.02, "one turn around the room"
    speed = np.linalg.norm(s.v, axis=1)
    assert 0.45 < speed.mean() < 1.0 and speed.max() < 1.6
    assert (np.abs(s.p[:, 0]) < 1.42).all() and (np.abs(s.p[:, 1]) < 0.92).all()
    assert (s.p[:, 2] > 1.2).all() and (s.p[:, 2] < 1.6).all()


@pytest.mark.parametrize("route", ["return", "oneway"])
def test_room_route_derivatives_are_exact(route):
    m = make_scene("room", seed=4, route=route, route_duration_s=8.0).motion
    t = np.linspace(0.01, 7.99, 200)
    h = 1e-5
    s, sp, sm = m.sample(t), m.sample(t + h), m.sample(t - h)
    np.testing.assert_allclose((sp.p - sm.p) / (2 * h), s.v, atol=1e-6)
    np.testing.assert_allclose((sp.v - sm.v) / (2 * h), s.a, atol=1e-5)
    dR = np.einsum("nji,njk->nik", sm.R, sp.R)
    w_fd = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]],
                    -1) / (4 * h)
    np.testing.assert_allclose(w_fd, s.w, atol=1e-5)


@pytest.mark.parametrize("route", ["return", "oneway"])
def test_room_routes_keep_clear_of_furniture_and_movers(route):
    for seed in range(3):
        scene = make_scene("room", seed=seed, dynamic=True, route=route, route_duration_s=14.95)
        t = np.arange(0.0, 14.95, 0.05)
        p = scene.motion.sample(t).p
        assert (np.abs(p[:, 0]) < 1.42).all() and (np.abs(p[:, 1]) < 0.92).all()   # as the default
        for m in scene.movers:
            c = np.stack([m.cx(t), m.cy(t), m.cz(t)], -1)
            assert np.linalg.norm((c - p)[:, :2], axis=1).min() > 0.5


def _seen_cells(scene, camera, T_wc: np.ndarray, t: np.ndarray, cell: float = 0.25) -> set:
    """The ``cell``-metre voxels of every surface point the views ``T_wc`` at times ``t`` see."""
    H, W = camera.height, camera.width
    v, u = np.indices((H, W), dtype=np.float64)
    rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)], -1)
    seen = set()
    for T, ti in zip(T_wc, t):
        r = render_view_full(scene, camera, T, float(ti), antialias=False)
        hit = r.prim >= 0
        X = (rays[hit] * r.depth[hit][:, None].astype(np.float64)) @ T[:3, :3].T + T[:3, 3]
        seen |= set(map(tuple, np.floor(X / cell).astype(np.int64)))
    return seen


@pytest.mark.parametrize("seed", [0, 3])
def test_room_oneway_never_re_sees_its_first_views(seed):
    n = 300
    scene = build_scene("room", seed=seed, route="oneway", fps=20.0)
    t = np.arange(n) / 20.0
    T_wc = scene.T_wc(t)
    first, last = slice(0, n // 5), slice(n // 2, n)
    # the walk goes one way along x (its smooth step; the sway aside) and the view turns round
    walk = scene.motion.x.terms[0]
    assert abs(walk(t[-1]) - walk(0.0)) > 2.0
    assert (walk(t[1:-1], 1) * np.sign(walk(t[-1]) - walk(0.0)) > 0).all()
    x = T_wc[:, 0, 3] * np.sign(T_wc[0, 0, 3])              # > 0 at the start's end of the room
    assert x[first].min() > x[last].max(), "the last half stays away from where the start was"
    h = _heading_deg(T_wc)
    gap = np.abs((h[last][None, :] - h[first][:, None] + 180) % 360 - 180)
    assert gap.min() > 120, "the end looks away from where the start looked"
    cam = default_camera(48, 32)
    A = _seen_cells(scene, cam, T_wc[first][::4], t[first][::4])
    B = _seen_cells(scene, cam, T_wc[last][::4], t[last][::4])
    assert len(A) > 100
    assert len(A - B) / len(A) > 0.95, "the last half never sees what the first fifth saw"
    # and the return route does re-see it at its end
    ret = build_scene("room", seed=seed, route="return", fps=20.0)
    T_r = ret.T_wc(t)
    A_r = _seen_cells(ret, cam, T_r[:10:3], t[:10:3])
    B_r = _seen_cells(ret, cam, T_r[-10::3], t[-10::3])
    assert len(A_r & B_r) / len(A_r) > 0.6


def test_room_handheld_route_is_the_default_motion():
    a, b = make_scene("room", seed=5), make_scene("room", seed=5, route="handheld")
    t = np.linspace(0, 10, 50)
    np.testing.assert_array_equal(a.motion.sample(t).p, b.motion.sample(t).p)
    assert a.info["route"] == "handheld"


@pytest.mark.parametrize("route", ["return", "oneway"])
def test_cli_room_routes(tmp_path, capsys, route):
    from vings_ros.cli import main

    out = tmp_path / route
    rc = main(["sim", "--scene", "room", "--route", route, "--frames", "101", "--width", "24",
               "--height", "16", "--no-mcap", "--no-noise", "--out", str(out)])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["route"] == route and summary["scene_info"]["route"] == route
    assert summary["retrace"] is None and summary["revisit"] is None
    p, ts, cams = _gt(out)
    assert ts[-1] == cams[-1]
    if route == "return":
        assert summary["start_end_distance_m"] < 0.01
        assert np.linalg.norm(p[-1] - p[0]) < 0.01
    else:
        assert summary["start_end_distance_m"] > 1.5


# ----------------------------------------------------------------------------- bad options


@pytest.mark.parametrize("kw,match", [
    (dict(scene_name="street", retrace=0.5), "needs --loop"),
    (dict(scene_name="street", loop=True, retrace=0.0), r"\(0, 1\]"),
    (dict(scene_name="street", loop=True, retrace=1.5), r"\(0, 1\]"),
    (dict(scene_name="street", loop=True, retrace=float("nan")), r"\(0, 1\]"),
    (dict(scene_name="room", retrace=0.5), "street scene only"),
    (dict(scene_name="street", route="return"), "room scene only"),
    (dict(scene_name="street", loop=True, route="handheld"), "room scene only"),
    (dict(scene_name="room", route="circle"), "unknown room route"),
    (dict(scene_name="room", route="return", frames=60), "at least 101 frames at 20 fps"),
    (dict(scene_name="room", route="oneway", frames=120, slow_start_s=2.0), "at least 121 frames"),
])
def test_generate_bad_route_options(tmp_path, kw, match):
    with pytest.raises(ConfigError, match=match):
        generate(out_dir=tmp_path / "x", width=16, height=12, mcap=False, **kw)
    assert not (tmp_path / "x").exists()


def test_make_scene_route_options():
    with pytest.raises(ConfigError, match="needs --loop"):
        make_scene("street", length_m=60.0, retrace=0.5)
    with pytest.raises(ConfigError, match="at least 5 s"):
        make_scene("room", route="return", route_duration_s=3.0)
    with pytest.raises(ConfigError, match="'return' and 'oneway' routes only"):
        make_scene("room", route_duration_s=10.0)
    with pytest.raises(ConfigError, match="does not take"):
        make_scene("room", retrace=0.5)


@pytest.mark.parametrize("argv,needle", [
    (["--scene", "street", "--loop", "--retrace", "2"], "retrace"),
    (["--scene", "street", "--retrace", "0.5"], "--loop"),
    (["--scene", "street", "--route", "return"], "--route"),
])
def test_cli_bad_route_options_are_one_line(tmp_path, capsys, argv, needle):
    from vings_ros.cli import main

    rc = main(["sim", *argv, "--no-mcap", "--out", str(tmp_path / "z")])
    assert rc == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
