"""Map checkpoints: a mapper's whole state in one ``.npz`` (an uncompressed zip of ``.npy``
entries), restored bit-exactly, with a layout version.

Version 7 (:data:`CHECKPOINT_VERSION`, written) holds the entries

* ``meta``: JSON (``version``, ``config``, ``camera``, ``render_count``, ``kf_count``, the training
  and refinement rounds ``queue`` / ``rqueue``, the score ``slots``, ``window`` size, ``counters``);
* ``active/<field>``: the active Gaussians (:data:`~.gaussians.ALL_FIELDS`); ``rng_state``;
* ``kf/stamps`` (K,) int64 and ``kf/T_wc`` (K, 4, 4) float64 camera-to-world, in stamp order;
* ``win<i>/{stamp, index, image, T_wc, depth, inv_depth_var, valid, dynamic, loss_map}``: window
  keyframes (``dynamic``: the eraser's mask, ``(0, 0)`` when the keyframe has none);
* ``pose_adam/{stamps, m, v, steps, v_shared}`` and ``pose_gn/{stamps, steps}``: refinement state;
* ``pchunk/count`` and per passive chunk ``pchunk/<k>/<field>``, ``pchunk/<k>/owners``,
  ``pchunk/<k>/owner_T`` (owner poses when stored) and ``pchunk/<k>/owner_s`` (pending scales);
* ``hist/stamps``, ``hist/index`` and per history keyframe ``hist/<stamp>/<field>``;
  ``hist/scale_stamps`` / ``hist/scale``: depth factors pending for history keyframes.

Earlier versions are read through one migration per version, each turning a version's entries
into the next one's (:data:`MIGRATIONS`):

1. the passive Gaussians stacked (``passive/<field>``) and already moved to the keyframe poses of
   the time; history records stacked (``hist/<field>``); ``pose_adam/v_shared`` possibly missing;
2. the passive store as stored, with the owner poses it was stored under
   (``passive_chunks/{chunk, owner_chunk, owners, owner_T}``);
3. history records one entry each (``hist/<stamp>/<field>``);
4. the passive store one entry set per chunk (``pchunk/...``);
5. Gauss-Newton step counts (``pose_gn/...``);
6. pending scales (``pchunk/<k>/owner_s``, ``hist/scale_stamps``, ``hist/scale``);
7. dynamic masks (``win<i>/dynamic``, ``hist/<stamp>/dynamic``).

Files of versions 1 to 5 all say ``"version": 1`` in their meta; :func:`stored_version` tells them
apart by their entries. A file of a newer (or unknown) version is refused with an
:class:`~vings_core.errors.InputError` naming it.
"""
from __future__ import annotations

import json
import math
import os
import zipfile
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional

import numpy as np
import torch

from ..config import config_from_dict
from ..errors import InputError
from ..types import CameraModel, Keyframe
from ..util import NPZ_READ_ERRORS, atomic_write
from .config import MapperConfig
from .gaussians import ALL_FIELDS, GaussianMap
from .history import FIELDS as HISTORY_FIELDS

#: the history record fields before version 7 (no dynamic mask)
HISTORY_FIELDS_V6 = ("image", "depth", "inv_depth_var", "valid")

if TYPE_CHECKING:
    from .mapper import Mapper

CHECKPOINT_VERSION = 7

_META_KEYS = ("config", "camera", "window", "render_count", "kf_count", "queue", "rqueue", "slots",
              "counters")
_PASSIVE_CHUNK_KEYS = ("chunk", "owner_chunk", "owners", "owner_T")


# ----------------------------------------------------------------------------- writing


def save_checkpoint(m: "Mapper", path: str | os.PathLike) -> None:
    """Write mapper ``m`` to ``path`` (version :data:`CHECKPOINT_VERSION`), atomically. The
    passive store and the history are written one chunk / record at a time (a long run's spilled
    store is not gathered in memory)."""
    d = _state_entries(m)

    def _w(tmp: str) -> None:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for k, a in d.items():
                _write_npy(zf, k, a)
            # passive Gaussians chunk by chunk as stored (a spilled chunk is read only while it
            # is written), with the owner poses they were stored under and the scales still
            # pending: a pose change still pending for them is applied once, on return, exactly
            # as without the checkpoint
            count = 0
            for fields, owners, owner_T, owner_s in m.passive.stored_chunks():
                for k in ALL_FIELDS:
                    _write_npy(zf, f"pchunk/{count}/{k}", fields[k])
                _write_npy(zf, f"pchunk/{count}/owners", owners)
                _write_npy(zf, f"pchunk/{count}/owner_T", owner_T)
                _write_npy(zf, f"pchunk/{count}/owner_s", owner_s)
                count += 1
            _write_npy(zf, "pchunk/count", np.array(count, dtype=np.int64))
            saved, index = [], []
            for s, rec in m.state.history.items():
                for k in HISTORY_FIELDS:
                    _write_npy(zf, f"hist/{s}/{k}", rec[k].numpy())
                saved.append(s)
                index.append(rec["index"])
            _write_npy(zf, "hist/stamps", np.array(saved, dtype=np.int64))
            _write_npy(zf, "hist/index", np.array(index, dtype=np.int64))
            ds = sorted(m.state.depth_scale)
            _write_npy(zf, "hist/scale_stamps", np.array(ds, dtype=np.int64))
            _write_npy(zf, "hist/scale", np.array([m.state.depth_scale[s] for s in ds], dtype=np.float64))
    atomic_write(path, _w)


def _state_entries(m: "Mapper") -> dict[str, np.ndarray]:
    """Every entry but the passive store's and the history's."""
    st, ref = m.state, m.refiner
    d: dict[str, np.ndarray] = {}
    for k, v in st.gm.to_numpy().items():
        d[f"active/{k}"] = v
    d["kf/stamps"] = np.array(st.order, dtype=np.int64)
    d["kf/T_wc"] = np.stack([st.poses[s] for s in st.order]) if st.order else np.zeros((0, 4, 4))
    for i, kf in enumerate(st.window):
        d[f"win{i}/stamp"] = np.array(kf.stamp_ns, dtype=np.int64)
        d[f"win{i}/index"] = np.array(kf.index, dtype=np.int64)
        for k in ("image", "T_wc", "depth", "inv_depth_var", "valid"):
            d[f"win{i}/{k}"] = getattr(kf, k).cpu().numpy()
        d[f"win{i}/dynamic"] = (np.zeros((0, 0), bool) if kf.dynamic is None else kf.dynamic.cpu().numpy())
        d[f"win{i}/loss_map"] = (st.loss_maps[kf.stamp_ns].numpy() if kf.stamp_ns in st.loss_maps
                                 else np.zeros((0, 0), np.float32))
    meta = {"version": CHECKPOINT_VERSION, "config": asdict(st.cfg), "render_count": st.render_count,
            "kf_count": st.kf_count, "queue": m.trainer.queue, "rqueue": ref.queue, "slots": m.scores.slots,
            "window": len(st.window), "counters": st.counters,
            "camera": st.camera.to_dict() if st.camera is not None else None}
    d["meta"] = np.frombuffer(json.dumps(meta).encode(), dtype=np.uint8)
    d["rng_state"] = st.rng.get_state().numpy()
    pa = sorted(ref.adam)
    d["pose_adam/stamps"] = np.array(pa, dtype=np.int64)
    d["pose_adam/m"] = np.stack([ref.adam[s][0] for s in pa]) if pa else np.zeros((0, 6))
    d["pose_adam/v"] = np.stack([ref.adam[s][1] for s in pa]) if pa else np.zeros((0, 6))
    d["pose_adam/steps"] = np.array([ref.adam[s][2] for s in pa], dtype=np.int64)
    d["pose_adam/v_shared"] = ref.adam_v.copy()
    gs = sorted(ref.gn_steps)
    d["pose_gn/stamps"] = np.array(gs, dtype=np.int64)
    d["pose_gn/steps"] = np.array([ref.gn_steps[s] for s in gs], dtype=np.int64)
    return d


def _write_npy(zf: zipfile.ZipFile, name: str, a) -> None:
    """One ``name.npy`` entry of an ``.npz`` (what ``np.savez`` writes, and ``np.load`` reads)."""
    with zf.open(name + ".npy", "w", force_zip64=True) as f:
        np.lib.format.write_array(f, np.asanyarray(a), allow_pickle=False)


# ----------------------------------------------------------------------------- reading


def load_checkpoint(path: str | os.PathLike, config: Optional[MapperConfig], device: str,
                    make: Callable[[MapperConfig, str], "Mapper"]) -> "Mapper":
    """The mapper saved in ``path`` (any version up to :data:`CHECKPOINT_VERSION`), built by
    ``make(config, device)`` and filled in. ``config`` overrides the stored one (None = the stored
    config); it must keep the stored ``window_size`` and ``sh_degree``. A missing, damaged, foreign
    or newer file raises :class:`InputError` naming it."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: map checkpoint not found")
    try:
        npz = np.load(path, allow_pickle=False)
    except NPZ_READ_ERRORS as e:
        raise InputError(f"{path}: not a VINGS map checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(npz, np.lib.npyio.NpzFile):
        raise InputError(f"{path}: not a VINGS map checkpoint (a single .npy array, not an .npz)")
    with npz:
        z = Entries(npz, path)
        try:
            meta = json.loads(bytes(z["meta"]).decode())
        except (ValueError, UnicodeDecodeError) as e:
            raise InputError(f"{path}: not a VINGS map checkpoint (meta: {e})") from None
        if not isinstance(meta, dict):
            raise InputError(f"{path}: not a VINGS map checkpoint (meta is not a JSON object)")
        version = stored_version(meta, z, path)
        lacking = [k for k in _META_KEYS if k not in meta]
        if lacking:
            raise InputError(f"{path}: not a VINGS map checkpoint, or damaged (meta lacks {', '.join(lacking)})")
        for v in range(version, CHECKPOINT_VERSION):
            MIGRATIONS[v](z)
        cfg = config if config is not None else config_from_dict(MapperConfig, meta["config"], f"{path}: config")
        m = make(cfg, device)
        _restore(m, z, meta, path)
        return m


def stored_version(meta: dict, z: "Entries", path: Path) -> int:
    """The layout version of a checkpoint from its ``meta`` (and, for ``"version": 1``, which the
    files of versions 1 to 5 all carry, from its entries ``z``). InputError naming ``path`` for a
    version this build does not read."""
    v = meta.get("version")
    if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= CHECKPOINT_VERSION:
        raise InputError(f"{path}: checkpoint version {v!r} not supported (this build reads versions "
                         f"1 to {CHECKPOINT_VERSION}; a newer one wrote it?)")
    if v != 1:
        return v
    if "pchunk/count" in z:
        return 5 if "pose_gn/stamps" in z else 4
    if "passive_chunks/chunk" in z:
        return 2 if "hist/image" in z else 3
    return 1


def _restore(m: "Mapper", z: "Entries", meta: dict, path: Path) -> None:
    """Fill the new mapper ``m`` from the entries ``z`` of the current version."""
    st, cfg = m.state, m.state.cfg

    def _check_sh(gm: GaussianMap) -> GaussianMap:
        if gm.sh.shape[1] != (cfg.sh_degree + 1) ** 2:
            raise InputError(f"{path}: checkpoint holds SH of degree {math.isqrt(gm.sh.shape[1]) - 1}, "
                             f"the config {cfg.sh_degree}; load it with the same sh_degree")
        return gm
    st.gm = _check_sh(GaussianMap.from_numpy({k: z[f"active/{k}"] for k in ALL_FIELDS}, st.device))
    stamps = z["kf/stamps"]
    st.order = sorted(int(s) for s in stamps)
    st.poses = {int(s): np.array(T) for s, T in zip(stamps, z["kf/T_wc"])}
    st.camera = CameraModel.from_dict(meta["camera"]) if meta["camera"] else None
    _restore_window(m, z, int(meta["window"]))
    st.rng.set_state(torch.from_numpy(z["rng_state"]))
    for s, ix in zip(z["hist/stamps"].tolist(), z["hist/index"].tolist()):
        st.history.put(int(s), {**{k: torch.from_numpy(z[f"hist/{s}/{k}"]) for k in HISTORY_FIELDS}, "index": int(ix)})
    st.depth_scale = {int(s): float(k) for s, k in zip(z["hist/scale_stamps"].tolist(), z["hist/scale"].tolist())}
    ref = m.refiner
    ref.adam_v = np.array(z["pose_adam/v_shared"], dtype=np.float64)
    ref.adam = {int(s): (np.array(a), np.array(b), int(c)) for s, a, b, c in
                zip(z["pose_adam/stamps"], z["pose_adam/m"], z["pose_adam/v"], z["pose_adam/steps"])}
    ref.gn_steps = {int(s): int(c) for s, c in zip(z["pose_gn/stamps"], z["pose_gn/steps"])}
    for k in range(int(z["pchunk/count"])):    # one chunk at a time (it spills as it goes, like the saved store)
        p = f"pchunk/{k}/"
        gm = _check_sh(GaussianMap.from_numpy({f: z[p + f] for f in ALL_FIELDS}))
        owners = z[p + "owners"]
        st.passive.put(gm, {int(s): T for s, T in zip(owners, z[p + "owner_T"])},
                       {int(s): float(x) for s, x in zip(owners, z[p + "owner_s"])})
    st.render_count = int(meta["render_count"])
    st.kf_count = int(meta["kf_count"])
    m.trainer.queue = [int(s) for s in meta["queue"]]
    ref.queue = [int(s) for s in meta["rqueue"]]
    if len(meta["slots"]) != cfg.window_size or st.gm.win_c.shape[1] != cfg.window_size:
        raise InputError(f"{path}: checkpoint has a window of {len(meta['slots'])} keyframes, the config "
                         f"{cfg.window_size}; load it with the same window_size")
    m.scores.slots = [int(s) for s in meta["slots"]]
    st.counters.update(meta["counters"])


def _restore_window(m: "Mapper", z: "Entries", n: int) -> None:
    st = m.state
    for i in range(n):
        p = f"win{i}/"
        kf = Keyframe(stamp_ns=int(z[p + "stamp"]), image=torch.from_numpy(z[p + "image"]),
                      T_wc=torch.from_numpy(z[p + "T_wc"]), depth=torch.from_numpy(z[p + "depth"]),
                      inv_depth_var=torch.from_numpy(z[p + "inv_depth_var"]),
                      valid=torch.from_numpy(z[p + "valid"]), camera=st.camera, index=int(z[p + "index"]),
                      dynamic=torch.from_numpy(z[p + "dynamic"]) if z[p + "dynamic"].size else None)
        st.window.append(kf)
        lm = z[p + "loss_map"]
        if lm.size:
            st.loss_maps[kf.stamp_ns] = torch.from_numpy(lm)


class Entries:
    """An open checkpoint's entries as its layout version has them: the file's (``np.load``
    reads them lazily, so damage shows where an entry is first read; a missing or damaged one is
    an InputError naming the file) with those a migration added or dropped."""

    def __init__(self, npz, path: Path) -> None:
        self.npz, self.path = npz, path
        self._added: dict[str, np.ndarray] = {}
        self._dropped: set[str] = set()

    def __contains__(self, name: str) -> bool:
        return name in self._added or (name not in self._dropped and name in self.npz.files)

    def __getitem__(self, name: str) -> np.ndarray:
        if name in self._added:
            return self._added[name]
        try:
            if name in self._dropped:
                raise KeyError(name)
            return self.npz[name]
        except KeyError:
            raise InputError(f"{self.path}: not a VINGS map checkpoint, or damaged (lacks {name})") from None
        except NPZ_READ_ERRORS as e:
            raise InputError(f"{self.path}: not a VINGS map checkpoint, or damaged ({name}: "
                             f"{type(e).__name__}: {e})") from None

    def add(self, name: str, a: np.ndarray) -> None:
        """Entry ``name`` is ``a`` from now on (a migration's)."""
        self._added[name] = a
        self._dropped.discard(name)

    def drop(self, name: str) -> None:
        """Entry ``name`` is gone from now on (a migration's)."""
        self._added.pop(name, None)
        self._dropped.add(name)


# ----------------------------------------------------------------------------- migrations


def _v1_to_v2(z: Entries) -> None:
    """The passive Gaussians were saved moved to the keyframe poses of the time: one chunk whose
    owner snapshots are those poses (no move pending). A missing shared Adam second moment is 0."""
    if "pose_adam/v_shared" not in z:
        z.add("pose_adam/v_shared", np.zeros(7))
    poses = {int(s): T for s, T in zip(z["kf/stamps"], z["kf/T_wc"])}
    kid = z["passive/kf_id"]
    owners = np.unique(kid)
    z.add("passive_chunks/chunk", np.zeros(len(kid), np.int64))
    z.add("passive_chunks/owner_chunk", np.zeros(len(owners), np.int64))
    z.add("passive_chunks/owners", owners)
    z.add("passive_chunks/owner_T", np.stack([np.asarray(poses.get(int(s), np.eye(4)), dtype=np.float64)
                                              for s in owners]) if len(owners) else np.zeros((0, 4, 4)))


def _v2_to_v3(z: Entries) -> None:
    """History records stacked (``hist/<field>``) become one entry each (``hist/<stamp>/<field>``)."""
    stacked = {k: z[f"hist/{k}"] for k in HISTORY_FIELDS_V6}
    for j, s in enumerate(z["hist/stamps"].tolist()):
        for k in HISTORY_FIELDS_V6:
            z.add(f"hist/{s}/{k}", np.array(stacked[k][j]))
    for k in HISTORY_FIELDS_V6:
        z.drop(f"hist/{k}")


def _v3_to_v4(z: Entries) -> None:
    """The stacked passive store (``passive/<field>``, ``passive_chunks/...``) becomes one entry
    set per chunk (``pchunk/<k>/...``), in chunk order."""
    fields = {f: z[f"passive/{f}"] for f in ALL_FIELDS}
    ch = {k: z[f"passive_chunks/{k}"] for k in _PASSIVE_CHUNK_KEYS}
    ids = np.unique(ch["chunk"])
    for j, c in enumerate(ids.tolist()):
        rows = ch["chunk"] == c
        own = ch["owner_chunk"] == c
        for f in ALL_FIELDS:
            z.add(f"pchunk/{j}/{f}", fields[f][rows])
        z.add(f"pchunk/{j}/owners", ch["owners"][own])
        z.add(f"pchunk/{j}/owner_T", ch["owner_T"][own])
    z.add("pchunk/count", np.array(len(ids), dtype=np.int64))
    for name in [f"passive/{f}" for f in ALL_FIELDS] + [f"passive_chunks/{k}" for k in _PASSIVE_CHUNK_KEYS]:
        z.drop(name)


def _v4_to_v5(z: Entries) -> None:
    """No Gauss-Newton step counts (none taken)."""
    z.add("pose_gn/stamps", np.zeros(0, dtype=np.int64))
    z.add("pose_gn/steps", np.zeros(0, dtype=np.int64))


def _v5_to_v6(z: Entries) -> None:
    """No scale pending for any passive chunk's owners, nor for any history keyframe's depth."""
    for k in range(int(z["pchunk/count"])):
        z.add(f"pchunk/{k}/owner_s", np.ones(len(z[f"pchunk/{k}/owners"]), dtype=np.float64))
    z.add("hist/scale_stamps", np.zeros(0, dtype=np.int64))
    z.add("hist/scale", np.zeros(0, dtype=np.float64))


def _v6_to_v7(z: Entries) -> None:
    """No dynamic masks: window keyframes get none, history records an all-False one."""
    i = 0
    while f"win{i}/stamp" in z:
        z.add(f"win{i}/dynamic", np.zeros((0, 0), bool))
        i += 1
    for s in z["hist/stamps"].tolist():
        z.add(f"hist/{s}/dynamic", np.zeros(z[f"hist/{s}/valid"].shape, bool))


#: version -> the migration of its entries to the next version's
MIGRATIONS: dict[int, Callable[[Entries], None]] = {1: _v1_to_v2, 2: _v2_to_v3, 3: _v3_to_v4, 4: _v4_to_v5,
                                                    5: _v5_to_v6, 6: _v6_to_v7}
