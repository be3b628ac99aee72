"""Synthetic scenes (`vings sim`): ray-caster, trajectories, IMU, EuRoC output, CLI."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from vings_core.errors import ConfigError
from vings_core.geometry import np_pose_inverse, rotation_angle_deg
from vings_core.sim import (T_BC_DEFAULT, build_scene, default_camera, generate, make_scene,
                            raycast, raycast_reference, render_view, render_view_full)
from vings_core.sim.imu import GRAVITY, ImuNoise, imu_truth, simulate_imu
from vings_core.sim.quads import make_quads
from vings_core.sim.textures import SIZE, load_atlas


@pytest.fixture(scope="module")
def room():
    return make_scene("room", seed=3, dynamic=True)


@pytest.fixture(scope="module")
def street():
    return make_scene("street", seed=5, length_m=600, dynamic=True)


def _look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (optical frame) at ``eye`` looking at ``target``."""
    eye, target, up = (np.asarray(a, float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    T = np.eye(4)
    T[:3, :3] = np.stack([x, y, z], 1)
    T[:3, 3] = eye
    return T


def _backproject(cam, T_wc, u, v, depth):
    depth = np.broadcast_to(np.asarray(depth, float), np.shape(u))
    pc = np.stack([(u - cam.cx) / cam.fx * depth, (v - cam.cy) / cam.fy * depth, depth], -1)
    return pc @ T_wc[:3, :3].T + T_wc[:3, 3]


def _project(cam, T_wc, X):
    pc = (X - T_wc[:3, 3]) @ T_wc[:3, :3]
    return cam.fx * pc[:, 0] / pc[:, 2] + cam.cx, cam.fy * pc[:, 1] / pc[:, 2] + cam.cy, pc[:, 2]


# ----------------------------------------------------------------------------- ray-caster


def test_render_view_api(room):
    cam = default_camera(96, 64)
    rgb, depth, mask = render_view(room, cam, room.T_wc(1.0)[0], t=1.0)
    assert rgb.shape == (64, 96, 3) and rgb.dtype == np.uint8
    assert depth.shape == (64, 96) and depth.dtype == np.float32
    assert mask.shape == (64, 96) and mask.dtype == bool
    assert (depth > 0).all(), "the room is closed: every pixel sees a surface"
    assert depth.max() < np.linalg.norm([6, 5, 3]) + 0.1
    assert rgb.std() > 20, "textured photographs, not a flat colour"


@pytest.mark.parametrize("which", ["room", "street"])
def test_kernel_matches_reference(which, room, street):
    scene = room if which == "room" else street
    cam = default_camera(80, 56)
    for t in (0.7, 4.2, 9.9):
        T_wc = scene.T_wc(t)[0]
        quads = scene.quads_at(t)
        out = raycast(quads, scene.atlas, cam, T_wc, sky=scene.sky)
        d_ref, prim_ref, uv_ref = raycast_reference(quads, cam, T_wc)
        same = out.prim == prim_ref
        assert same.mean() > 0.999
        hit = same & (prim_ref >= 0)
        np.testing.assert_allclose(out.depth[hit], d_ref[hit], rtol=2e-6, atol=1e-6)
        np.testing.assert_allclose(out.uv[hit], uv_ref[hit], atol=1e-6)
        assert np.array_equal(out.mask, (out.prim >= 0) & (quads.obj[np.maximum(out.prim, 0)] >= 0))


def test_plane_depth_is_analytic():
    """Ground plane z = 0 seen by a camera 1.5 m up pitched down: depth equals -h / d_z."""
    atlas = load_atlas()
    ground = make_quads([[-500.0, 500.0, 0.0]], [[0.0, -1.0, 0.0]], [[1.0, 0.0, 0.0]],
                        [[1000.0, 1000.0]], atlas.index("asphalt"), (2.0, 2.0), (0.0, 0.0),
                        (1.0, 1.0, 1.0))
    cam = default_camera(120, 80)
    T_wc = _look_at([0.3, -0.2, 1.5], [6.0, 1.0, 0.2])
    out = raycast(ground, atlas, cam, T_wc, sky=True)
    v, u = np.mgrid[0:cam.height, 0:cam.width].astype(float)
    d_w = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1) @ T_wc[:3, :3].T
    expect = np.where(d_w[..., 2] < 0, -1.5 / np.minimum(d_w[..., 2], -1e-300), 0.0)
    expect[expect > 5000] = 0.0  # beyond the plane's edge
    on = (expect > 0) & (expect < 600)
    assert on.sum() > 1000 and (out.depth[expect == 0] == 0).all()
    np.testing.assert_allclose(out.depth[on], expect[on], rtol=1e-6)


def test_point_projects_onto_predicted_texel():
    """A point of a fronto-parallel textured plane, projected into the image, shows the colour
    of the photograph at that point's texture coordinates (upright, level-0 bilinear)."""
    atlas = load_atlas()
    k = atlas.index("astronaut")
    tile, off, tint = 16.0, (0.3, 0.7), (0.9, 1.0, 0.8)   # texel 3 cm > pixel footprint 2 cm
    # plane z = 2 facing the camera; u = +x, v = -y (image up)
    quad = make_quads([[-5.0, 5.0, 2.0]], [[1.0, 0, 0]], [[0, -1.0, 0]], [[10.0, 10.0]], k,
                      (tile, tile), off, tint)
    cam = default_camera(160, 100)
    T_wc = np.eye(4)
    out = raycast(quad, atlas, cam, T_wc, sky=False)
    rng = np.random.default_rng(0)
    X = np.stack([rng.uniform(-1.0, 1.0, 200), rng.uniform(-0.6, 0.6, 200), np.full(200, 2.0)], 1)
    u, v, z = _project(cam, T_wc, X)
    px, py = np.rint(u).astype(int), np.rint(v).astype(int)
    Xp = _backproject(cam, T_wc, px.astype(float), py.astype(float), 2.0)   # pixel-centre points
    a, b = Xp[:, 0] + 5.0, 5.0 - Xp[:, 1]
    s, t = (a + off[0]) / tile, (b + off[1]) / tile
    img = atlas.level(k, 0).astype(float)
    col = s % 1.0 * SIZE - 0.5
    row = (1.0 - t % 1.0) * SIZE - 0.5          # +v is up in the photograph
    c0, r0 = np.floor(col), np.floor(row)
    wc, wr = (col - c0)[:, None], (row - r0)[:, None]
    c0, r0 = c0.astype(int) % SIZE, r0.astype(int) % SIZE
    c1, r1 = (c0 + 1) % SIZE, (r0 + 1) % SIZE
    expect = ((1 - wc) * (1 - wr) * img[r0, c0] + wc * (1 - wr) * img[r0, c1]
              + (1 - wc) * wr * img[r1, c0] + wc * wr * img[r1, c1]) * np.asarray(tint)
    got = out.rgb[py, px].astype(float)
    assert np.abs(got - expect).max() <= 1.0
    np.testing.assert_allclose(out.depth[py, px], 2.0, rtol=1e-6)


def test_texture_is_filtered_not_aliased():
    """Far away, a tiled photograph averages out (mip filtering) instead of flickering noise."""
    atlas = load_atlas()
    k = atlas.index("brick")
    quad = make_quads([[-2000.0, 2000.0, 0.0]], [[0, -1.0, 0]], [[1.0, 0, 0]], [[4000.0, 4000.0]], k,
                      (0.5, 0.5), (0.0, 0.0), (1.0, 1.0, 1.0))
    cam = default_camera(160, 100)
    out = raycast(quad, atlas, cam, _look_at([0, 0, 2.0], [100.0, 0, 1.0]), sky=True)
    far = (out.depth > 50)
    assert far.sum() > 300
    mean = atlas.level(k, 9)[0, 0].astype(float)        # 1x1 level = photograph mean
    np.testing.assert_allclose(out.rgb[far].mean(0), mean, atol=6.0)
    assert out.rgb[far].astype(float).std(0).max() < 12.0


# ----------------------------------------------------------------------------- rig and GT


def test_extrinsic_is_non_identity_and_looks_forward(room):
    R, t = T_BC_DEFAULT[:3, :3], T_BC_DEFAULT[:3, 3]
    assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.isclose(np.linalg.det(R), 1.0)
    assert 0.01 < np.linalg.norm(t) < 0.2
    nominal = np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])
    assert 0.5 < rotation_angle_deg(nominal.T @ R) < 5.0      # mounting error, not identity
    assert R[:, 2] @ np.array([1.0, 0, 0]) > 0.99               # optical axis = body forward
    np.testing.assert_allclose(room.T_wc(2.0)[0], room.T_wb(2.0)[0] @ T_BC_DEFAULT)


def test_rendering_consistent_with_gt_camera(room):
    """Points seen at one time, re-projected with T_wc = T_wb @ T_bc at another time, are rendered
    at their predicted pixel with the predicted depth."""
    cam = default_camera(160, 100)
    t1, t2 = 2.0, 2.6
    T1, T2 = room.T_wb(t1)[0] @ room.T_bc, room.T_wb(t2)[0] @ room.T_bc
    r1 = render_view_full(room, cam, T1, t1)
    rng = np.random.default_rng(1)
    u = rng.integers(5, cam.width - 5, 400).astype(float)
    v = rng.integers(5, cam.height - 5, 400).astype(float)
    ok1 = ~r1.mask[v.astype(int), u.astype(int)]
    X = _backproject(cam, T1, u, v, r1.depth[v.astype(int), u.astype(int)].astype(float))[ok1]
    u2, v2, z2 = _project(cam, T2, X)
    inside = (u2 > 2) & (u2 < cam.width - 3) & (v2 > 2) & (v2 < cam.height - 3) & (z2 > 0)
    r2 = render_view_full(room, cam, T2, t2)
    # exact: ray through the predicted (sub-pixel) position, compared with the reference caster
    quads = room.quads_at(t2)
    d_pred = np.array([raycast_reference(quads, _subpixel_camera(cam, uu, vv), T2)[0][0, 0]
                       for uu, vv in zip(u2[inside][:60], v2[inside][:60])])
    z_in = z2[inside][:60]
    visible = np.abs(d_pred - z_in) < 1e-6 * z_in + 1e-6
    assert visible.mean() > 0.7, "most re-projected points are visible, at exactly their depth"
    # and the kernel's depth at the nearest pixel agrees (the depth changes a little within a pixel)
    pi, pj = np.rint(v2[inside]).astype(int), np.rint(u2[inside]).astype(int)
    rel = np.abs(r2.depth[pi, pj] - z2[inside]) / z2[inside]
    assert np.median(rel) < 0.01


def _subpixel_camera(cam, u, v):
    """A 1x1 camera whose only pixel centre is at (u, v) of ``cam``."""
    from dataclasses import replace
    return replace(cam, width=1, height=1, cx=cam.cx - u, cy=cam.cy - v)


# ----------------------------------------------------------------------------- trajectories


@pytest.mark.parametrize("which", ["room", "street"])
def test_derivatives_are_exact(which, room, street):
    m = (room if which == "room" else street).motion
    T = 20.0 if which == "room" else m.duration - 0.01
    t = np.linspace(0.01, T, 300)
    h = 1e-5
    s, sp, sm = m.sample(t), m.sample(t + h), m.sample(t - h)
    np.testing.assert_allclose((sp.p - sm.p) / (2 * h), s.v, atol=1e-6)
    np.testing.assert_allclose((sp.v - sm.v) / (2 * h), s.a, atol=1e-5)
    dR = np.einsum("nji,njk->nik", sm.R, sp.R)          # R(t-h)^T R(t+h) ~ exp(2h w^)
    w_fd = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]],
                    -1) / (4 * h)
    np.testing.assert_allclose(w_fd, s.w, atol=1e-5)


def test_room_motion_is_handheld_and_bounded():
    for seed in range(3):
        m = make_scene("room", seed=seed).motion
        s = m.sample(np.arange(0, 300, 0.05))
        speed = np.linalg.norm(s.v, axis=1)
        assert 0.5 <= speed.mean() <= 1.5 and speed.max() < 2.0
        assert (np.abs(s.p[:, 0]) < 1.6).all() and (np.abs(s.p[:, 1]) < 1.1).all()
        assert (s.p[:, 2] > 1.0).all() and (s.p[:, 2] < 1.8).all()
        yaw = np.unwrap(np.arctan2(s.R[:, 1, 0], s.R[:, 0, 0]))
        assert np.ptp(yaw) > 2 * np.pi, "looks all around the room"
        assert np.linalg.norm(s.w, axis=1).max() < 3.0


def test_street_motion_is_driving(street):
    m = street.motion
    s = m.sample(np.arange(0, m.duration, 0.05))
    speed = np.linalg.norm(s.v, axis=1)
    assert 8.0 <= speed.max() <= 12.0 and speed.min() > 4.0
    assert np.abs(s.a[:, :2]).max() < 6.0, "no more than ~0.6 g"
    cam_z = street.T_wc(s.t)[:, 2, 3]
    assert np.abs(cam_z - 1.6).max() < 0.05
    heading = np.arctan2(s.v[:, 1], s.v[:, 0])
    fwd = s.R[:, :2, 0]
    assert (np.einsum("ni,ni->n", fwd, np.stack([np.cos(heading), np.sin(heading)], 1)) > 0.999).all()
    assert abs(m.total_length - 600.0) < 1e-6
    path = np.linalg.norm(np.diff(s.p, axis=0), axis=1).sum()
    assert abs(path - 600.0) < 2.0


@pytest.mark.parametrize("length", [50.0, 400.0, 2000.0])
def test_street_loop_returns_to_start(length):
    scene = build_scene("street", seed=4, loop=True, length_m=length, fps=20.0)
    D = scene.motion.duration
    assert abs(D * 20 - round(D * 20)) < 1e-6, "the last frame lands on the end of the loop"
    s = scene.motion.sample(np.array([0.0, D]))
    assert np.linalg.norm(s.p[1] - s.p[0]) < 1e-6
    assert np.linalg.norm(s.v[1] - s.v[0]) < 1e-6
    assert rotation_angle_deg(s.R[0].T @ s.R[1]) < 1e-6
    path = np.linalg.norm(np.diff(scene.motion.sample(np.linspace(0, D, 20000)).p, axis=0), axis=1)
    assert path.sum() > 0.6 * length


# ----------------------------------------------------------------------------- IMU


def _preintegrate(motion, t0, T=2.0, rate=200.0, midpoint=True):
    """GTSAM pre-integration of the noise-free IMU from the true state at t0; returns the position
    (m) and rotation (deg) errors of the NavState prediction at t0 + T."""
    gtsam = pytest.importorskip("gtsam")
    from vings_core.geometry import np_so3_exp
    dt = 1.0 / rate
    n = int(round(T * rate))
    t = t0 + np.arange(n + 1) * dt
    imu = simulate_imu(motion, t)
    p = gtsam.PreintegrationParams.MakeSharedU(GRAVITY)
    for setter in (p.setGyroscopeCovariance, p.setAccelerometerCovariance,
                   p.setIntegrationCovariance):
        setter(np.eye(3) * 1e-8)
    pim = gtsam.PreintegratedImuMeasurements(p, gtsam.imuBias.ConstantBias())
    for k in range(n):
        if midpoint:
            # trapezoid rule: mean rate, and the end sample's specific force rotated into the
            # interval's start frame (GTSAM holds each reading constant over dt)
            g = 0.5 * (imu.gyro[k] + imu.gyro[k + 1])
            a = 0.5 * (imu.accel[k] + np_so3_exp(g * dt) @ imu.accel[k + 1])
        else:
            g, a = imu.gyro[k], imu.accel[k]
        pim.integrateMeasurement(a, g, dt)
    s = motion.sample(np.array([t[0], t[-1]]))
    pred = pim.predict(gtsam.NavState(gtsam.Rot3(s.R[0]), s.p[0], s.v[0]),
                       gtsam.imuBias.ConstantBias())
    dp = float(np.linalg.norm(pred.position() - s.p[1]))
    dr = float(rotation_angle_deg(pred.attitude().matrix().T @ s.R[1]))
    return dp, dr


@pytest.mark.parametrize("which,t0", [("room", 0.0), ("room", 6.3), ("street", 0.0),
                                      ("street", 17.0), ("street", 31.5)])
def test_imu_preintegration_reproduces_pose(which, t0, room, street):
    motion = (room if which == "room" else street).motion
    dp, dr = _preintegrate(motion, t0)
    assert dp < 0.01 and dr < 0.1, (dp, dr)


def test_imu_plain_gtsam_euler_converges_first_order(room):
    """Raw readings fed to GTSAM as-is (forward Euler): within 1 cm / 0.1 deg at 200 Hz in the room,
    and the error shrinks ~5x at 1 kHz, so nothing is inconsistent beyond discretisation."""
    dp200, dr200 = _preintegrate(room.motion, 1.0, midpoint=False)
    dp1k, dr1k = _preintegrate(room.motion, 1.0, rate=1000.0, midpoint=False)
    assert dp200 < 0.01 and dr200 < 0.1
    assert dp1k < 0.3 * dp200 and dr1k < 0.3 * dr200


def test_imu_at_rest_reads_gravity():
    from vings_core.sim.trajectory import HandheldMotion, SineSum
    z = SineSum(0.0, np.zeros(1), np.zeros(1), np.zeros(1))
    still = HandheldMotion(z, z, SineSum(1.0, np.zeros(1), np.zeros(1), np.zeros(1)), z, z, z)
    g, a = imu_truth(still, np.linspace(0, 1, 5))
    np.testing.assert_allclose(g, 0.0, atol=1e-15)
    np.testing.assert_allclose(a, np.tile([0, 0, GRAVITY], (5, 1)), atol=1e-12)


def test_imu_noise_statistics_and_seed(room):
    t = np.arange(40000) * 0.005
    cfg = ImuNoise()
    a = simulate_imu(room.motion, t, cfg, np.random.default_rng(7))
    b = simulate_imu(room.motion, t, cfg, np.random.default_rng(7))
    c = simulate_imu(room.motion, t, cfg, np.random.default_rng(8))
    assert np.array_equal(a.gyro, b.gyro) and np.array_equal(a.accel, b.accel)
    assert not np.allclose(a.gyro, c.gyro)
    white_g = a.gyro - a.gyro_true - a.bias_gyro
    white_a = a.accel - a.accel_true - a.bias_accel
    np.testing.assert_allclose(white_g.std(0), cfg.gyro_noise_density / np.sqrt(0.005), rtol=0.05)
    np.testing.assert_allclose(white_a.std(0), cfg.accel_noise_density / np.sqrt(0.005), rtol=0.05)
    np.testing.assert_allclose(np.diff(a.bias_gyro, axis=0).std(0),
                               cfg.gyro_random_walk * np.sqrt(0.005), rtol=0.05)
    np.testing.assert_allclose(np.diff(a.bias_accel, axis=0).std(0),
                               cfg.accel_random_walk * np.sqrt(0.005), rtol=0.05)


# ----------------------------------------------------------------------------- dynamic objects


def test_dynamic_masks_where_objects_are_seen(room):
    cam = default_camera(96, 64)
    seen = 0
    for t in np.arange(0.0, 30.0, 1.5):
        T_wc = room.T_wc(t)[0]
        out = render_view_full(room, cam, T_wc, t)
        for m in room.movers:
            _, c = m.pose(t)
            u, v, z = _project(cam, T_wc, c[None])
            if z[0] > 0.3 and 3 < u[0] < cam.width - 3 and 3 < v[0] < cam.height - 3:
                # the object's centre projects here: the mask is set unless something occludes it
                d_static = raycast(room.static, room.atlas, cam, T_wc, sky=False).depth
                occluded = d_static[int(v[0]), int(u[0])] < z[0] - 0.5
                if not occluded:
                    assert out.mask.any()
                    assert out.mask[int(round(v[0])), int(round(u[0]))]
                    seen += 1
        # mask = pixels whose nearest surface belongs to a moving object
        quads = room.quads_at(t)
        hit = out.prim >= 0
        assert np.array_equal(out.mask[hit], quads.obj[out.prim[hit]] >= 0)
    assert seen >= 2
    static_room = make_scene("room", seed=3)
    _, _, mask = render_view(static_room, cam, static_room.T_wc(3.0)[0], 3.0)
    assert not mask.any()


@pytest.mark.parametrize("which,clearance", [("room", 0.5), ("street", 3.0)])
def test_moving_objects_never_hit_the_camera(which, clearance, room):
    scene = room if which == "room" else make_scene("street", seed=9, length_m=2000, dynamic=True)
    assert scene.movers
    T = scene.motion.duration or 120.0
    t = np.arange(0.0, T, 0.05)
    p = scene.motion.sample(t).p
    for m in scene.movers:
        c = np.stack([m.cx(t), m.cy(t), m.cz(t)], -1)
        horiz = np.linalg.norm((c - p)[:, :2], axis=1)
        assert horiz.min() > clearance


def test_street_cars_move_and_are_masked(street):
    assert len(street.movers) > 0
    ts = np.linspace(0, street.motion.duration, 40)
    for m in street.movers:          # every car drives (metres over the route), none stands still
        assert max(np.ptp(m.cx(ts)), np.ptp(m.cy(ts))) > 3.0
    cam = default_camera(96, 64)
    frac, masks = [], []
    for t in ts:
        _, _, mask = render_view(street, cam, street.T_wc(t)[0], t)
        frac.append(mask.mean())
        masks.append(mask)
    seen = [i for i, f in enumerate(frac) if f > 0]
    assert max(frac) > 0.005 and len(seen) >= 3
    assert any(not np.array_equal(masks[a], masks[b]) for a, b in zip(seen[:-1], seen[1:]))


# ----------------------------------------------------------------------------- EuRoC output


def _read_csv(path: Path) -> tuple[str, list[list[str]]]:
    lines = path.read_text().splitlines()
    return lines[0], [ln.split(",") for ln in lines[1:]]


def test_generate_euroc_layout_and_mcap(tmp_path):
    import cv2

    from vings_core.io import open_source
    from vings_core.io.calib_yaml import read_yaml_doc

    out = generate("room", tmp_path / "seq", frames=4, width=64, height=48, seed=2, dynamic=True,
                   mcap=True, noise=False)
    mav0 = out / "mav0"
    header, rows = _read_csv(mav0 / "cam0" / "data.csv")
    assert header == "#timestamp [ns],filename" and len(rows) == 4
    stamps = [int(r[0]) for r in rows]
    assert np.all(np.diff(stamps) == 50_000_000)
    for s in stamps:
        img = cv2.imread(str(mav0 / "cam0" / "data" / f"{s}.png"), cv2.IMREAD_UNCHANGED)
        assert img.shape == (48, 64, 3)
        d = np.load(mav0 / "depth0" / "data" / f"{s}.npy")
        assert d.dtype == np.float32 and d.shape == (48, 64) and (d > 0).all()
        m = cv2.imread(str(mav0 / "mask0" / "data" / f"{s}.png"), cv2.IMREAD_UNCHANGED)
        assert m.dtype == np.uint8 and m.shape == (48, 64) and set(np.unique(m)) <= {0, 255}
    cam_yaml = read_yaml_doc(mav0 / "cam0" / "sensor.yaml")
    assert cam_yaml["camera_model"] == "pinhole"
    assert cam_yaml["distortion_model"] == "radial-tangential"
    assert cam_yaml["distortion_coefficients"] == [0.0, 0.0, 0.0, 0.0]
    assert cam_yaml["resolution"] == [64, 48] and cam_yaml["rate_hz"] == 20
    assert cam_yaml["T_BS"]["rows"] == 4 and cam_yaml["T_BS"]["cols"] == 4
    np.testing.assert_allclose(np.reshape(cam_yaml["T_BS"]["data"], (4, 4)), T_BC_DEFAULT, atol=1e-11)
    cam = default_camera(64, 48)
    np.testing.assert_allclose(cam_yaml["intrinsics"], [cam.fx, cam.fy, cam.cx, cam.cy])
    imu_yaml = read_yaml_doc(mav0 / "imu0" / "sensor.yaml")
    assert imu_yaml["gyroscope_noise_density"] == pytest.approx(1.6968e-4)
    assert imu_yaml["accelerometer_random_walk"] == pytest.approx(3.0e-3)
    assert imu_yaml["rate_hz"] == 200
    h, imu_rows = _read_csv(mav0 / "imu0" / "data.csv")
    assert h.startswith("#timestamp [ns],w_RS_S_x [rad s^-1]") and h.endswith("a_RS_S_z [m s^-2]")
    assert len(imu_rows) == 31 and int(imu_rows[0][0]) == stamps[0] and int(imu_rows[-1][0]) == stamps[-1]
    h, gt_rows = _read_csv(mav0 / "state_groundtruth_estimate0" / "data.csv")
    assert "q_RS_w" in h and "b_a_RS_S_z" in h and len(gt_rows[0]) == 17 and len(gt_rows) == 31
    summary = json.loads((out / "sim.json").read_text())
    assert summary["frames"] == 4 and summary["scene"] == "room" and summary["seed"] == 2
    assert {"path_length_m", "duration_s"} <= set(summary)
    assert (out / "room.mcap").is_file() and (out / "room.calib.yaml").is_file()
    assert not list(tmp_path.glob(".seq.tmp-*"))

    # the I/O layer reads it back: frames, exact IMU, body ground truth, depth
    src = open_source(out)
    assert src.kind == "euroc" and len(src.frame_stamps()) == 4
    np.testing.assert_allclose(src.calibration.T_bc, T_BC_DEFAULT, atol=1e-11)
    imu = src.imu_samples()
    scene = build_scene("room", seed=2, dynamic=True)
    g, a = imu_truth(scene.motion, (np.array([s.stamp_ns for s in imu]) - stamps[0]) * 1e-9)
    np.testing.assert_allclose(np.array([s.gyro for s in imu]), g, atol=1e-12)
    np.testing.assert_allclose(np.array([s.accel for s in imu]), a, atol=1e-12)
    gt_cam = src.gt_camera_trajectory()
    t_f = (np.asarray(stamps) - stamps[0]) * 1e-9
    idx = np.searchsorted(gt_cam.stamps_ns, stamps)
    np.testing.assert_allclose(gt_cam.poses[idx], scene.T_wc(t_f), atol=1e-9)
    _, d_render, _ = render_view(scene, cam, scene.T_wc(t_f[2])[0], t_f[2])
    np.testing.assert_array_equal(src.gt_depth(stamps[2]), d_render)
    mcap_src = open_source(out / "room.mcap")
    assert len(mcap_src.frame_stamps()) == 4 and len(mcap_src.imu_samples()) == 31


def test_generate_is_deterministic(tmp_path):
    kw = dict(frames=3, width=48, height=32, mcap=False, dynamic=True)
    a = generate("room", tmp_path / "a", seed=11, **kw)
    b = generate("room", tmp_path / "b", seed=11, **kw)
    c = generate("room", tmp_path / "c", seed=12, **kw)
    files = sorted(p.relative_to(a) for p in (a / "mav0").rglob("*") if p.is_file())
    assert len(files) > 10
    for f in files:
        assert (a / f).read_bytes() == (b / f).read_bytes(), f
    imu = Path("mav0/imu0/data.csv")
    assert (a / imu).read_bytes() != (c / imu).read_bytes()


def test_generate_replaces_previous_output_only(tmp_path):
    out = tmp_path / "seq"
    generate("room", out, frames=2, width=32, height=24, mcap=False)
    generate("room", out, frames=3, width=32, height=24, mcap=False)
    assert json.loads((out / "sim.json").read_text())["frames"] == 3
    assert len(list((out / "mav0" / "cam0" / "data").iterdir())) == 3
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep me")
    with pytest.raises(ConfigError, match="not a simulator output"):
        generate("room", foreign, frames=2, width=32, height=24, mcap=False)
    assert (foreign / "notes.txt").read_text() == "keep me"
    # a run's outputs kept inside an earlier simulator output would be deleted: refused
    (out / "run1").mkdir()
    (out / "run1" / "metrics.json").write_text("{}")
    with pytest.raises(ConfigError, match="run1.*would delete"):
        generate("room", out, frames=2, width=32, height=24, mcap=False)
    assert (out / "run1" / "metrics.json").exists()
    f = tmp_path / "afile"
    f.write_text("x")
    with pytest.raises(ConfigError, match="cannot write the simulator output"):
        generate("room", f / "sub", frames=2, width=32, height=24, mcap=False)


@pytest.mark.parametrize("kw,match", [
    (dict(scene_name="forest"), "unknown scene"),
    (dict(scene_name="room", length_m=100.0), "street scene only"),
    (dict(scene_name="room", loop=True), "street scene only"),
    (dict(scene_name="street", length_m=10.0), ">= 50 m"),
    (dict(scene_name="street", length_m=60.0, frames=500), "raise --length-m"),
    (dict(scene_name="room", fps=30.0), "divide"),
    (dict(scene_name="room", frames=1), ">= 2"),
])
def test_generate_bad_options(tmp_path, kw, match):
    with pytest.raises(ConfigError, match=match):
        generate(out_dir=tmp_path / "x", width=32, height=24, mcap=False, **kw)
    assert not (tmp_path / "x").exists()


def test_make_scene_rejects_unknown_options():
    with pytest.raises(ConfigError, match="does not take"):
        make_scene("room", length_m=10)


def test_cli_street_loop_returns_to_start(tmp_path, capsys):
    from vings_ros.cli import main

    out = tmp_path / "loop"
    rc = main(["sim", "--scene", "street", "--loop", "--length-m", "50", "--fps", "10",
               "--width", "24", "--height", "16", "--no-mcap", "--out", str(out)])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["loop"] and summary["start_end_distance_m"] < 1.0
    _, rows = _read_csv(out / "mav0" / "state_groundtruth_estimate0" / "data.csv")
    p = np.array([[float(x) for x in r[1:4]] for r in rows])
    _, cam_rows = _read_csv(out / "mav0" / "cam0" / "data.csv")
    assert int(cam_rows[-1][0]) == int(rows[-1][0])
    assert np.linalg.norm(p[-1] - p[0]) < 1.0
    assert np.linalg.norm(np.diff(p, axis=0), axis=1).sum() > 40.0


def test_cli_reports_bad_option_as_one_line(tmp_path, capsys):
    from vings_ros.cli import main

    rc = main(["sim", "--scene", "room", "--length-m", "10", "--out", str(tmp_path / "z")])
    assert rc == 2
    err = capsys.readouterr().err
    assert "length-m" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_mcap_skip_reason_reaches_the_summary(tmp_path, monkeypatch):
    import json

    from vings_core.sim import sequence
    monkeypatch.setattr(sequence, "_write_mcap", lambda tmp, name: (None, "MCAP skipped: test reason"))
    out = generate("room", tmp_path / "seq", frames=3, width=48, height=32, mcap=True, noise=False)
    summary = json.loads((out / sequence.SUMMARY_NAME).read_text())
    assert summary["mcap"] is None and "MCAP skipped: test reason" in summary["notes"]


def test_too_many_street_frames_names_the_frames():
    from vings_core.errors import ConfigError
    with pytest.raises(ConfigError, match=r"--frames 100000 at 20 fps needs a street of 60.0 km.*at most 83317 frames"):
        generate("street", "/nonexistent/never-written", frames=100000)


def test_blind_interval_covers_the_lens_and_nothing_else(tmp_path):
    """--blind T0:T1: the images in the interval are black (sensor noise only); depth and ground
    truth are those of the scene; a bad interval is a clear error."""
    import cv2
    from vings_core.errors import ConfigError
    from vings_core.sim import generate, load_summary
    out = generate("room", tmp_path / "b", frames=6, width=64, height=48, mcap=False, fps=20.0,
                   blind=(0.1, 0.2))
    pngs = sorted((out / "mav0" / "cam0" / "data").glob("*.png"))
    means = [float(cv2.imread(str(p)).mean()) for p in pngs]
    assert [m < 3 for m in means] == [False, False, True, True, False, False], means
    assert np.load(sorted((out / "mav0" / "depth0" / "data").glob("*.npy"))[2]).max() > 0
    s = load_summary(out)
    assert s["blind_frames"] == 2 and any("lens covered" in n for n in s["notes"])
    with pytest.raises(ConfigError, match="blind interval"):
        generate("room", tmp_path / "c", frames=4, width=32, height=24, mcap=False, blind=(0.3, 0.1))


def test_slow_start_motion_starts_from_rest_with_consistent_derivatives():
    """SlowStartMotion: zero speed and angular rate at t = 0; v, a the finite differences of p, v;
    after the ramp the base motion, ramp/2 seconds late."""
    from vings_core.sim import make_scene
    from vings_core.sim.trajectory import SlowStartMotion
    base = make_scene("room", seed=0).motion
    m = SlowStartMotion(base, 1.5)
    s0 = m.sample(0.0)
    assert np.abs(s0.v).max() < 1e-12 and np.abs(s0.w).max() < 1e-12
    t = np.linspace(0.05, 2.5, 40)
    h = 1e-5
    sp, sm, s = m.sample(t + h), m.sample(t - h), m.sample(t)
    assert np.allclose((sp.p - sm.p) / (2 * h), s.v, atol=1e-5)
    assert np.allclose((sp.v - sm.v) / (2 * h), s.a, atol=1e-3)
    late = m.sample(np.array([2.0, 3.0]))
    b = base.sample(np.array([1.25, 2.25]))
    assert np.allclose(late.p, b.p) and np.allclose(late.v, b.v) and np.allclose(late.w, b.w)
    assert m.duration == pytest.approx(base.duration + 0.75) if base.duration is not None else True


def test_speed_factor_plays_the_same_route_faster(tmp_path):
    """`vings sim --speed-factor`: the same poses reached F times sooner, speeds x F, accelerations
    x F^2 (the IMU stays exact for the faster motion)."""
    a = build_scene("street", seed=3, length_m=300.0, fps=10.0)
    b = build_scene("street", seed=3, length_m=300.0, fps=10.0, speed_factor=2.5)
    t = np.linspace(0.0, 4.0, 9)
    sa, sb = a.motion.sample(2.5 * t), b.motion.sample(t)
    assert np.allclose(sb.p, sa.p) and np.allclose(sb.R, sa.R)
    assert np.allclose(sb.v, 2.5 * sa.v) and np.allclose(sb.a, 6.25 * sa.a) and np.allclose(sb.w, 2.5 * sa.w)
    with pytest.raises(ConfigError, match="speed factor"):
        generate("room", tmp_path / "c", frames=4, width=48, height=32, mcap=False, speed_factor=0.0)


def test_imu_stream_options_thin_shift_drop_and_gap_the_recorded_readings(tmp_path):
    from vings_core.sim.sequence import ImuStreamOptions
    full = generate("room", tmp_path / "full", frames=21, width=48, height=32, mcap=False)
    opts = ImuStreamOptions(rate_hz=100.0, td_s=0.015, drop=0.05, gaps=((0.4, 0.6),))
    d = generate("room", tmp_path / "thin", frames=21, width=48, height=32, mcap=False, imu=opts)
    a = np.loadtxt(full / "mav0" / "imu0" / "data.csv", delimiter=",", comments="#")
    b = np.loadtxt(d / "mav0" / "imu0" / "data.csv", delimiter=",", comments="#")
    t0 = a[0, 0]
    tb = (b[:, 0] - t0) * 1e-9 - 0.015                         # true time of each reading
    k = np.round(tb / 0.005).astype(int)
    assert np.allclose(tb, k * 0.005, atol=1e-6)                # stamped t + td (CSV floats)
    assert np.all(k % 2 == 0)                                   # 100 Hz: every other 200 Hz reading
    assert not np.any((tb >= 0.4) & (tb < 0.6))                 # the gap
    n_kept = np.sum((np.arange(len(a)) % 2 == 0) & ~(((a[:, 0] - t0) * 1e-9 >= 0.4) & ((a[:, 0] - t0) * 1e-9 < 0.6)))
    assert 0.8 * n_kept < len(b) < n_kept                       # about 5 % dropped
    assert np.allclose(b[:, 1:], a[k, 1:])                      # the same readings, only fewer
    # the ground truth keeps every 200 Hz sample on the true clock
    ga = np.loadtxt(full / "mav0" / "state_groundtruth_estimate0" / "data.csv", delimiter=",", comments="#")
    gb = np.loadtxt(d / "mav0" / "state_groundtruth_estimate0" / "data.csv", delimiter=",", comments="#")
    assert np.array_equal(ga[:, 0], gb[:, 0])
    with pytest.raises(ConfigError, match="divide"):
        generate("room", tmp_path / "bad", frames=4, width=48, height=32, mcap=False,
                 imu=ImuStreamOptions(rate_hz=70.0))
