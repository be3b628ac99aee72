"""Bag loader: ROS 1, ROS 2 (sqlite3, mcap) and plain MCAP; encodings, topic choice, bad input."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from fixtures_io import CX, CY, FX, FY, H, T0, W, BagSpec, gt_series, image_payload, imu_series, make_bag

from vings_core.errors import InputError
from vings_core.io import BagSource, SourceOptions, open_source
from vings_core.io.image_codec import FrameConverter

STORAGES = [("mcap", "bag2_mcap"), ("sqlite3", "bag2_sqlite"), ("plain", "seq.mcap"), ("ros1", "seq.bag")]


@pytest.mark.parametrize("storage,name", STORAGES, ids=[s for s, _ in STORAGES])
def test_every_container_reads_frames_imu_and_calibration(tmp_path, storage, name):
    p = make_bag(tmp_path / name, BagSpec(gt_topic="/ground_truth/pose"), storage)
    src = open_source(p)
    assert isinstance(src, BagSource) and src.kind == ("mcap" if name.endswith(".mcap") else "bag")
    st = [T0 + i * 50_000_000 for i in range(4)]
    assert src.frame_stamps().tolist() == st
    frames = list(src.frames())
    assert [f.stamp_ns for f in frames] == st
    for i, f in enumerate(frames):
        assert np.array_equal(f.image, image_payload(i, "mono8")[0])
    c = src.calibration.camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (W, H, FX, FY, CX, CY)
    ist, g, a = imu_series(40)
    imu = src.imu_samples()
    assert [s.stamp_ns for s in imu] == ist.tolist()
    assert np.allclose(np.stack([s.gyro for s in imu]), g) and np.allclose(np.stack([s.accel for s in imu]), a)
    gst, T = gt_series(4)
    assert src.gt_frame == "body" and src.ground_truth.stamps_ns.tolist() == gst.tolist()
    assert np.allclose(src.ground_truth.poses, T, atol=1e-12)
    info = src.info()
    assert info["topics_used"] == {"image": "/cam0/image_raw", "imu": "/imu0",
                                   "camera_info": "/cam0/camera_info", "ground_truth": "/ground_truth/pose"}
    # IMU present but no extrinsic / noise known: said so
    assert any("T_bc unknown" in w for w in src.warnings)
    assert any("IMU noise parameters unknown" in w for w in src.warnings)


ENCODINGS = ["mono8", "rgb8", "bgr8", "rgba8", "bgra8", "16UC1", "32FC1"]


@pytest.mark.parametrize("enc", ENCODINGS)
def test_image_encodings(tmp_path, enc):
    p = make_bag(tmp_path / "b", BagSpec(image_topics={"/cam": enc}, n_images=2, imu_topics=()), "mcap")
    src = open_source(p)
    frames = list(src.frames())
    assert len(frames) == 2
    for i, f in enumerate(frames):
        expect = image_payload(i, enc)[0]
        if expect.dtype != np.uint8:  # one fixed 8-bit mapping for the stream
            conv = FrameConverter("x")
            conv(image_payload(0, enc)[0])
            expect = conv(expect)
        assert f.image.dtype == np.uint8 and np.array_equal(f.image, expect)
    if enc in ("16UC1", "32FC1"):
        assert any("converted to 8 bit" in w for w in src.warnings)


@pytest.mark.parametrize("fmt", ["jpeg", "png"])
def test_compressed_images(tmp_path, fmt):
    from fixtures_io import texture
    p = make_bag(tmp_path / "c.bag", BagSpec(image_topics={"/cam/compressed": "compressed-" + fmt},
                                             n_images=3, imu_topics=()), "ros1")
    frames = list(open_source(p).frames())
    assert len(frames) == 3 and frames[0].image.shape == (H, W, 3)
    for i, f in enumerate(frames):  # exactly what OpenCV decodes from the same bytes, as RGB
        ok, buf = cv2.imencode("." + fmt, cv2.cvtColor(texture(i, color=True), cv2.COLOR_RGB2BGR))
        expect = cv2.cvtColor(cv2.imdecode(buf, cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB)
        assert np.array_equal(f.image, expect)
    if fmt == "png":
        assert np.array_equal(frames[1].image, texture(1, color=True))


def test_topic_detection_and_choice(tmp_path):
    spec = BagSpec(image_topics={"/left/image_raw": "mono8", "/right/image_raw": "mono8"},
                   imu_topics=("/imu/a", "/imu/b"), camera_info="/left/camera_info")
    p = make_bag(tmp_path / "two", spec, "mcap")
    with pytest.raises(InputError, match=r"several image topics: /left/image_raw, /right/image_raw; "
                                         r"choose one with --image-topic"):
        open_source(p)
    with pytest.raises(InputError, match=r"several IMU topics: /imu/a, /imu/b"):
        open_source(p, SourceOptions(image_topic="/right/image_raw"))
    # the only CameraInfo is the left camera's: never taken for the right images
    with pytest.raises(InputError, match=r"no calibration for image topic /right/image_raw: no usable "
                                         r"CameraInfo topic \(the camera-info topic\(s\) /left/camera_info are "
                                         r"not in the namespace /right"):
        open_source(p, SourceOptions(image_topic="/right/image_raw", imu_topic="/imu/b"))
    src = open_source(p, SourceOptions(image_topic="/left/image_raw", imu_topic="/imu/b"))
    assert src.camera_info_topic == "/left/camera_info"
    src = open_source(p, SourceOptions(image_topic="/right/image_raw", imu_topic="/imu/b",
                                       camera_info_topic="/left/camera_info"))     # the user's choice
    assert (src.image_topic, src.imu_topic, src.camera_info_topic) == ("/right/image_raw", "/imu/b",
                                                                      "/left/camera_info")
    with pytest.raises(InputError, match=r"image topic '/nope' not found; topics in the bag: .*/imu/a"):
        open_source(p, SourceOptions(image_topic="/nope"))
    with pytest.raises(InputError, match=r"image topic '/imu/a' has type sensor_msgs/msg/Imu"):
        open_source(p, SourceOptions(image_topic="/imu/a"))


def test_empty_topic(tmp_path):
    p = make_bag(tmp_path / "e", BagSpec(image_topics={}, empty_topics=("/cam/empty",), camera_info=None), "mcap")
    with pytest.raises(InputError, match=r"image topic '/cam/empty' is empty \(0 messages\)"):
        open_source(p, SourceOptions(image_topic="/cam/empty"))
    src = open_source(p)  # detected: empty topic ignored with a warning, IMU-only recording
    assert len(src.frame_stamps()) == 0 and src.calibration.camera is None and src.calibration.has_imu
    assert any("empty image topic(s) ignored: /cam/empty" in w for w in src.warnings)
    info = src.info()
    assert info["frames"] == 0 and info["imu_samples"] == 40 and info["resolution"] is None
    assert info["calibration"]["camera"] is None and info["calibration"]["has_imu"]
    assert list(src.frames()) == [] and len(list(src.stream())) == 40


def test_unknown_encoding_and_corrupt_images(tmp_path):
    p = make_bag(tmp_path / "u", BagSpec(image_topics={"/cam": "mono8"}, corrupt_image_index=2,
                                         imu_topics=()), "sqlite3")
    src = open_source(p, SourceOptions(on_bad_frame="abort"))
    it = src.frames()
    next(it), next(it)
    with pytest.raises(InputError, match=r"/cam @ \d+ ns: image data has 1536 bytes, expected 3072"):
        next(it)
    src = open_source(p)                    # the default: skipped and counted
    n = len(src.frame_stamps())
    assert len(list(src.frames())) == n - 1 and "expected 3072" in src.bad_frames[0]
    p = make_bag(tmp_path / "j.mcap", BagSpec(image_topics={"/cam": "compressed-jpeg"}, corrupt_image_index=1,
                                              imu_topics=()), "plain")
    with pytest.raises(InputError, match=r"j.mcap:/cam @ \d+ ns: corrupt compressed image"):
        list(open_source(p, SourceOptions(on_bad_frame="abort")).frames())
    # unknown encoding: the first image is decoded when the bag is opened
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore
    ts = get_typestore(Stores.ROS2_JAZZY)
    T = ts.types
    with Writer(tmp_path / "enc", version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection("/cam", "sensor_msgs/msg/Image", typestore=ts)
        m = T["sensor_msgs/msg/Image"](header=T["std_msgs/msg/Header"](
            stamp=T["builtin_interfaces/msg/Time"](sec=5, nanosec=0), frame_id="c"), height=2, width=2,
            encoding="nv21", is_bigendian=0, step=2, data=np.zeros(6, np.uint8))
        w.write(c, 5_000_000_000, ts.serialize_cdr(m, "sensor_msgs/msg/Image"))
    with pytest.raises(InputError, match=r"enc:/cam @ 5000000000 ns: unknown image encoding 'nv21'"):
        open_source(tmp_path / "enc")


def test_out_of_order_and_duplicate_stamps(tmp_path):
    st = [T0 + 300, T0 + 100, T0 + 200, T0 + 200, T0 + 400]
    ist = [T0 + 30, T0 + 10, T0 + 20, T0 + 20, T0 + 40, T0 + 50]
    p = make_bag(tmp_path / "o.bag", BagSpec(image_stamps=st, n_imu=6, imu_stamps=ist), "ros1")
    src = open_source(p)
    assert src.frame_stamps().tolist() == [T0 + 100, T0 + 200, T0 + 300, T0 + 400]
    frames = list(src.frames())
    assert [f.stamp_ns for f in frames] == [T0 + 100, T0 + 200, T0 + 300, T0 + 400]
    # the first message with a stamp wins: T0+200 is image 2, T0+300 image 0
    assert np.array_equal(frames[1].image, image_payload(2, "mono8")[0])
    assert np.array_equal(frames[2].image, image_payload(0, "mono8")[0])
    assert [s.stamp_ns for s in src.imu_samples()] == [T0 + 10, T0 + 20, T0 + 30, T0 + 40, T0 + 50]
    w = " | ".join(src.warnings)
    # counted as backward steps in arrival order
    assert "/cam0/image_raw: 1 time stamp(s) out of order" in w and "/cam0/image_raw: 1 duplicated" in w
    assert "/imu0: 1 time stamp(s) out of order" in w and "/imu0: 1 duplicated" in w
    assert len(list(open_source(p, SourceOptions(max_frames=2)).frames())) == 2


def test_zero_header_stamps_fall_back_to_bag_time(tmp_path):
    p = make_bag(tmp_path / "z", BagSpec(zero_header=True, gt_topic="/ground_truth/pose"), "mcap")
    src = open_source(p)
    assert src.frame_stamps().tolist() == [T0 + i * 50_000_000 for i in range(4)]
    assert any("image(s) with a zero header stamp" in w for w in src.warnings)
    assert any("/imu0: 40 IMU sample(s) with a zero header stamp" in w for w in src.warnings)
    assert any("/ground_truth/pose: " in w and "ground-truth pose(s) with a zero header stamp" in w
               for w in src.warnings)
    assert len(list(src.frames())) == 4


def test_binned_camera_info_gives_the_image_intrinsics(tmp_path):
    # CameraInfo of a 2x larger sensor, binned 2x2 (REP-104): the recorded image's intrinsics
    p = make_bag(tmp_path / "b", BagSpec(info_scale=2, imu_topics=()), "mcap")
    c = open_source(p).calibration.camera
    assert (c.width, c.height, c.fx, c.fy, c.cx, c.cy) == (W, H, FX, FY, CX, CY)


def test_rectified_image_topic_takes_the_projection_matrix(tmp_path):
    """``image_rect``: the images are already rectified, so the camera is P without distortion; the
    CameraInfo's K and D (the raw sensor) would undistort them a second time."""
    D = (-0.3, 0.1, 0.0, 0.0, 0.0)
    raw = open_source(make_bag(tmp_path / "raw", BagSpec(D=D, imu_topics=()), "mcap"))
    assert raw.raw_camera.distortion_model == "radtan"
    rect = open_source(make_bag(tmp_path / "rect", BagSpec(D=D, imu_topics=(), image_topics={
        "/cam0/image_rect": "mono8"}), "mcap"))
    c = rect.raw_camera
    assert c.distortion_model == "none" and (c.fx, c.fy, c.cx, c.cy) == (FX, FY, CX, CY)
    assert rect.calibration.camera == c            # no undistortion, no change of intrinsics


def test_rectified_frame_turns_the_extrinsic_by_the_rectification_rotation(tmp_path):
    """image_rect lives in the rectified frame (x_rect = R x_raw); T_bc describes the raw camera, so
    the source's extrinsic (used to map body ground truth to the camera) becomes T_bc [R^T | 0]."""
    from vings_core.geometry import np_so3_exp
    R = np_so3_exp(np.radians(3.0) * np.array([0.2, 1.0, -0.1]) / np.linalg.norm([0.2, 1.0, -0.1]))
    spec = BagSpec(imu_topics=(), R=tuple(R.reshape(-1)), image_topics={"/cam0/image_rect": "mono8"})
    p = make_bag(tmp_path / "rect", spec, "mcap")
    T_bc = np.array([[0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float)
    (tmp_path / "rect.calib.yaml").write_text(f"T_bc: {T_bc.tolist()}\n")
    src = open_source(p)
    want = T_bc.copy()
    want[:3, :3] = T_bc[:3, :3] @ R.T
    assert np.allclose(src.calibration.T_bc, want, atol=1e-12)
    # raw images: the raw camera is the camera, R does not apply
    p = make_bag(tmp_path / "raw", BagSpec(imu_topics=(), R=tuple(R.reshape(-1))), "mcap")
    (tmp_path / "raw.calib.yaml").write_text(f"T_bc: {T_bc.tolist()}\n")
    assert np.array_equal(open_source(p).calibration.T_bc, T_bc)
    # no extrinsic: said, outputs are in the rectified frame
    src = open_source(make_bag(tmp_path / "noext", spec, "mcap"))
    assert any("rectified camera frame" in w for w in src.warnings)
    bad = make_bag(tmp_path / "bad", BagSpec(imu_topics=(), R=(1, 0, 0, 0, 2, 0, 0, 0, 1),
                                              image_topics={"/cam0/image_rect": "mono8"}), "mcap")
    with pytest.raises(InputError, match="camera_info: field r: the rectification matrix is not a rotation"):
        open_source(bad)


def test_late_entries_bounds_the_reorder_buffer():
    from vings_core.io.common import late_entries
    # time order 0..5 arriving as 1 2 3 4 5 0: with a window of 5 all wait for 0; with 3 it is late
    arrival = np.array([5, 0, 1, 2, 3, 4])
    assert not late_entries(arrival, 5).any()
    assert late_entries(arrival, 3).tolist() == [True, False, False, False, False, False]
    assert not late_entries(np.arange(10), 0).any()   # in order: nothing ever waits
    rng = np.random.default_rng(0)
    for _ in range(20):        # replaying the mask never holds more than the window
        arr = rng.permutation(60)
        w = int(rng.integers(0, 8))
        late = late_entries(arr, w)
        keep = np.flatnonzero(~late)
        t_of_pos = {int(a): k for k, a in enumerate(arr)}
        waiting, nxt, most = set(), 0, 0
        for pos in range(60):
            k = t_of_pos[pos]
            if late[k]:
                continue
            waiting.add(k)
            while nxt < len(keep) and keep[nxt] in waiting:
                waiting.discard(keep[nxt])
                nxt += 1
            most = max(most, len(waiting))
        assert most <= w and nxt == len(keep)


def test_image_far_out_of_order_is_dropped_and_the_buffer_stays_bounded(tmp_path, monkeypatch):
    from vings_core.io import bag as bag_mod
    monkeypatch.setattr(bag_mod, "REORDER_WINDOW", 3)
    # header stamps: images 1..9 in order, then image 0 (stamped first) recorded last
    st = [T0 + (i + 1) * 50_000_000 for i in range(9)] + [T0]
    late_bag = make_bag(tmp_path / "late", BagSpec(imu_topics=(), image_stamps=st, n_images=10), "mcap")
    src = open_source(late_bag)
    assert any("1 image(s) recorded more than 3 images after" in w for w in src.warnings)
    assert src.frame_stamps().tolist() == st[:9]
    most = []
    real_decode = bag_mod.BagSource._decode

    def watch(self, r, conn, raw, stamp):      # delivered images decode one by one at their turn
        most.append(stamp)
        return real_decode(self, r, conn, raw, stamp)
    monkeypatch.setattr(bag_mod.BagSource, "_decode", watch)
    assert [f.stamp_ns for f in src.frames()] == st[:9] and most == st[:9]
    # max_frames counts delivered frames: the late one does not take a place
    src = open_source(late_bag, SourceOptions(max_frames=4))
    assert src.frame_stamps().tolist() == st[:4]
    monkeypatch.setattr(bag_mod, "REORDER_WINDOW", 10)     # room to wait: nothing dropped
    src = open_source(make_bag(tmp_path / "ok", BagSpec(imu_topics=(), image_stamps=st, n_images=10), "mcap"))
    assert [f.stamp_ns for f in src.frames()] == sorted(st)


def test_unusable_default_ground_truth_topic_is_ignored_with_a_warning(tmp_path):
    p = make_bag(tmp_path / "g", BagSpec(empty_topics=("/ground_truth/pose",), imu_topics=()), "mcap")
    src = open_source(p)                   # nobody asked for it: not an error
    assert src.ground_truth is None
    assert any("/ground_truth/pose" in w and "no ground truth" in w for w in src.warnings)
    with pytest.raises(InputError, match="ground-truth topic '/ground_truth/pose'"):
        open_source(p, SourceOptions(gt_topic="/ground_truth/pose"))   # asked for: an error


def test_upper_case_mcap_suffix_and_bad_stamp_nanoseconds(tmp_path):
    import struct

    from vings_core.io.bag import header_stamp_ns
    p = make_bag(tmp_path / "seq.mcap", BagSpec(imu_topics=()), "plain")
    up = p.rename(tmp_path / "SEQ.MCAP")
    with pytest.raises(InputError, match="lower-case suffix '.mcap'"):   # not "unknown format"
        open_source(up)
    raw = bytes([0, 1, 0, 0]) + struct.pack("<iI", 5, 1_500_000_000)
    with pytest.raises(InputError, match=r"bag:/cam: header stamp nanoseconds 1500000000"):
        header_stamp_ns(raw, False, "bag:/cam")


def test_calibration_sources(tmp_path):
    # no CameraInfo and no YAML -> clear error
    p = make_bag(tmp_path / "nocal", BagSpec(camera_info=None), "mcap")
    with pytest.raises(InputError, match=r"no calibration for image topic /cam0/image_raw.*--calib"):
        open_source(p)
    # YAML beside the bag (<name>.calib.yaml) is found, and carries T_bc and IMU noise
    (tmp_path / "nocal.calib.yaml").write_text(
        f"camera: {{width: {W}, height: {H}, fx: 40.0, fy: 41.0, cx: 30.0, cy: 20.0}}\n"
        "T_bc: [[0, -1, 0, 0.1], [1, 0, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n"
        "gyro_noise_density: 0.001\naccel_noise_density: 0.01\n")
    src = open_source(p)
    assert src.calibration.camera.fx == 40.0 and src.calibration.T_bc[0, 3] == 0.1
    assert src.calibration.gyro_noise_density == 0.001 and src.calibration.has_imu
    assert not any("T_bc unknown" in w for w in src.warnings)
    # equidistant CameraInfo -> undistorted pinhole frames
    p = make_bag(tmp_path / "eq", BagSpec(distortion_model="equidistant", D=(0.01, -0.02, 0.003, -0.001)), "mcap")
    src = open_source(p)
    assert src.raw_camera.distortion_model == "equidistant" and src.calibration.camera.distortion_model == "none"
    p = make_bag(tmp_path / "rt", BagSpec(distortion_model="plumb_bob", D=(-0.2, 0.05, 0.001, 0.0, 0.0)), "mcap")
    src = open_source(p, SourceOptions(width=32))
    assert src.raw_camera.distortion.tolist() == [-0.2, 0.05, 0.001, 0.0, 0.0]
    assert src.calibration.camera.width == 32 and next(iter(src.frames())).image.shape == (24, 32)
    p = make_bag(tmp_path / "bad", BagSpec(distortion_model="mystery", D=(0.1, 0, 0, 0, 0)), "mcap")
    with pytest.raises(InputError, match=r"/cam0/camera_info: distortion_model: unknown distortion model 'mystery'"):
        open_source(p)


def test_odometry_ground_truth_topic(tmp_path):
    p = make_bag(tmp_path / "odo", BagSpec(gt_topic="/vicon/odom", gt_type="nav_msgs/msg/Odometry"), "sqlite3")
    assert open_source(p).ground_truth is None   # not the default name: not used unless asked
    src = open_source(p, SourceOptions(gt_topic="/vicon/odom"))
    gst, T = gt_series(4)
    assert np.allclose(src.ground_truth.poses, T, atol=1e-12)


def test_missing_and_unreadable_bags(tmp_path):
    with pytest.raises(InputError, match="no such file or folder"):
        open_source(tmp_path / "nope.bag")
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    with pytest.raises(InputError, match=r"junk.bag: cannot open ROS 1 bag"):
        open_source(tmp_path / "junk.bag")
    (tmp_path / "junk.mcap").write_bytes(b"\x89MCAP0\r\n garbage")
    with pytest.raises(InputError, match=r"junk.mcap: cannot open MCAP file"):
        open_source(tmp_path / "junk.mcap")


def test_mcap_with_a_non_ros_channel_names_it(tmp_path):
    """rosbags cannot open an MCAP that also holds e.g. a JSON channel (Foxglove annotations); the
    error names the non-ROS channels, not rosbags' bare "cannot open MCAP file: 'jsonschema'"."""
    import json

    from mcap.writer import Writer
    with open(tmp_path / "mixed.mcap", "wb") as fh:
        w = Writer(fh)
        w.start()
        sid = w.register_schema(name="note", encoding="jsonschema", data=b"{}")
        cid = w.register_channel(topic="/notes", message_encoding="json", schema_id=sid)
        w.add_message(channel_id=cid, log_time=T0, publish_time=T0, data=json.dumps({"i": 0}).encode())
        w.finish()
    with pytest.raises(InputError, match=r"mixed.mcap: cannot open MCAP file: it has channels that are not "
                                         r"ROS messages \('/notes' \(json\)\).*mcap filter"):
        open_source(tmp_path / "mixed.mcap")


def test_frames_are_streamed_not_held(tmp_path):
    """frames() re-reads the bag: the source keeps no decoded images between iterations."""
    p = make_bag(tmp_path / "s", BagSpec(n_images=6, imu_topics=()), "mcap")
    src = open_source(p)
    held = [v for v in vars(src).values() if isinstance(v, np.ndarray) and v.size >= H * W]
    assert held == []
    a = [f.image for f in src.frames()]
    b = [f.image for f in src.frames()]
    assert len(a) == 6 and all(np.array_equal(x, y) for x, y in zip(a, b))


def test_imu_without_gyro_is_not_used(tmp_path):
    p = make_bag(tmp_path / "g", BagSpec(gyro_cov0=-1.0), "mcap")
    src = open_source(p)
    assert src.imu_samples() == [] and not src.calibration.has_imu
    assert any("/imu0: messages mark gyro as unavailable" in w for w in src.warnings)
    assert len(list(src.frames())) == 4


def test_a_linked_bag_finds_the_calibration_beside_its_target(tmp_path):
    """``room.mcap`` linked from elsewhere still reads ``room.calib.yaml`` beside the real file."""
    import shutil
    spec = BagSpec()
    p = make_bag(tmp_path / "real" / "b", spec, "mcap")
    cal = p.parent / f"{p.stem}.calib.yaml"
    cal.write_text("T_bc: [[1, 0, 0, 0.25], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n")
    (tmp_path / "links").mkdir()
    link = tmp_path / "links" / p.name
    link.symlink_to(p)
    src = open_source(link)
    assert np.isclose(src.calibration.T_bc[0, 3], 0.25)
    shutil.copy(cal, tmp_path / "links" / cal.name)           # one beside the link wins
    (tmp_path / "links" / cal.name).write_text("T_bc: [[1, 0, 0, 0.5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n")
    assert np.isclose(open_source(link).calibration.T_bc[0, 3], 0.5)


def test_one_camera_in_two_transports_keeps_its_differently_named_camera_info(tmp_path):
    """raw + compressed of one camera is one camera: the bag's only CameraInfo (another namespace)
    is still paired with it (warned); a second camera's images would make it ambiguous."""
    spec = BagSpec(image_topics={"/usb_cam/image_raw": "mono8", "/usb_cam/image_raw/compressed": "compressed-png"},
                   camera_info="/camera_info")
    p = make_bag(tmp_path / "one.mcap", spec, "mcap")
    src = open_source(p, SourceOptions(image_topic="/usb_cam/image_raw"))
    assert src.camera_info_topic == "/camera_info" and any("different namespaces" in w for w in src.warnings)
    spec = BagSpec(image_topics={"/usb_cam/image_raw": "mono8", "/other/image_raw": "mono8"},
                   camera_info="/camera_info")
    p = make_bag(tmp_path / "two.mcap", spec, "mcap")
    with pytest.raises(InputError, match="not in the namespace /usb_cam"):
        open_source(p, SourceOptions(image_topic="/usb_cam/image_raw"))
