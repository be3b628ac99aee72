"""Storage tiers (paper "GPU-CPU transfer"): an active set that is rendered and optimised, and a
passive store in host memory that spills to disk files when a memory budget is exceeded.

Tiering uses the pose of each Gaussian's ID(g) keyframe, not the Gaussian centres: a Gaussian is
active when its keyframe lies within ``tau`` metres of the current camera, and the nearest ones are
kept when the active set would exceed its cap.

The passive store keeps whole :class:`GaussianMap` records (parameters, scores, optimiser state) as
numpy arrays; a spilled chunk is one ``.npz`` file written atomically. Every round trip
(memory or disk) is bit-exact. Each chunk remembers the poses its owner keyframes had when it was
stored; if a keyframe pose changed meanwhile (loop closure, pose refinement) its Gaussians are moved
rigidly by the pose change when they come back (paper eq. loop correction). A similarity (scale)
correction of an owner is kept as a pending scale ``s`` per owner: on return its Gaussians move by
``T_now diag(s, s, s, 1) T_stored^-1`` (scaled about the stored camera centre, then moved rigidly).
"""
from __future__ import annotations

import contextlib
import itertools
import os
import shutil
import socket
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Optional

import numpy as np
import torch

from ..errors import ConfigError, InputError, VingsError
from ..util import NPZ_READ_ERRORS, atomic_write, log
from .gaussians import ALL_FIELDS, GaussianMap


# ----------------------------------------------------------------------------- pure tier functions


def owner_positions(kf_id: torch.Tensor, stamps: np.ndarray, positions: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-Gaussian owner keyframe position ``(N, 3)`` and a found-mask ``(N,)``.

    ``stamps`` (K,) int64 sorted ascending, ``positions`` (K, 3) float64 (camera centres, world).
    """
    n = kf_id.numel()
    if len(stamps) == 0:
        return torch.zeros(n, 3, dtype=torch.float64), torch.zeros(n, dtype=torch.bool)
    st = torch.from_numpy(np.asarray(stamps, dtype=np.int64))
    idx = torch.searchsorted(st, kf_id.cpu()).clamp_max(len(st) - 1)
    found = st[idx] == kf_id.cpu()
    pos = torch.from_numpy(np.asarray(positions, dtype=np.float64))[idx]
    return pos, found


def owner_distances(kf_id: torch.Tensor, stamps: np.ndarray, positions: np.ndarray,
                    current: np.ndarray) -> torch.Tensor:
    """Distance (m) from each Gaussian's ID(g) keyframe to ``current`` (3,); 0 for unknown owners."""
    pos, found = owner_positions(kf_id, stamps, positions)
    d = torch.linalg.norm(pos - torch.as_tensor(np.asarray(current, dtype=np.float64)), dim=-1)
    return torch.where(found, d, torch.zeros_like(d))


def active_split(dist: torch.Tensor, tau: float, max_active: int) -> torch.Tensor:
    """Bool mask of Gaussians that stay active: ``dist < tau``, at most ``max_active`` (nearest first)."""
    keep = dist < tau
    n_keep = int(keep.sum())
    if n_keep > max_active:
        d = torch.where(keep, dist, torch.full_like(dist, float("inf")))
        # stable sort: equal distances (same owner) keep their row order -> deterministic
        order = torch.sort(d, stable=True).indices[:max_active]
        keep = torch.zeros_like(keep)
        keep[order] = True
    return keep


# ----------------------------------------------------------------------------- spill folder


_OWNER_FILE = "owner"


def _process_identity(pid: int) -> Optional[str]:
    """``"host pid start"`` of a live process (start: its start time from ``/proc``, so a reused pid
    is not mistaken for the owner; empty where ``/proc`` is missing), None when it is not running."""
    try:
        with contextlib.suppress(PermissionError):     # alive, another user's process
            os.kill(pid, 0)
    except ProcessLookupError:
        return None
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            start = f.read().rsplit(b")", 1)[1].split()[19].decode()
    except (OSError, IndexError):
        start = ""
    return f"{socket.gethostname()} {pid} {start}"


def remove_stale_spill_folders(parent: Path, prefix: str) -> list[Path]:
    """Delete the ``prefix*`` spill folders in ``parent`` whose owning process (on this host) has
    ended: a mapper killed by SIGKILL or the OOM killer cannot clean up after itself. Folders
    without an owner record (being created, or another host's) are left alone. Returns the
    folders removed."""
    removed = []
    host = socket.gethostname()
    try:
        candidates = [d for d in parent.iterdir() if d.name.startswith(prefix) and d.is_dir()]
    except OSError:
        return removed
    for d in candidates:
        try:
            rec = (d / _OWNER_FILE).read_text().split()
            if len(rec) < 2 or rec[0] != host:
                continue
            alive = _process_identity(int(rec[1]))
        except (OSError, ValueError):
            continue
        if alive is not None:
            now_start, rec_start = alive.split()[2:3], rec[2:3]
            if not (now_start and rec_start and now_start != rec_start):
                continue           # the owner runs (its pid was not reused by another process)
        shutil.rmtree(d, ignore_errors=True)
        if not d.exists():
            removed.append(d)
    if removed:
        log.warning("removed %d spill folder(s) left by mappers that ended without cleaning up: %s",
                    len(removed), ", ".join(str(d) for d in removed))
    return removed


class SpillFolder:
    """A private folder for spilled ``.npz`` files: inside ``parent`` when given (created at once,
    so a bad ``mapping.spill_dir`` is reported up front), else a temporary folder made on first
    use. Stores sharing a parent never read, overwrite or delete each other's files; :meth:`close`
    deletes the folder. Each folder records its owning process, and folders of the same prefix
    whose owner has ended (killed before it could clean up) are deleted when a new one is made."""

    def __init__(self, parent: Optional[str], prefix: str):
        self.prefix = prefix
        self._dir: Optional[Path] = None
        if parent:
            try:
                Path(parent).mkdir(parents=True, exist_ok=True)
                self._dir = self._make(Path(parent))
            except OSError as e:
                raise ConfigError(f"mapping.spill_dir {parent!r}: cannot create a folder "
                                  f"there ({e.strerror or e})") from None

    def _make(self, parent: Path) -> Path:
        remove_stale_spill_folders(parent, self.prefix)
        d = Path(tempfile.mkdtemp(prefix=self.prefix, dir=parent))
        ident = _process_identity(os.getpid()) or ""
        (d / _OWNER_FILE).write_text(ident + "\n")
        return d

    def path(self, name: str) -> Path:
        if self._dir is None:
            self._dir = self._make(Path(tempfile.gettempdir()))
        return self._dir / name

    def write(self, name: str, arrays: dict) -> Path:
        """Write ``arrays`` to ``name`` atomically; returns its path. A failed write (disk full,
        folder gone) raises :class:`VingsError` naming the file and leaves no partial file."""
        try:
            path = self.path(name)
        except OSError as e:    # the private folder cannot be made (temp dir full or gone)
            raise VingsError(f"{self.prefix}*: cannot create a spill folder ({e.strerror or e})") from None

        def _w(tmp: str) -> None:
            with open(tmp, "wb") as f:
                np.savez(f, **arrays)
        atomic_write(path, _w)
        return path

    @staticmethod
    def read(path: Optional[Path], keys, what: str) -> dict:
        """The arrays ``keys`` of a spilled file; InputError naming ``what`` and the file when it
        is missing or damaged."""
        if path is None or not path.exists():
            raise InputError(f"{what} file missing: {path}")
        try:
            with np.load(path) as z:
                return {k: z[k] for k in keys}
        except NPZ_READ_ERRORS as e:
            raise InputError(f"{what} file {path} is damaged ({type(e).__name__}: {e})") from None

    def close(self) -> None:
        if self._dir is not None and self._dir.exists():
            shutil.rmtree(self._dir, ignore_errors=True)
        self._dir = None


# ----------------------------------------------------------------------------- passive store


@dataclass
class _Chunk:
    cid: int
    n: int
    nbytes: int
    owners: np.ndarray                      # unique owner stamps (int64, sorted)
    owner_T: np.ndarray                     # (U, 4, 4) owner poses when stored
    owner_s: np.ndarray                     # (U,) float64 scale still to apply on return (1: none)
    arrays: Optional[dict] = None           # None when spilled
    path: Optional[Path] = None


@dataclass
class PassiveStore:
    """Host-memory store of inactive Gaussians, spilling whole chunks to ``.npz`` files.

    ``memory_budget_bytes``: in-memory size above which the oldest chunks are written to disk;
    ``spill_dir``: folder for those files: the store spills into its own sub-folder there (None =
    a private temporary folder); :meth:`close` removes that sub-folder. A chunk file found missing
    or damaged when read is reported and its Gaussians dropped (``lost_total``); the rest of the
    map stays usable.
    """

    memory_budget_bytes: int
    spill_dir: Optional[str] = None
    chunks: list = field(default_factory=list)
    _ids: itertools.count = field(default_factory=itertools.count)
    spilled_total: int = 0                  # number of chunk writes so far
    loaded_total: int = 0                   # number of chunk reads so far
    lost_total: int = 0                     # Gaussians of chunk files found missing or corrupt

    def __post_init__(self) -> None:
        self._folder = SpillFolder(self.spill_dir, "vings_passive_")

    # ---------------------------------------------------------------- accounting
    @property
    def num_gaussians(self) -> int:
        return int(sum(c.n for c in self.chunks))

    @property
    def memory_bytes(self) -> int:
        return int(sum(c.nbytes for c in self.chunks if c.arrays is not None))

    @property
    def disk_bytes(self) -> int:
        return int(sum(c.path.stat().st_size for c in self.chunks if c.arrays is None and c.path is not None
                       and c.path.exists()))

    @property
    def num_on_disk(self) -> int:
        """Gaussians of the chunks spilled to disk."""
        return int(sum(c.n for c in self.chunks if c.arrays is None))

    @property
    def num_spilled_chunks(self) -> int:
        return int(sum(1 for c in self.chunks if c.arrays is None))

    def owners(self) -> np.ndarray:
        """All owner stamps present in the store (unique, sorted)."""
        if not self.chunks:
            return np.zeros(0, dtype=np.int64)
        return np.unique(np.concatenate([c.owners for c in self.chunks]))

    # ---------------------------------------------------------------- put / take
    def put(self, gm: GaussianMap, poses: dict[int, np.ndarray], scales: Optional[dict[int, float]] = None) -> None:
        """Store ``gm`` (moved to host memory) as one chunk; ``poses``: stamp -> T_wc of owners now;
        ``scales``: stamp -> scale still to apply to the owner's Gaussians on return (None: none;
        what :meth:`stored_chunks` gives back)."""
        if len(gm) == 0:
            return
        arrays = gm.to_numpy()
        owners = np.unique(arrays["kf_id"])
        owner_T = np.stack([np.asarray(poses.get(int(s), np.eye(4)), dtype=np.float64) for s in owners])
        owner_s = np.array([float((scales or {}).get(int(s), 1.0)) for s in owners], dtype=np.float64)
        nbytes = int(sum(a.nbytes for a in arrays.values()))
        self.chunks.append(_Chunk(next(self._ids), len(gm), nbytes, owners, owner_T, owner_s, arrays))
        self._spill_if_needed()

    def take(self, want_owner: Callable[[np.ndarray], np.ndarray], poses: dict[int, np.ndarray],
             remove: bool = True) -> Optional[GaussianMap]:
        """Gaussians whose owner stamp satisfies ``want_owner(stamps) -> bool mask``.

        They are returned (moved by the owner pose change since they were stored) and, if ``remove``,
        deleted from the store; the chunk remainder stays. None when nothing matches.
        """
        out = []
        kept = []
        lost = False
        for c in self.chunks:
            sel_owner = np.asarray(want_owner(c.owners), dtype=bool)
            if not sel_owner.any():
                kept.append(c)
                continue
            arrays = self._read(c)
            if arrays is None:
                lost = True
                continue
            rows = np.isin(arrays["kf_id"], c.owners[sel_owner])
            part = {k: v[rows] for k, v in arrays.items()}
            gm = GaussianMap.from_numpy(part)
            _apply_pose_changes(gm, c.owners, c.owner_T, c.owner_s, poses)
            out.append(gm)
            if remove:
                if c.path is not None and c.path.exists():
                    c.path.unlink()
                rest = ~rows
                if rest.any():
                    ra = {k: v[rest] for k, v in arrays.items()}
                    o = np.unique(ra["kf_id"])
                    keep = np.searchsorted(c.owners, o)
                    kept.append(_Chunk(next(self._ids), int(rest.sum()), int(sum(a.nbytes for a in ra.values())),
                                       o, c.owner_T[keep], c.owner_s[keep], ra))
            else:
                kept.append(c)
        if remove or lost:       # kept: every chunk but the lost ones (and, if remove, the taken rows)
            self.chunks = kept
        if remove:
            self._spill_if_needed()
        if not out:
            return None
        return GaussianMap.concat(out)

    def all(self, poses: dict[int, np.ndarray]) -> Optional[GaussianMap]:
        """Every stored Gaussian (copies, moved by pose changes), the store unchanged."""
        parts = list(self.iter_moved(poses))
        return GaussianMap.concat(parts) if parts else None

    def stored_chunks(self) -> Iterator[tuple[dict, np.ndarray, np.ndarray, np.ndarray]]:
        """The store as stored, one chunk at a time (a spilled chunk is read only while it is
        yielded), for a lossless checkpoint: ``(fields, owners, owner_T, owner_s)`` with the
        Gaussians' fields ``{name: rows}`` *not* moved by pose changes since they were stored and,
        per owner stamp, the pose it was stored under and the scale still pending. Saving the moved
        Gaussians instead would round a later pose change differently (two float32 moves instead of
        one). Chunks whose file is lost are reported and dropped. Restore with :meth:`put`
        ``(GaussianMap.from_numpy(fields), dict(zip(owners, owner_T)), dict(zip(owners, owner_s)))``
        in the same order."""
        for c in list(self.chunks):
            arrays = self._read(c)
            if arrays is None:
                self.chunks.remove(c)
                continue
            yield arrays, c.owners, c.owner_T, c.owner_s

    def iter_moved(self, poses: dict[int, np.ndarray]) -> Iterator[GaussianMap]:
        """Every stored Gaussian, one chunk at a time (copies moved by pose changes since they were
        stored; the store unchanged): for writing a large map without gathering it in memory."""
        for arrays, owners, owner_T, owner_s in self.stored_chunks():
            gm = GaussianMap.from_numpy({k: v.copy() for k, v in arrays.items()})
            _apply_pose_changes(gm, owners, owner_T, owner_s, poses)
            yield gm

    def resnapshot(self, changes: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
        """Owner pose changes that must not move the stored Gaussians: ``changes`` maps stamp ->
        ``(T_old, T_new)`` (``T_wc``). A snapshot ``S`` becomes ``S T_old^-1 T_new`` (``T_new``
        itself when ``S`` is ``T_old``), so the move applied when they come back (``T_now S^-1``)
        stays the one still pending from earlier moving changes, if any, and gains nothing. With a
        pending scale ``s`` (``Z = diag(s, s, s, 1)``) it becomes ``S Z^-1 T_old^-1 T_new Z``, which
        keeps ``T_now Z S^-1`` the same."""
        for c in self.chunks:
            for i, s in enumerate(c.owners):
                if int(s) in changes:
                    T_old, T_new = changes[int(s)]
                    S, k = c.owner_T[i], float(c.owner_s[i])
                    if k != 1.0:
                        Z = np.diag([k, k, k, 1.0])
                        c.owner_T[i] = S @ np.linalg.inv(Z) @ np.linalg.inv(T_old) @ T_new @ Z
                    else:
                        c.owner_T[i] = T_new if np.array_equal(S, T_old) else S @ np.linalg.inv(T_old) @ T_new

    def rescale(self, scales: dict[int, float]) -> None:
        """Owners whose Gaussians are to be scaled by ``scales[stamp]`` about their keyframe's
        camera centre (a similarity correction ``C`` of the keyframe: the new pose is
        :func:`~vings_core.geometry.sim3_apply_to_pose` ``(C, T_old)``, so ``C = T_new diag(s, s, s, 1) T_old^-1``).
        The scale is applied when they come back, with the pose change; the snapshots stay."""
        for c in self.chunks:
            for i, s in enumerate(c.owners):
                if int(s) in scales:
                    c.owner_s[i] = c.owner_s[i] * float(scales[int(s)])

    def clear(self) -> None:
        for c in self.chunks:
            if c.path is not None and c.path.exists():
                c.path.unlink()
        self.chunks = []

    def close(self) -> None:
        """Delete spill files (and the private spill folder)."""
        self.clear()
        self._folder.close()

    # ---------------------------------------------------------------- spill / load
    def _spill_if_needed(self) -> None:
        for c in self.chunks:
            if self.memory_bytes <= self.memory_budget_bytes:
                break
            if c.arrays is None:
                continue
            try:
                c.path = self._folder.write(f"chunk_{c.cid:08d}.npz", c.arrays)
            except VingsError as e:     # disk full, folder gone: the chunk stays in memory
                log.warning("passive Gaussians: cannot spill to disk (%s); kept in memory over "
                            "passive_memory_mb", e)
                return
            c.arrays = None
            self.spilled_total += 1

    def _read(self, c: _Chunk) -> Optional[dict]:
        """The chunk's arrays; None (reported, counted in ``lost_total``) when its file is gone or
        damaged: the caller drops the chunk and keeps the rest of the map."""
        try:
            return self._load(c)
        except InputError as e:
            log.error("%s: %d passive Gaussians lost", e, c.n)
            self.lost_total += c.n
            return None

    def _load(self, c: _Chunk) -> dict:
        if c.arrays is not None:
            return c.arrays
        arrays = SpillFolder.read(c.path, ALL_FIELDS, "passive Gaussian chunk")
        self.loaded_total += 1
        return arrays

    def __del__(self) -> None:  # best effort: private temp folders do not outlive the store
        try:
            self.close()
        except Exception:
            pass


def _apply_pose_changes(gm: GaussianMap, owners: np.ndarray, owner_T: np.ndarray, owner_s: np.ndarray,
                        poses: dict[int, np.ndarray]) -> None:
    """Move ``gm``'s Gaussians by ``T_now diag(s, s, s, 1) T_stored^-1`` of their owner where the
    pose changed or a scale ``s`` (``owner_s``) is pending."""
    if not poses or len(gm) == 0:
        return
    now = np.stack([np.asarray(poses.get(int(s), owner_T[i]), dtype=np.float64) for i, s in enumerate(owners)])
    scaled = owner_s != 1.0
    changed = np.any(now != owner_T, axis=(1, 2)) | scaled
    if not changed.any():
        return
    delta = now @ np.linalg.inv(owner_T)
    if scaled.any():
        Z = np.zeros((int(scaled.sum()), 4, 4))
        Z[:, [0, 1, 2], [0, 1, 2]] = owner_s[scaled, None]
        Z[:, 3, 3] = 1.0
        delta[scaled] = now[scaled] @ Z @ np.linalg.inv(owner_T[scaled])
    idx = np.searchsorted(owners, gm.kf_id.numpy())
    rows = torch.from_numpy(changed[idx])
    moves = torch.from_numpy(delta[idx][changed[idx]])
    if scaled.any():
        gm.apply_similarity(moves, rows, torch.from_numpy(owner_s[idx][changed[idx]]))
    else:
        gm.apply_rigid(moves, rows)


def spill_dir_size(path: str | os.PathLike) -> int:
    p = Path(path)
    return int(sum(f.stat().st_size for f in p.glob("*.npz"))) if p.exists() else 0
