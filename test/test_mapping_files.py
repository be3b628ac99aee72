"""Map files and spill folders: numpy-typed inputs, foreign PLY headers, stale spill folders left by a
killed mapper, and checkpoint / map.ply writing without gathering the passive store in memory."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tracemalloc
import zipfile

import numpy as np
import pytest
import torch

from vings_core.errors import InputError
from vings_core.mapping import GaussianMap, Mapper, MapperConfig, read_ply
from vings_core.types import CameraModel, Keyframe


def _random_map(n: int, seed: int = 0, owners=(1, 2, 3)) -> GaussianMap:
    g = torch.Generator().manual_seed(seed)
    return GaussianMap.create(torch.randn(n, 3, generator=g), torch.randn(n, 4, generator=g),
                              torch.randn(n, 2, generator=g) - 3, torch.randn(n, generator=g),
                              torch.randn(n, 1, 3, generator=g),
                              torch.tensor(owners)[torch.randint(len(owners), (n,), generator=g)])


def _flat_keyframe(stamp, cam: CameraModel) -> Keyframe:
    H, W = cam.height, cam.width
    d = torch.full((H, W), 2.0)
    img = torch.rand((H, W, 3), generator=torch.Generator().manual_seed(0))
    return Keyframe(stamp_ns=stamp, image=img, T_wc=torch.eye(4, dtype=torch.float64), depth=d,
                    inv_depth_var=torch.zeros_like(d), valid=d > 0, camera=cam)


def _assert_maps_equal(a: GaussianMap, b: GaussianMap) -> None:
    da, db = a.to_numpy(), b.to_numpy()
    assert da.keys() == db.keys()
    for k in da:
        assert np.array_equal(da[k], db[k]), k


def test_numpy_typed_stamps_and_intrinsics_checkpoint(tmp_path):
    # a stamp taken from a stamps array (np.int64) and intrinsics from a float32 K matrix: mapping
    # worked, but the checkpoint failed with "Object of type int64 is not JSON serializable"
    K = np.array([[30.0, 0, 15.5], [0, 30.0, 11.5], [0, 0, 1]], dtype=np.float32)
    cam = CameraModel(width=np.int64(32), height=np.int64(24), fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2])
    assert all(type(getattr(cam, k)) is float for k in ("fx", "fy", "cx", "cy"))
    assert type(cam.width) is int and type(cam.height) is int
    kf = _flat_keyframe(np.int64(1_000_000_000), cam)
    assert type(kf.stamp_ns) is int
    m = Mapper(MapperConfig(points_per_keyframe=200, iters_per_keyframe=2, sample_ratio=1.0))
    m.add_keyframe(kf)
    m.train()
    m.save_checkpoint(tmp_path / "c.npz")
    m2 = Mapper.load_checkpoint(tmp_path / "c.npz")
    assert m2.camera == cam and list(m2.keyframe_poses()) == [1_000_000_000]
    _assert_maps_equal(m.gm, m2.gm)
    with pytest.raises(ValueError, match="Keyframe.stamp_ns must be an integer"):
        _flat_keyframe(1.0e9, cam)        # a float nanosecond stamp has lost precision already
    m.close()
    m2.close()


def _ply(path, header_lines, body: bytes) -> None:
    head = "\n".join(["ply", "format binary_little_endian 1.0", *header_lines, "end_header"]) + "\n"
    path.write_bytes(head.encode() + body)


def test_read_ply_skips_elements_before_vertex(tmp_path):
    # compressed splat files put an element (e.g. 'chunk') before 'vertex': its bytes were returned
    # as the vertices
    chunk = np.array([100, 101, 102, 103], "<f4").tobytes()           # 2 chunks x (a, b)
    verts = np.array([(1, 2), (4, 5)], dtype=[("x", "<f4"), ("y", "<u2")]).tobytes()
    p = tmp_path / "c.ply"
    _ply(p, ["element chunk 2", "property float a", "property float b",
             "element vertex 2", "property float x", "property ushort y"], chunk + verts)
    d = read_ply(p)
    assert d["x"].tolist() == [1.0, 4.0] and d["y"].tolist() == [2, 5]


@pytest.mark.parametrize("lines", [
    ["element vertex abc", "property float x"],
    ["element vertex", "property float x"],
    ["element vertex -1", "property float x"],
    ["element vertex 2", "property float"],
    ["element vertex 2", "property list uchar int vertex_indices"],
    ["property float x", "element vertex 1"],
    ["element vertex 1", "property float x", "property float x"],
])
def test_read_ply_malformed_header_is_an_input_error(tmp_path, lines):
    p = tmp_path / "bad.ply"
    _ply(p, lines, b"\0" * 64)
    with pytest.raises(InputError, match="bad.ply"):
        read_ply(p)


def test_stale_spill_folders_of_a_killed_mapper_are_removed(tmp_path):
    spill = tmp_path / "spill"
    child = (
        "import os, sys, torch\n"
        "from vings_core.mapping import GaussianMap, Mapper, MapperConfig\n"
        "m = Mapper(MapperConfig(passive_memory_mb=0.0, spill_dir=sys.argv[1]))\n"
        "g = torch.Generator().manual_seed(0)\n"
        "m.passive.put(GaussianMap.create(torch.randn(50, 3, generator=g), torch.randn(50, 4, generator=g),\n"
        "    torch.randn(50, 2, generator=g), torch.randn(50, generator=g), torch.randn(50, 1, 3, generator=g),\n"
        "    torch.ones(50, dtype=torch.int64)), {})\n"
        "assert m.passive.num_spilled_chunks == 1\n"
        "os.kill(os.getpid(), 9)\n")
    r = subprocess.run([sys.executable, "-c", child, str(spill)], capture_output=True, text=True, timeout=120)
    assert r.returncode == -9, r.stderr
    left = sorted(d.name for d in spill.iterdir())
    assert any(n.startswith("vings_passive_") for n in left) and any(n.startswith("vings_history_") for n in left)
    # a folder without an owner record (another host's, or one being created) is left alone
    (spill / "vings_passive_foreign").mkdir()
    m = Mapper(MapperConfig(passive_memory_mb=0.0, spill_dir=str(spill)))
    now = sorted(d.name for d in spill.iterdir())
    assert not set(left) & set(now), now                         # the killed mapper's folders are gone
    assert "vings_passive_foreign" in now
    mine = [n for n in now if n != "vings_passive_foreign"]
    assert len(mine) == 2                                         # the live mapper's own folders
    # a live owner's folders are never removed
    from vings_core.mapping.storage import remove_stale_spill_folders
    assert remove_stale_spill_folders(spill, "vings_passive_") == []
    assert sorted(d.name for d in spill.iterdir()) == now
    m.close()
    assert sorted(d.name for d in spill.iterdir()) == ["vings_passive_foreign"]


def _spilled_mapper(tmp_path, chunks: int = 8, n: int = 10_000) -> Mapper:
    """A mapper whose passive store (``chunks`` x ``n`` random Gaussians) is spilled to disk."""
    m = Mapper(MapperConfig(passive_memory_mb=0.0, spill_dir=str(tmp_path / "spill")))
    for k in range(chunks):
        m.passive.put(_random_map(n, seed=k, owners=(k + 1,)), {})
    assert m.passive.memory_bytes == 0 and m.passive.num_spilled_chunks == chunks
    return m


def _peak_mb(f) -> float:
    tracemalloc.start()
    try:
        f()
        return tracemalloc.get_traced_memory()[1] / 2**20
    finally:
        tracemalloc.stop()


def test_checkpoint_and_ply_do_not_gather_the_spilled_passive_store(tmp_path):
    m = _spilled_mapper(tmp_path, chunks=24, n=4000)
    passive_mb = m.passive.disk_bytes / 2**20                     # ~22 MiB of spilled chunks
    assert passive_mb > 15
    # the old code concatenated the whole store (about 2x its size) for each of these; now a few
    # copies of one chunk (~0.9 MiB) at a time
    assert _peak_mb(lambda: m.save_checkpoint(tmp_path / "c.npz")) < 0.4 * passive_mb
    assert _peak_mb(lambda: m.save_ply(tmp_path / "m.ply")) < 0.4 * passive_mb
    box = {}
    assert _peak_mb(lambda: box.setdefault("m", Mapper.load_checkpoint(tmp_path / "c.npz"))) < 0.4 * passive_mb
    m2 = box["m"]
    assert m2.num_passive == m.num_passive and m2.passive.memory_bytes < 2**20
    _assert_maps_equal(m.all_gaussians(), m2.all_gaussians())
    ply = read_ply(tmp_path / "m.ply")
    assert len(ply["x"]) == m.num_gaussians
    assert np.array_equal(ply["x"], m.all_gaussians().means[:, 0].numpy())
    m.close()
    m2.close()


def test_older_stacked_checkpoint_layout_still_loads(tmp_path):
    # checkpoint version 3 holds the passive store in stacked arrays (passive/<field> +
    # passive_chunks/{chunk, owner_chunk, owners, owner_T}) and says "version": 1
    m = _spilled_mapper(tmp_path, chunks=3, n=500)
    m.save_checkpoint(tmp_path / "new.npz")
    with np.load(tmp_path / "new.npz") as z:
        entries = {k: z[k] for k in z.files if not k.endswith("/owner_s") and not k.startswith("pose_gn/")}
    meta = json.loads(bytes(entries["meta"]).decode())
    entries["meta"] = np.frombuffer(json.dumps({**meta, "version": 1}).encode(), dtype=np.uint8)
    count = int(entries.pop("pchunk/count"))
    parts = [{k.split("/", 2)[2]: entries.pop(k) for k in list(entries) if k.startswith(f"pchunk/{c}/")}
             for c in range(count)]
    fields = [k for k in parts[0] if k not in ("owners", "owner_T")]
    for f in fields:
        entries[f"passive/{f}"] = np.concatenate([p[f] for p in parts])
    entries["passive_chunks/chunk"] = np.concatenate([np.full(len(p["kf_id"]), c) for c, p in enumerate(parts)])
    entries["passive_chunks/owner_chunk"] = np.concatenate([np.full(len(p["owners"]), c) for c, p in enumerate(parts)])
    entries["passive_chunks/owners"] = np.concatenate([p["owners"] for p in parts])
    entries["passive_chunks/owner_T"] = np.concatenate([p["owner_T"] for p in parts])
    with zipfile.ZipFile(tmp_path / "old.npz", "w") as zf:
        for k, a in entries.items():
            with zf.open(k + ".npy", "w") as f:
                np.lib.format.write_array(f, a)
    m2 = Mapper.load_checkpoint(tmp_path / "old.npz")
    assert len(m2.passive.chunks) == len(m.passive.chunks)
    _assert_maps_equal(m.all_gaussians(), m2.all_gaussians())
    m.close()
    m2.close()


def test_point_sample_matches_the_gathered_map_without_gathering_it(tmp_path):
    # the mapper node's point-cloud preview: the same evenly spread rows as indexing all_gaussians()
    m = _spilled_mapper(tmp_path, chunks=6, n=3000)
    m.gm = _random_map(2000, seed=99, owners=(50,))
    allg = m.all_gaussians()
    n = len(allg)
    for k in (0, 1, 7, 5000, n, n + 10):
        xyz, rgb = m.point_sample(k)
        idx = np.linspace(0, n - 1, min(n, k)).round().astype(int) if k > 0 else np.zeros(0, int)
        assert np.array_equal(xyz, allg.means[idx].numpy())
        ref = np.clip(allg.sh[idx, 0, :].numpy() * 0.28209479177387814 + 0.5, 0, 1)
        assert np.allclose(rgb, ref, atol=1e-7) and xyz.dtype == np.float32 and rgb.shape == xyz.shape
    m.close()
    big = _spilled_mapper(tmp_path / "big", chunks=24, n=4000)        # ~22 MiB spilled
    assert _peak_mb(lambda: big.point_sample(5000)) < 0.4 * big.passive.disk_bytes / 2**20
    big.close()
