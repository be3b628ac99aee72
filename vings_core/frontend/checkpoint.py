"""The front end's checkpoint: everything it needs to go on tracking after a restart.

A restarted front end (a respawned ``frontend_node``) loads the checkpoint it wrote last and goes on
from there: the keyframe window (images, depths, poses, flows), the pose of every processed frame,
the map segment, the motion model and, with the IMU fused, the smoother's states. What to do with the
gap between the checkpoint and the first new image is :func:`restart_policy`'s decision
(:class:`RestartMode`).

File format: a pickle (protocol 5) of a dict: ``format`` (:data:`FORMAT`), ``version``
(:data:`VERSION`), ``camera`` (the working camera, :meth:`CameraModel.to_dict`), ``last_stamp_ns``
(the last frame processed), ``written_unix_s``, ``extra`` (the caller's plain data, e.g. a node's
raw camera) and ``state``: the pickled objects (the
:class:`~vings_core.frontend.Frontend` and whatever the caller adds, e.g. its pose keeper, pickled
together so shared references stay shared). The flow estimators are not stored (OpenCV objects):
the loading front end's are put in their place. Only load checkpoints you wrote: unpickling runs
code named in the file.
"""
from __future__ import annotations

import enum
import io
import os
import pickle
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Optional

from ..errors import InputError
from ..util import atomic_write_bytes
from .config import FrontendConfig
from .flow import FlowEstimator

if TYPE_CHECKING:                       # pragma: no cover
    from .tracker import Frontend

FORMAT = "vings-frontend-checkpoint"
VERSION = 2
_FLOW, _CHAIN = "flow_estimator", "chain_estimator"


class RestartMode(str, enum.Enum):
    """What a front end restarted from its checkpoint does with the first new image."""

    FRESH = "fresh"             #: no checkpoint: a new front end
    RESUMED = "resumed"         #: short gap: tracking goes on from the checkpoint's window and motion
    RELOCALISING = "relocalising"   #: long gap: the image is relocalised against the checkpoint's
    #: window keyframes (a pose in the same world frame), else a new map segment starts


@dataclass
class FrontendCheckpoint:
    """A loaded checkpoint: the objects (``state['frontend']`` and the caller's), the last frame
    processed (``last_stamp_ns``), when it was written (``written_unix_s``, wall clock) and the
    caller's ``extra`` data."""

    state: dict[str, Any]
    last_stamp_ns: Optional[int]
    written_unix_s: float
    extra: dict = field(default_factory=dict)

    @property
    def frontend(self) -> "Frontend":
        return self.state["frontend"]


class _Pickler(pickle.Pickler):
    def __init__(self, f, flows: dict[int, str]) -> None:
        super().__init__(f, protocol=5)
        self._flows = flows

    def persistent_id(self, obj):  # noqa: D102 - pickle hook
        return self._flows.get(id(obj))


class _Unpickler(pickle.Unpickler):
    def __init__(self, f, flows: dict[str, FlowEstimator]) -> None:
        super().__init__(f)
        self._flows = flows

    def persistent_load(self, pid):  # noqa: D102 - pickle hook
        if pid not in self._flows:
            raise pickle.UnpicklingError(f"unknown persistent id {pid!r}")
        return self._flows[pid]


def save_frontend_checkpoint(path: str | os.PathLike, state: dict[str, Any], extra: Optional[dict] = None) -> int:
    """Write ``state`` (``'frontend'``: the :class:`~vings_core.frontend.Frontend`, plus any objects
    that refer to it) to ``path`` atomically; returns the file size in bytes. Call it between two
    frames (not while :meth:`Frontend.process` runs)."""
    fe = state["frontend"]
    flows = {id(fe.ctx.flow_est): _FLOW, id(fe.ctx.chain_est): _CHAIN}
    buf = io.BytesIO()
    _Pickler(buf, flows).dump(state)
    doc = {"format": FORMAT, "version": VERSION, "camera": fe.camera.to_dict(),
           "last_stamp_ns": fe.last_stamp_ns, "written_unix_s": time.time(), "extra": extra or {},
           "state": buf.getvalue()}
    data = pickle.dumps(doc, protocol=5)
    atomic_write_bytes(path, data)
    return len(data)


def load_frontend_checkpoint(path: str | os.PathLike, config: FrontendConfig,
                             flow: FlowEstimator) -> FrontendCheckpoint:
    """Load a checkpoint written by :func:`save_frontend_checkpoint`. The front end gets ``config``
    (the current parameters) and ``flow`` as its flow estimator (a new chain estimator from the
    config). :class:`InputError` (naming the file) if it is missing, not a front-end checkpoint, or
    of another version."""
    from .flow import DISFlow
    p = Path(path)
    try:
        with open(p, "rb") as f:
            doc = pickle.load(f)
    except FileNotFoundError:
        raise InputError(f"{p}: front-end checkpoint not found") from None
    except Exception as e:  # noqa: BLE001 - any unpickling failure is a bad file
        raise InputError(f"{p}: not a VINGS front-end checkpoint ({type(e).__name__}: {e})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"{p}: not a VINGS front-end checkpoint")
    if doc.get("version") != VERSION:
        raise InputError(f"{p}: front-end checkpoint version {doc.get('version')}, this build reads "
                         f"{VERSION}; start without it (move the file away)")
    try:
        state = _Unpickler(io.BytesIO(doc["state"]),
                           {_FLOW: flow, _CHAIN: DISFlow(config.chain_preset, None)}).load()
    except Exception as e:  # noqa: BLE001 - a file of another build of the classes
        raise InputError(f"{p}: the front-end checkpoint cannot be restored ({type(e).__name__}: {e}); "
                         f"start without it (move the file away)") from None
    fe = state["frontend"]
    fe.cfg = config
    fe.ctx.cfg = config
    return FrontendCheckpoint(state, doc.get("last_stamp_ns"), float(doc.get("written_unix_s", 0.0)),
                              dict(doc.get("extra") or {}))


def restart_policy(gap_s: float, resume_max_gap_s: float) -> RestartMode:
    """``RESUMED`` when the first new image is at most ``resume_max_gap_s`` after the last frame the
    checkpoint holds, else ``RELOCALISING``."""
    return RestartMode.RESUMED if 0.0 <= gap_s <= resume_max_gap_s else RestartMode.RELOCALISING
