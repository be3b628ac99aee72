"""The mapper's input queue (vings_core.keyframe_queue): order, memory bound, spill files, recovery."""
from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from vings_core.errors import VingsError
from vings_core.keyframe_queue import KeyframeQueue, keyframe_from_dict, keyframe_to_dict
from vings_core.types import CameraModel, Keyframe


def _kf(stamp: int, H: int = 6, W: int = 8) -> Keyframe:
    g = torch.Generator().manual_seed(stamp)
    cam = CameraModel(W, H, 5.0, 5.0, W / 2, H / 2, "radtan", np.array([0.1, 0.0, 0.0, 0.0]))
    T = torch.eye(4, dtype=torch.float64)
    T[:3, 3] = torch.tensor([stamp, 1.0, 2.0])
    return Keyframe(stamp_ns=stamp, image=torch.rand(H, W, 3, generator=g), T_wc=T,
                    depth=torch.rand(H, W, generator=g) * 5, inv_depth_var=torch.rand(H, W, generator=g),
                    valid=torch.rand(H, W, generator=g) > 0.5, camera=cam, index=stamp % 7)


def _same(a: Keyframe, b: Keyframe) -> bool:
    return (a.stamp_ns == b.stamp_ns and a.index == b.index and a.camera.fx == b.camera.fx
            and a.camera.distortion_model == b.camera.distortion_model
            and np.array_equal(a.camera.distortion, b.camera.distortion)
            and all(torch.equal(getattr(a, f), getattr(b, f)) for f in ("image", "T_wc", "depth", "inv_depth_var", "valid")))


def test_round_trip_of_the_spill_dict():
    kf = _kf(3)
    assert _same(keyframe_from_dict(keyframe_to_dict(kf)), kf)


def test_malformed_spill_dict_is_one_line_error():
    d = keyframe_to_dict(_kf(3))
    del d["depth"]
    with pytest.raises(VingsError, match="f.pt: malformed keyframe"):
        keyframe_from_dict(d, "f.pt")
    with pytest.raises(VingsError, match="unsupported keyframe spill version"):
        keyframe_from_dict({**keyframe_to_dict(_kf(3)), "version": 99}, "f.pt")


def test_fifo_with_spills_keeps_order_and_content(tmp_path):
    q = KeyframeQueue(memory_keyframes=2, spill_dir=tmp_path / "s")
    kfs = [_kf(i) for i in range(1, 7)]
    for i, kf in enumerate(kfs):
        q.put("kf", kf)
        q.put("poses", f"batch{i}")
    assert q.keyframes == 6 and q.keyframes_on_disk == 4 and q.spilled == 4
    assert len(list((tmp_path / "s").glob("kf-*.pt"))) == 4
    got = []
    while len(q):
        kind, item = q.get(0)
        got.append((kind, item))
    assert [k for k, _ in got] == ["kf", "poses"] * 6
    assert [b for k, b in got if k == "poses"] == [f"batch{i}" for i in range(6)]
    assert all(_same(a, b) for a, b in zip([x for k, x in got if k == "kf"], kfs))
    assert not list((tmp_path / "s").glob("kf-*.pt"))       # read back: deleted
    assert q.stats()["queue_peak_keyframes"] == 6 and q.keyframes == 0


def test_memory_slot_is_freed_when_taken(tmp_path):
    q = KeyframeQueue(memory_keyframes=1, spill_dir=tmp_path)
    q.put("kf", _kf(1))
    q.get(0)
    q.put("kf", _kf(2))            # the slot is free again: held in memory
    assert q.spilled == 0 and q.keyframes_on_disk == 0


def test_end_marker_and_timeout():
    q = KeyframeQueue(1)
    assert q.get(0.01) is None and not q.closed()
    q.put(None)
    assert q.get(0.01) is None and q.closed()


def test_producer_and_consumer_threads(tmp_path):
    q = KeyframeQueue(memory_keyframes=2, spill_dir=tmp_path)
    out = []

    def consume():
        while True:
            m = q.get(0.5)
            if m is None:
                if q.closed() and not len(q):
                    return
                continue
            out.append(m[1].stamp_ns)
    t = threading.Thread(target=consume)
    t.start()
    for i in range(1, 30):
        q.put("kf", _kf(i, 4, 4))
    q.put(None)
    t.join(30)
    assert out == list(range(1, 30))


def test_a_killed_process_spill_files_are_recovered_in_order(tmp_path):
    d = tmp_path / "s"
    q = KeyframeQueue(memory_keyframes=1, spill_dir=d)
    for i in range(1, 5):
        q.put("kf", _kf(i))
    (d / ".kf-000000099-5.pt.tmp").write_bytes(b"half")      # killed mid-write
    # the process dies: memory (keyframe 1) is lost with it, the spill files stay
    q2 = KeyframeQueue(memory_keyframes=1, spill_dir=d)
    assert q2.recover() == 3
    q2.put("kf", _kf(9))
    got = [q2.get(0)[1].stamp_ns for _ in range(4)]
    assert got == [2, 3, 4, 9]
    assert not (d / ".kf-000000099-5.pt.tmp").exists()


def test_lost_spill_file_is_a_clear_error(tmp_path):
    q = KeyframeQueue(memory_keyframes=1, spill_dir=tmp_path)
    q.put("kf", _kf(1))
    q.put("kf", _kf(2))
    q.get(0)
    next(tmp_path.glob("kf-*.pt")).unlink()
    with pytest.raises(VingsError, match=r"spilled keyframe \(stamp 2\) is gone from disk"):
        q.get(0)


def test_unwritable_spill_folder_is_a_clear_error(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    q = KeyframeQueue(memory_keyframes=1, spill_dir=f / "sub")
    q.put("kf", _kf(1))
    with pytest.raises(VingsError, match="cannot create the keyframe spill folder"):
        q.put("kf", _kf(2))


def test_private_folder_and_clear(tmp_path):
    q = KeyframeQueue(memory_keyframes=1)
    for i in range(1, 4):
        q.put("kf", _kf(i))
    d = q._dir
    assert d is not None and len(list(d.glob("kf-*.pt"))) == 2
    assert q.clear() == 3 and not list(d.glob("kf-*.pt"))
    q.close()
    assert not d.exists()


def test_persist_then_recover_keeps_every_keyframe_in_order(tmp_path):
    d = tmp_path / "s"
    q = KeyframeQueue(memory_keyframes=2, spill_dir=d)
    for i in range(1, 6):
        q.put("kf", _kf(i))
    assert q.get(0)[1].stamp_ns == 1            # mapped before the stop
    assert q.persist() == 1 and q.keyframes_on_disk == 4
    q2 = KeyframeQueue(memory_keyframes=2, spill_dir=d)
    assert q2.recover() == 4
    got = [q2.get(0)[1] for _ in range(4)]
    assert [k.stamp_ns for k in got] == [2, 3, 4, 5] and _same(got[0], _kf(2))


def test_nice_current_thread_lowers_only_the_calling_thread():
    import os
    from vings_core.util import nice_current_thread
    main = os.getpriority(os.PRIO_PROCESS, 0)
    seen = {}

    def worker():
        tid = threading.get_native_id()
        before = os.getpriority(os.PRIO_PROCESS, tid)
        assert nice_current_thread(3)
        seen["delta"] = os.getpriority(os.PRIO_PROCESS, tid) - before
    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert seen["delta"] == min(3, 19 - main) and os.getpriority(os.PRIO_PROCESS, 0) == main


def test_unacked_keyframes_hold_until_the_mapper_lists_them(tmp_path):
    import numpy as np
    import torch

    from vings_core.keyframe_queue import UnackedKeyframes
    from vings_core.types import CameraModel, Keyframe
    cam = CameraModel(8, 6, 5.0, 5.0, 3.5, 2.5)

    def kf(i):
        return Keyframe(stamp_ns=(i + 1) * 10, image=torch.rand(6, 8, 3), T_wc=torch.eye(4, dtype=torch.float64),
                        depth=torch.ones(6, 8), inv_depth_var=torch.ones(6, 8), valid=torch.ones(6, 8, dtype=torch.bool),
                        camera=cam, index=i)
    u = UnackedKeyframes(memory_keyframes=2, spill_dir=tmp_path / "spill")
    for i in range(5):
        u.sent(kf(i), now=float(i))
    u.sent(kf(0), now=9.0)                          # a re-send is held once
    assert len(u) == 5 and len(list((tmp_path / "spill").glob("kf-*.pt"))) == 3   # 2 in memory, 3 on disk
    assert u.acknowledged([20]) == 0                # out of order: kept until 10 is acknowledged
    assert len(u) == 4 and [int(k.stamp_ns) for k in u.pending()] == [10, 30, 40, 50]   # 20 is not re-sent
    assert u.acknowledged([10]) == 2 and len(u) == 3
    assert u.acknowledged([40]) == 0 and len(u) == 2
    pend = u.pending()
    assert [int(k.stamp_ns) for k in pend] == [30, 50] and len(u) == 2     # still held
    assert np.allclose(pend[0].image.numpy(), pend[0].image.numpy())
    assert u.overdue(now=10.0, timeout_s=5.0) and not u.overdue(now=3.5, timeout_s=5.0)
    u.restamp(20.0)
    assert not u.overdue(now=21.0, timeout_s=5.0)
    assert u.acknowledged([10, 20, 30, 40, 50]) == 3 and len(u) == 0 and u.released == 5
    u.close()


def test_unacked_keyframes_kept_on_disk_come_back_after_a_crash(tmp_path):
    from vings_core.keyframe_queue import UnackedKeyframes
    keep = tmp_path / "fe.ckpt.unacked"
    u = UnackedKeyframes(memory_keyframes=1, keep_dir=keep)
    for i in range(4):
        u.sent(_kf((i + 1) * 10), now=float(i))
    assert u.acknowledged([10, 20]) == 2
    assert sorted(f.name for f in keep.glob("*.pt")) == ["kf-30.pt", "kf-40.pt"]
    # the process dies without closing; a new one finds what was not acknowledged
    (keep / "kf-5.pt").write_bytes(b"torn")         # a damaged file is dropped, not fatal
    v = UnackedKeyframes(memory_keyframes=1, keep_dir=keep)
    back = v.restore()
    assert [int(k.stamp_ns) for k in back] == [30, 40] and len(v) == 2
    assert _same(back[0], _kf(30))
    assert v.overdue(now=1.0, timeout_s=0.5)        # held as sent long ago: due for a re-send
    v.discard()
    assert len(v) == 0 and not list(keep.glob("*.pt"))
    v.close()
