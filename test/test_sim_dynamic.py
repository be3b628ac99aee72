"""`vings sim --scene street --dynamic`: the lead car driving ahead of the ego vehicle in its lane."""
from __future__ import annotations

import numpy as np
import pytest

from vings_core.sim import build_scene, default_camera, make_scene, render_view_full
from vings_core.sim.scene import LEAD_GAP_S


def _lead(scene):
    info = scene.info["lead_car"]
    return scene.movers[info["mover"]], np.asarray(info["size_m"]), info


def _corners_world(box, size, t) -> np.ndarray:
    """(8, 3) corners of the lead car's box at time ``t``."""
    R, p = box.pose(t)
    h = 0.5 * size
    signs = np.array([[a, b, c] for a in (-1, 1) for b in (-1, 1) for c in (-1, 1)], float)
    return p + (signs * h) @ R.T


def _check_ahead_on_the_road(scene, ts, min_depth=2.0) -> int:
    """At every time in ``ts`` the lead car stands on the road (bottom at the cars' 10 cm
    clearance), wholly in front of the camera, on the ego's own path and headed along it.
    Returns how many times were checked."""
    box, size, info = _lead(scene)
    # the ego body's path, densely, far enough to hold every point the lead is at
    path_t = np.arange(0.0, ts.max() + 6.0, 0.01)
    path = scene.motion.sample(path_t)
    path_yaw = np.arctan2(path.R[:, 1, 0], path.R[:, 0, 0])
    for t in ts:
        X = _corners_world(box, size, t)
        assert X[:, 2].min() == pytest.approx(0.1, abs=1e-9)          # bottom on the road
        assert X[:, 2].max() == pytest.approx(0.1 + size[2], abs=1e-9)
        T_wc = scene.T_wc(t)[0]
        z_cam = (X - T_wc[:3, 3]) @ T_wc[:3, 2]
        assert z_cam.min() > min_depth                               # in front of the camera
        R, c = box.pose(t)
        later = path_t > t                                           # where the ego will be
        d = np.where(later, np.linalg.norm(path.p[:, :2] - c[:2], axis=1), np.inf)
        k = int(np.argmin(d))
        assert d[k] < 0.15                                           # in the ego's lane
        yaw = np.arctan2(R[1, 0], R[0, 0])
        assert abs((yaw - path_yaw[k] + np.pi) % (2 * np.pi) - np.pi) < np.radians(1.5)
        # at least min_ahead_m (along the route) ahead of the body, a little less as the crow flies
        ego = scene.T_wb(t)[0][:2, 3]
        assert np.linalg.norm(c[:2] - ego) > 0.9 * info["min_ahead_m"]
    return len(ts)


def test_street_lead_car_is_ahead_on_the_road_and_in_the_mask():
    scene = make_scene("street", seed=1, length_m=200, dynamic=True)
    box, size, info = _lead(scene)
    assert scene.info["moving_objects"] == len(scene.movers) and info["gap_s"] == list(LEAD_GAP_S)
    ts = np.linspace(0.0, scene.motion.duration, 24)
    _check_ahead_on_the_road(scene, ts)
    cam = default_camera(96, 60)
    frac, dist = [], []
    for t in ts:
        out = render_view_full(scene, cam, scene.T_wc(t)[0], t)
        obj = scene.quads_at(t).obj
        hit = out.prim >= 0
        lead_px = np.zeros(out.mask.shape, bool)
        lead_px[hit] = obj[out.prim[hit]] == info["mover"]
        frac.append(lead_px.mean())
        dist.append(np.linalg.norm(box.pose(t)[1][:2] - scene.T_wb(t)[0][:2, 3]))
    frac = np.array(frac)
    assert np.mean(frac > 0.003) >= 0.8                  # the lead car is seen in most frames
    assert frac.max() >= 0.15                            # sometimes close: a big part of the image
    assert max(dist) > 2 * min(dist)                     # its gap varies: near and far


@pytest.mark.parametrize("kw", [dict(slow_start_s=3.0, speed_factor=2.5),
                                dict(loop=True, length_m=400.0, retrace=0.5)])
def test_lead_car_follows_the_retimed_motion(kw):
    """A slow start, a speed factor or a loop driven again: the lead car stays ahead in the lane."""
    scene = build_scene("street", seed=2, dynamic=True, fps=10.0, **{"length_m": 200.0, **kw})
    D = scene.motion.duration
    ts = np.concatenate([np.linspace(0.0, 1.0, 3), np.linspace(0.0, D, 12)])
    if "retrace" in kw:                                  # across the end of the first lap
        lap = scene.revisit["first_pass_end_s"]
        ts = np.concatenate([ts, lap + np.array([-1.0, -0.3, 0.0, 0.4])])
    assert _check_ahead_on_the_road(scene, ts) == len(ts) >= 15


def test_dynamic_street_keeps_the_static_street_and_is_deterministic():
    a = make_scene("street", seed=4, length_m=200, dynamic=False)
    b = make_scene("street", seed=4, length_m=200, dynamic=True)
    c = make_scene("street", seed=4, length_m=200, dynamic=True)
    assert not a.movers and "lead_car" not in a.info
    for f in ("origin", "u", "v", "extent", "tint", "offset", "tex", "obj"):
        assert np.array_equal(getattr(a.static, f), getattr(b.static, f))
    t = np.linspace(0.0, a.motion.duration, 9)
    assert np.array_equal(a.T_wc(t), b.T_wc(t))
    for t1 in (0.0, 7.3):
        qb, qc = b.quads_at(t1), c.quads_at(t1)
        assert np.array_equal(qb.origin, qc.origin) and np.array_equal(qb.tint, qc.tint)
