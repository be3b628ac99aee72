"""The run report (docs/report.md): bird's-eye view kernel against its reference, the view's up
axis, the timeline, report.html from a real run (every section drawn, images decodable) and
`vings report` on an existing output folder."""
from __future__ import annotations

import base64
import json
import re

import cv2
import numpy as np
import pytest

from vings_core.profiling import Profile
from vings_core.report import Surfels, Timeline, UpSource, splat_bev, splat_bev_reference, view_basis
from vings_core.report.timeline import read_timeline


def _path(n=20, plane_normal=(0.0, 0.0, 1.0), radius=2.0):
    """Cameras on a circle in the plane of ``plane_normal``, optical y axis = -normal (camera up =
    normal), looking outwards."""
    nrm = np.asarray(plane_normal, float) / np.linalg.norm(plane_normal)
    a = np.cross(nrm, [1.0, 0, 0] if abs(nrm[0]) < 0.9 else [0, 1.0, 0])
    a /= np.linalg.norm(a)
    b = np.cross(nrm, a)
    T = np.tile(np.eye(4), (n, 1, 1))
    for i, th in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False)):
        p = radius * (np.cos(th) * a + np.sin(th) * b)
        z = p / np.linalg.norm(p)
        y = -nrm
        x = np.cross(y, z)
        T[i, :3, :3] = np.stack([x, y, z], 1)
        T[i, :3, 3] = p
    return T


def _surfels(n, rng, extent=5.0):
    return Surfels(means=rng.uniform(-extent, extent, (n, 3)) * [1, 1, 0.3], rgb=rng.uniform(0, 1, (n, 3)),
                   opacity=rng.uniform(0, 1, n), radius=rng.uniform(0.0, 0.4, n))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_bev_kernel_matches_reference(seed):
    rng = np.random.default_rng(seed)
    s = _surfels(400, rng)
    s.means[:50] = s.means[50:100]          # equal heights at the same place: the later surfel wins
    T = _path(12)
    for grav in (True, False):
        fast = splat_bev(s, T, grav, size_px=96, chunk=200)
        ref = splat_bev_reference(s, T, grav, size_px=96)
        assert fast.rgb.shape == ref.shape
        assert np.array_equal(fast.rgb, ref)
        assert (fast.rgb != 255).any()      # something was drawn


def test_bev_hides_what_is_above_the_camera_and_draws_a_scale_bar_only_when_metric():
    T = _path(12, radius=1.0)               # cameras at height 0
    s = Surfels(means=np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.5]]), rgb=np.array([[1.0, 0, 0], [0, 0, 1.0]]),
                opacity=np.array([1.0, 1.0]), radius=np.array([0.3, 0.3]))
    b = splat_bev(s, T, True, size_px=64)
    assert b.surfels_drawn == 1             # the one above the path (a ceiling) is left out
    c = b.rgb[b.rgb.shape[0] // 2, b.rgb.shape[1] // 2]
    assert tuple(c) == (255, 0, 0)
    m = splat_bev(s, T, True, metric=True, size_px=64)
    assert not np.array_equal(m.rgb, b.rgb) and np.array_equal(m.rgb[:32], b.rgb[:32])  # bar at the bottom only


def test_view_basis_up_axis():
    tilt = np.array([0.3, -0.2, 1.0])
    T = _path(30, plane_normal=tilt)
    b = view_basis(T, gravity_aligned=False)
    assert b.source is UpSource.PATH_PLANE
    assert b.R[2] @ (tilt / np.linalg.norm(tilt)) > 0.999     # signed like the cameras' up
    assert np.allclose(b.R @ b.R.T, np.eye(3), atol=1e-9) and np.linalg.det(b.R) > 0
    g = view_basis(T, gravity_aligned=True)
    assert g.source is UpSource.GRAVITY and np.allclose(g.R[2], [0, 0, 1])
    line = np.tile(np.eye(4), (10, 1, 1))
    line[:, :3, :3] = np.stack([[1, 0, 0], [0, 0, -1], [0, 1, 0]], 1)    # optical y = -z world: up = +z
    line[:, 1, 3] = np.linspace(0, 10, 10)
    lb = view_basis(line, gravity_aligned=False)
    assert lb.source is UpSource.CAMERA_UP and lb.R[2] @ [0, 0, 1] > 0.999


def test_timeline_takes_step_differences():
    prof = Profile()
    prof.enable()
    tl = Timeline(prof)
    prof.add("tracking", "frame (total)", 0.5)
    prof.add("tracking", "flow", 0.2)
    a = tl.record(1, {"active": 3, "passive": 1, "on_disk": 0, "total": 4}, "tracking", None,
                  {"light": False, "backlog": 0}, None, None)
    prof.add("mapping", "keyframe (total)", 1.25)
    b = tl.record(2, {"active": 5, "passive": 1, "on_disk": 1, "total": 6}, "tracking", None,
                  {"light": False, "backlog": 0}, {"candidates": 1, "accepted": 0}, None)
    assert a["stage_s"]["tracking"] == 0.5 and a["steps"]["tracking"]["flow"] == 0.2
    assert b["stage_s"] == {"io": 0.0, "tracking": 0.0, "eraser": 0.0, "mapping": 1.25, "loop": 0.0}
    assert "tracking" not in b["steps"]
    assert b["t_s"] >= a["t_s"] and b["index"] == 1


@pytest.fixture(scope="module")
def run_out(tmp_path_factory):
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    from vings_core.sim import generate
    d = tmp_path_factory.mktemp("report")
    generate("room", d / "room", frames=40, width=192, height=128, seed=3, dynamic=True, mcap=False)
    p = d / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 3\n"
                 "      points_per_keyframe: 1500\n      refine_iters: 2\n")
    r = SlamRunner(open_source(d / "room"), d / "out", str(p),
                   RunConfig(sync=True, eval_keyframes=4, eval_novel=2, save_renders=2), progress=False)
    m = r.run()
    return d / "out", m


def _images(html: str) -> list[bytes]:
    return [base64.b64decode(b) for b in re.findall(r'src="data:image/[a-z]+;base64,([^"]+)"', html)]


def test_run_writes_report_and_its_data(run_out):
    out, m = run_out
    for f in ("report.html", "bev.png", "timeline.jsonl", "run.json", "ground_truth.tum", "views/index.json"):
        assert (out / f).is_file(), f
    tl = read_timeline(out / "timeline.jsonl")
    assert len(tl) == m["keyframes"]
    assert [ln["stamp_ns"] for ln in tl] == sorted(ln["stamp_ns"] for ln in tl)
    assert tl[-1]["gaussians"]["total"] == m["num_gaussians"]
    assert all(ln["eraser"] is not None for ln in tl)           # the eraser is on by default
    assert sum(ln["stage_s"]["mapping"] for ln in tl) > 0 and sum(ln["stage_s"]["tracking"] for ln in tl) > 0
    info = json.loads((out / "run.json").read_text())
    assert info["params"]["mapping"]["iters_per_keyframe"] == 3 and "torch" in info["versions"]
    views = json.loads((out / "views" / "index.json").read_text())["views"]
    assert len(views) == 2
    for v in views:
        for kind in ("input", "depth", "normal"):
            img = cv2.imread(str(out / "views" / f"kf_{v['stamp_ns']}_{kind}.png"))
            assert img is not None and img.shape[:2] == (128, 192)
    bev = cv2.imread(str(out / "bev.png"))
    assert bev is not None and max(bev.shape[:2]) == 1024 and (bev != 255).any()
    html = (out / "report.html").read_text()
    assert "http://" not in html and "https://" not in html          # self-contained
    for sec in ("summary", "trajectory", "map", "keyframes", "resources", "loops", "eraser", "parameters"):
        assert f'<section id="{sec}">' in html
    imgs = _images(html)
    # trajectory, error, (RPE if a length fits), map, 2 x 4 views, Gaussians, stages, masked fraction
    assert len(imgs) >= 13
    for b in imgs:
        dec = cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_UNCHANGED)
        assert dec is not None and min(dec.shape[:2]) >= 64


def test_vings_report_redraws_an_output_folder(run_out, tmp_path):
    import shutil

    from vings_ros.cli import main
    out, _ = run_out
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    (copy / "report.html").unlink()
    (copy / "bev.png").unlink()
    assert main(["report", str(copy)]) == 0
    assert (copy / "report.html").is_file() and (copy / "bev.png").is_file()
    assert main(["report", str(tmp_path / "missing")]) == 2


def _need(found: bool, what: str) -> None:
    """Skip with the reason on a developer's machine without ``what``; in CI (``VINGS_CI=1``, set by
    .ci/run, which installs it) a missing tool is a failure."""
    import os
    if not found:
        if os.environ.get("VINGS_CI") == "1":
            pytest.fail(f"{what} is missing in CI (.ci/run installs it)")
        pytest.skip(f"{what} is not installed on this machine")


def test_report_renders_in_a_headless_browser(run_out, tmp_path):
    import shutil
    import subprocess
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    _need(browser is not None, "chromium (Debian package `chromium`)")
    out, _ = run_out
    url = (out / "report.html").resolve().as_uri()
    base = [browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
            f"--user-data-dir={tmp_path / 'profile'}", "--enable-logging=stderr", "--v=0",
            "--virtual-time-budget=5000"]
    dom = subprocess.run(base + ["--dump-dom", url], capture_output=True, text=True, timeout=120)
    assert dom.returncode == 0, dom.stderr[-2000:]
    console = [ln for ln in dom.stderr.splitlines() if "CONSOLE" in ln]
    assert not any("error" in ln.lower() or "report:" in ln for ln in console), console
    m = re.search(r'<pre id="selfcheck">(.*?)</pre>', dom.stdout, re.S)
    assert m and m.group(1).strip(), "the report's self-check script did not run"
    check = json.loads(m.group(1).replace("&quot;", '"'))
    assert check["broken"] == 0 and check["images"] >= 13
    assert all(s["height"] > 40 for s in check["sections"]), check["sections"]
    assert {s["id"] for s in check["sections"]} >= {"summary", "trajectory", "map", "keyframes", "resources",
                                                   "loops", "eraser", "parameters"}
    plots = [s for s in check["sizes"] if s["alt"] in ("trajectory from above", "Gaussians and memory",
                                                        "time per stage per keyframe", "error along the path")]
    assert len(plots) == 4 and all(s["w"] >= 400 and s["h"] >= 200 for s in plots), plots
    shot = tmp_path / "report.png"
    r = subprocess.run(base + [f"--screenshot={shot}", "--window-size=1200,3000", url], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0 and shot.is_file(), r.stderr[-2000:]
    img = cv2.imread(str(shot))
    assert img is not None and img.shape[:2] == (3000, 1200)
    assert img.std() > 20          # a page with plots and images, not a blank one


def test_rerun_log_reads_back(tmp_path):
    import collections
    try:
        from rerun.chunk import RrdReader
    except ImportError:
        RrdReader = None
    _need(RrdReader is not None, "the rerun SDK (pip install '.[viz]')")
    from vings_core.io import open_source
    from vings_core.pipeline import RunConfig, SlamRunner
    from vings_core.sim import generate
    generate("room", tmp_path / "room", frames=24, width=160, height=112, seed=1, mcap=False)
    p = tmp_path / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 2\n"
                 "      points_per_keyframe: 800\n      refine_iters: 1\n")
    rrd = tmp_path / "run.rrd"
    r = SlamRunner(open_source(tmp_path / "room"), tmp_path / "out", str(p),
                   RunConfig(sync=True, eval_keyframes=1, eval_novel=1, save_renders=0, report=False),
                   progress=False, rerun_path=str(rrd))
    m = r.run()
    rows = collections.Counter()
    for ch in RrdReader(rrd).stream():
        rows[ch.entity_path] += ch.num_rows
    tracked = len(r.trajectory())
    assert rows["/world/camera/image/rgb"] == m["frames"]
    assert 0 < rows["/world/camera"] <= tracked        # frames posed live (the back-filled ones are not)
    assert rows["/world/trajectory"] == m["keyframes"]
    assert m["keyframes"] - 1 <= rows["/world/keyframes/render"] == rows["/world/keyframes/depth"] <= m["keyframes"]
    assert 1 <= rows["/world/map"] <= len(range(0, m["keyframes"], 5))
    assert rows["/world/camera/image"] == 1        # the pinhole, static


def test_foxglove_layout_names_recorded_topics():
    from pathlib import Path

    from vings_ros.recorder import OUTPUT_TOPICS
    import vings_ros
    lay = json.loads((Path(vings_ros.__file__).parent / "config" / "foxglove_layout.json").read_text())
    recorded = {t for t, _, _ in OUTPUT_TOPICS}

    def leaves(node):
        return [node] if isinstance(node, str) else leaves(node["first"]) + leaves(node["second"])
    assert sorted(leaves(lay["layout"])) == sorted(lay["configById"])
    named = set(re.findall(r'"(/[a-z_/]+)', json.dumps(lay["configById"])))
    assert named and named <= recorded, named - recorded


def test_vings_report_on_a_launch_recording(tmp_path):
    """A recording shaped like `vings launch --record`'s (raw CDR of the graph's messages through the
    rosbag2 MCAP writer, as recorder_node writes them) becomes an output folder and a report."""
    pytest.importorskip("rclpy")
    from rclpy.serialization import serialize_message
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from msg_adapters import topics as T
    from msg_adapters.eraser import mask_to_msg
    from msg_adapters.image import float_image_to_msg, image_to_msg
    from msg_adapters.pointcloud import points_to_pointcloud2
    from msg_adapters.pose import estimate_to_odometry, trajectory_to_path
    from vings_core.trajectory_io import read_tum
    from vings_core.types import PoseEstimate, Trajectory
    from vings_ros.cli import main
    from vings_ros.recorder import OUTPUT_TOPICS

    rng = np.random.default_rng(0)
    frame = "camera_optical_frame"
    msgs = []       # (topic, stamp, message)
    poses = {}
    for i in range(30):
        s = 10_000_000_000 + i * 50_000_000
        T_wc = np.eye(4)
        T_wc[:3, 3] = [0.05 * i, 0.01 * np.sin(i), 0.0]
        poses[s] = T_wc
        msgs.append((T.ODOMETRY_TOPIC, s, estimate_to_odometry(PoseEstimate(s, T_wc))))
        if i % 5 == 0:
            img = (rng.uniform(0, 255, (48, 64, 3))).astype(np.uint8)
            msgs.append((T.KEYFRAME_IMAGE_TOPIC, s, image_to_msg(img, s, frame)))
            msgs.append((T.RENDER_COLOR_TOPIC, s, image_to_msg(np.clip(img.astype(int) + 5, 0, 255).astype(np.uint8), s, frame)))
            msgs.append((T.RENDER_DEPTH_TOPIC, s, float_image_to_msg(rng.uniform(1, 3, (48, 64)).astype(np.float32), s, frame)))
            msgs.append((T.RENDER_NORMAL_TOPIC, s, image_to_msg(np.full((48, 64, 3), 128, np.uint8), s, frame)))
            m = np.zeros((48, 64), bool)
            m[10:20, 10:30] = True
            msgs.append((T.DYNAMIC_MASK_TOPIC, s, mask_to_msg(m, s)))
    kf = Trajectory.from_poses({s: T for s, T in poses.items() if (s - 10_000_000_000) // 50_000_000 % 5 == 0})
    last = int(kf.stamps_ns[-1])
    msgs.append((T.REFINED_KEYFRAMES_TOPIC, last, trajectory_to_path(kf)))
    msgs.append((T.MAP_POINTS_TOPIC, last, points_to_pointcloud2(rng.uniform(-1, 1, (500, 3)).astype(np.float32) * [2, 2, 0.2],
                                                                 rng.integers(0, 255, (500, 3)).astype(np.uint8), last)))
    types = {t: ty for t, ty, _ in OUTPUT_TOPICS}
    bag = tmp_path / "rec"
    ts = get_typestore(Stores.ROS2_JAZZY)
    with Writer(bag, version=9, storage_plugin=StoragePlugin.MCAP) as w:
        conns = {t: w.add_connection(t, types[t], typestore=ts) for t in {m[0] for m in msgs}}
        for t, s, msg in msgs:
            w.write(conns[t], s, serialize_message(msg))
    mcap = tmp_path / "run.mcap"
    (bag / "rec.mcap").rename(mcap)
    assert main(["report", str(mcap)]) == 0
    out = tmp_path / "run_report"
    assert len(read_tum(out / "trajectory.tum")) == 30 and len(read_tum(out / "keyframes.tum")) == 6
    assert len(list((out / "masks").glob("kf_*.png"))) == 6
    views = json.loads((out / "views" / "index.json").read_text())["views"]
    assert len(views) == 6 and all(v["psnr_db"] > 30 for v in views)
    bev = cv2.imread(str(out / "bev.png"))
    assert bev is not None and (bev != 255).any()
    html = (out / "report.html").read_text()
    assert html.count("<img") >= 6 * 4 + 2
    # a second conversion never writes over the first
    assert main(["report", str(mcap)]) == 2
    assert main(["report", str(tmp_path / "nothing.mcap")]) == 2


def test_vings_eval_writes_the_trajectory_plots(run_out, tmp_path):
    from vings_ros.cli import main
    out, _ = run_out
    assert main(["eval", str(out), "--gt", str(out / "ground_truth.tum"), "--plots", str(tmp_path / "p")]) == 0
    for name in ("trajectory.png", "error.png"):
        img = cv2.imread(str(tmp_path / "p" / name))
        assert img is not None and min(img.shape[:2]) >= 200
    (tmp_path / "f").write_text("x")
    assert main(["eval", str(out), "--gt", str(out / "ground_truth.tum"), "--plots", str(tmp_path / "f")]) == 2
