"""Heavy mapping cases at the working resolution (``make test-slow``)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from vings_core.mapping import Mapper, MapperConfig, read_ply
from vings_core.types import Keyframe

pytestmark = pytest.mark.slow


def _sequence(scene_name: str, n: int, every: int, **kw):
    sim = pytest.importorskip("vings_core.sim")
    scene = sim.build_scene(scene_name, **kw)
    cam = sim.default_camera(376, 240)
    t = np.arange(n) / 20.0
    Ts = scene.T_wc(t)
    views = {i: sim.render_view(scene, cam, Ts[i])[:2] for i in range(n)}

    def kf(i):
        rgb, d = views[i]
        dd = torch.from_numpy(d)
        return Keyframe(stamp_ns=1_000_000_000 + i * 50_000_000, image=torch.from_numpy(rgb.astype(np.float32) / 255),
                        T_wc=torch.from_numpy(Ts[i]), depth=dd, inv_depth_var=torch.zeros_like(dd), valid=dd > 0,
                        camera=cam, index=i)
    return cam, Ts, views, kf


def _psnr(a, b):
    return float(-10 * np.log10(((a - b) ** 2).mean()))


def test_room_mapping_quality_at_working_resolution(tmp_path):
    cam, Ts, views, kf = _sequence("room", 31, 5)
    m = Mapper(MapperConfig(iters_per_keyframe=30))
    kfs = list(range(0, 31, 5))
    for i in kfs:
        m.add_keyframe(kf(i))
        m.train()
    pk = np.mean([_psnr(m.render(Ts[i], cam)["color"], views[i][0] / 255.0) for i in kfs])
    pn = np.mean([_psnr(m.render(Ts[i], cam)["color"], views[i][0] / 255.0) for i in (2, 12, 22, 27)])
    assert pk > 28.0 and pn > 25.0, (pk, pn)
    # rendered depth matches the ground truth where the map is opaque
    r = m.render(Ts[10], cam)
    d = views[10][1]
    ok = (r["alpha"] > 0.95) & (d > 0)
    assert np.median(np.abs(r["depth"][ok] - d[ok]) / d[ok]) < 0.02
    m.save_ply(tmp_path / "map.ply")
    assert len(read_ply(tmp_path / "map.ply")["x"]) == m.num_gaussians


def test_street_tiers_round_trip_through_disk(tmp_path):
    cam, Ts, views, kf = _sequence("street", 120, 4, loop=False, length_m=120.0)
    cfg = MapperConfig(iters_per_keyframe=3, outdoor=True, tau=15.0, max_active=30000, delta_k=2,
                       passive_memory_mb=1.0, spill_dir=str(tmp_path / "spill"), points_per_keyframe=6000)
    m = Mapper(cfg)
    for i in range(0, 120, 4):
        m.add_keyframe(kf(i))
        m.train()
        assert m.num_active <= cfg.max_active
    assert m.num_passive > 0 and m.passive.spilled_total > 0
    first = m.render(Ts[0], cam)
    before = m.num_gaussians
    m.update_tiers(Ts[0])
    assert m.num_gaussians == before and m.passive.loaded_total > 0
    again = m.render(Ts[0], cam)
    gt = views[0][0] / 255.0
    assert abs(_psnr(first["color"], gt) - _psnr(again["color"], gt)) < 1.0
    m.close()
