"""Map checkpoint versions: files of every earlier layout, written the way the code of that version
wrote them, load through their migrations to the same mapper; a newer or unknown version is one
InputError naming the file."""
from __future__ import annotations

import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
import torch

from vings_core.errors import InputError
from vings_core.geometry import np_se3_exp
from vings_core.mapping import GaussianMap, Mapper, MapperConfig
from vings_core.mapping.checkpoint import CHECKPOINT_VERSION, MIGRATIONS, Entries, stored_version
from vings_core.mapping.gaussians import ALL_FIELDS
from vings_core.types import CameraModel, Keyframe

CAM = CameraModel(width=32, height=24, fx=30.0, fy=30.0, cx=15.5, cy=11.5)
STAMPS = (1_000, 2_000, 3_000)
HIST_FIELDS = ("image", "depth", "inv_depth_var", "valid")


def _random_map(n: int, seed: int, owners) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    gm = GaussianMap.create(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g),
                            torch.randn(n, 2, generator=g) - 3, torch.randn(n, generator=g),
                            torch.randn(n, 1, 3, generator=g),
                            torch.tensor(owners)[torch.randint(len(owners), (n,), generator=g)], window=2)
    gm.m_means.copy_(torch.randn(n, 3, generator=g))
    return gm


def _keyframe(stamp: int, x: float) -> Keyframe:
    g = torch.Generator().manual_seed(stamp)
    d = 2.0 + 0.1 * torch.rand((CAM.height, CAM.width), generator=g)
    T = np.eye(4)
    T[0, 3] = x
    return Keyframe(stamp_ns=stamp, image=torch.rand((CAM.height, CAM.width, 3), generator=g), T_wc=torch.from_numpy(T),
                    depth=d, inv_depth_var=torch.zeros_like(d), valid=d > 0, camera=CAM)


def _mapper(tmp_path: Path) -> Mapper:
    """Window, history (one keyframe left the window), Adam refinement state, Gauss-Newton step
    counts, and two passive chunks with a pose change still pending for them."""
    m = Mapper(MapperConfig(points_per_keyframe=200, iters_per_keyframe=3, sample_ratio=1.0, window_size=2,
                            history_ratio=0.5, refine_solver="adam", spill_dir=str(tmp_path / "spill")))
    for i, s in enumerate(STAMPS):
        m.add_keyframe(_keyframe(s, 0.05 * i))
        m.train()
    m.refine_poses(3, mode="multi")
    m.refiner.gn_steps = {2_000: 2, 3_000: 1}
    m.passive.put(_random_map(300, 0, (1_000, 2_000)), m.state.poses)
    m.passive.put(_random_map(200, 1, (2_000,)), m.state.poses)
    m.set_keyframe_poses({1_000: m.keyframe_poses()[1_000] @ np_se3_exp(np.array([0.01, 0, 0, 0, 0.02, 0]))})
    assert len(m.state.history) == 1 and m.refiner.adam and len(m.passive.chunks) == 2
    return m


def _write_old(m: Mapper, path: Path, version: int, v_shared: bool = True) -> None:
    """``m`` saved as the code of checkpoint ``version`` (1 to 6) saved it; 1 to 5 all say
    "version": 1."""
    cur = path.with_name("current.npz")
    m.save_checkpoint(cur)
    with np.load(cur) as z:
        e = {k: z[k] for k in z.files if not k.endswith("/dynamic")}        # dynamic masks: version 7
    if version <= 5:                     # pending scales: version 6
        e = {k: a for k, a in e.items() if not k.endswith("/owner_s")}
        for k in ("hist/scale_stamps", "hist/scale"):
            e.pop(k, None)
    e["meta"] = np.frombuffer(json.dumps({**json.loads(bytes(e["meta"]).decode()),
                                          "version": 1 if version <= 5 else version}).encode(), np.uint8)
    if version <= 4:                     # Gauss-Newton step counts: version 5
        del e["pose_gn/stamps"], e["pose_gn/steps"]
    if version <= 3:                     # one entry set per passive chunk: version 4
        parts = [{f: e.pop(f"pchunk/{c}/{f}") for f in ALL_FIELDS + ("owners", "owner_T")}
                 for c in range(int(e.pop("pchunk/count")))]
        for f in ALL_FIELDS:
            e[f"passive/{f}"] = np.concatenate([p[f] for p in parts])
        e["passive_chunks/chunk"] = np.concatenate([np.full(len(p["kf_id"]), c, np.int64) for c, p in enumerate(parts)])
        e["passive_chunks/owner_chunk"] = np.concatenate([np.full(len(p["owners"]), c, np.int64)
                                                          for c, p in enumerate(parts)])
        e["passive_chunks/owners"] = np.concatenate([p["owners"] for p in parts])
        e["passive_chunks/owner_T"] = np.concatenate([p["owner_T"] for p in parts])
    if version <= 2:                     # one entry per history record: version 3
        hs = e["hist/stamps"].tolist()
        for f in HIST_FIELDS:
            e[f"hist/{f}"] = np.stack([e.pop(f"hist/{s}/{f}") for s in hs]) if hs else np.zeros((0,))
    if version == 1:                     # passive Gaussians as stored, with owner snapshots: version 2
        for k in [k for k in e if k.startswith("passive")]:
            del e[k]
        for f, a in m.passive.all(m.state.poses).to_numpy().items():     # moved to the poses of the time
            e[f"passive/{f}"] = a
        if not v_shared:
            del e["pose_adam/v_shared"]
    if version <= 2:
        np.savez(path, **e)
    else:
        with zipfile.ZipFile(path, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for k, a in e.items():
                with zf.open(k + ".npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, a, allow_pickle=False)


def _assert_maps_equal(a: GaussianMap, b: GaussianMap) -> None:
    for k, t in a.tensors().items():
        assert t.dtype == getattr(b, k).dtype and torch.equal(t, getattr(b, k)), k


def _assert_same_mapper(m: Mapper, m2: Mapper, gn_steps: dict, v_shared: np.ndarray) -> None:
    _assert_maps_equal(m.gm, m2.gm)
    _assert_maps_equal(m.all_gaussians(), m2.all_gaussians())
    assert m.keyframe_poses().keys() == m2.keyframe_poses().keys()
    assert all(np.array_equal(T, m2.keyframe_poses()[s]) for s, T in m.keyframe_poses().items())
    assert [k.stamp_ns for k in m.window] == [k.stamp_ns for k in m2.window]
    assert m.state.history.stamps() == m2.state.history.stamps()
    for s in m.state.history.stamps():
        r1, r2 = m.state.history.get(s), m2.state.history.get(s)
        assert r1["index"] == r2["index"] and all(torch.equal(r1[k], r2[k]) for k in HIST_FIELDS)
    assert (m2.render_count, m2.kf_count, m2.counters) == (m.render_count, m.kf_count, m.counters)
    assert m2.scores.slots == m.scores.slots and m2.trainer.queue == m.trainer.queue
    assert m2.refiner.queue == m.refiner.queue and m2.refiner.gn_steps == gn_steps
    assert np.array_equal(m2.refiner.adam_v, v_shared)
    assert m2.refiner.adam.keys() == m.refiner.adam.keys()
    for s, (a, b, c) in m.refiner.adam.items():
        a2, b2, c2 = m2.refiner.adam[s]
        assert np.array_equal(a, a2) and np.array_equal(b, b2) and c == c2
    assert torch.equal(m.rng.get_state(), m2.rng.get_state())


@pytest.mark.parametrize("version,v_shared", [(1, False), (1, True), (2, True), (3, True), (4, True), (5, True),
                                              (6, True)])
def test_each_earlier_version_loads_through_its_migrations(tmp_path, version, v_shared):
    m = _mapper(tmp_path)
    path = tmp_path / f"v{version}.npz"
    _write_old(m, path, version, v_shared)
    with np.load(path) as npz:
        assert json.loads(bytes(npz["meta"]).decode())["version"] == (1 if version <= 5 else version)
        meta = json.loads(bytes(npz["meta"]).decode())
        assert stored_version(meta, Entries(npz, path), path) == version
    m2 = Mapper.load_checkpoint(path)
    _assert_same_mapper(m, m2, gn_steps=m.refiner.gn_steps if version >= 5 else {},
                        v_shared=m.refiner.adam_v if v_shared else np.zeros(7))
    # resumed training follows the same path
    m.train(2)
    m2.train(2)
    _assert_maps_equal(m.gm, m2.gm)
    # saved again, it is a current checkpoint
    m2.save_checkpoint(tmp_path / "again.npz")
    with np.load(tmp_path / "again.npz") as z:
        assert json.loads(bytes(z["meta"]).decode())["version"] == CHECKPOINT_VERSION
    m.close()
    m2.close()


def test_every_earlier_version_has_a_migration():
    assert sorted(MIGRATIONS) == list(range(1, CHECKPOINT_VERSION))


@pytest.mark.parametrize("version", [CHECKPOINT_VERSION + 1, 0, "6", True, None, 1.5])
def test_a_newer_or_unknown_version_is_one_input_error_naming_the_file(tmp_path, version):
    m = Mapper(MapperConfig(points_per_keyframe=100, iters_per_keyframe=1))
    m.add_keyframe(_keyframe(1_000, 0.0))
    m.save_checkpoint(tmp_path / "good.npz")
    with np.load(tmp_path / "good.npz") as z:
        e = {k: z[k] for k in z.files}
    meta = json.loads(bytes(e["meta"]).decode())
    if version is None:
        del meta["version"]
    else:
        meta["version"] = version
    e["meta"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tmp_path / "future.npz", **e)
    with pytest.raises(InputError, match=r"future\.npz: checkpoint version .* not supported") as err:
        Mapper.load_checkpoint(tmp_path / "future.npz")
    assert "\n" not in str(err.value)
    assert len(Mapper.load_checkpoint(tmp_path / "good.npz").gm) == len(m.gm)
