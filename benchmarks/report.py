"""Cost and size of the run report (docs/report.md).

Experiments (``--exp``, comma list):

* ``demo``: what ``make demo`` runs (``vings sim --scene room --frames 80``, then ``vings run``
  with the default parameters): the time to draw ``report.html`` and ``bev.png`` (measured inside
  the run) against the run's ``wall_s``, the report's size; then ``vings report`` on the folder
  (the redraw time).
* ``kitti07``: ``vings run ../shared/data/kitti07_160``: the report's size (target <= 20 MB) and
  its drawing time.

``--screenshots DIR`` also writes a screenshot of each report (headless Chromium, 1200 px wide) as
``DIR/report_<exp>.png``. The last stdout line is one JSON object keyed by experiment.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _harness import run_experiments  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared" / "data"


def _log(*a) -> None:
    print("[bench report]", *a, file=sys.stderr, flush=True)


def _run(source: Path, out: Path) -> dict:
    from vings_core.io import SourceOptions
    from vings_core.pipeline import RunConfig, SlamRunner, open_working_source
    src = open_working_source(str(source), SourceOptions())     # as `vings run SOURCE` (automatic size)
    r = SlamRunner(src, out, run_cfg=RunConfig(), progress=False)
    m = r.run()
    rep = out / "report.html"
    return {"frames": m["frames"], "keyframes": m["keyframes"], "wall_s": round(m["wall_s"], 2),
            "report_s": None if r.report_s is None else round(r.report_s, 3),
            "report_share": None if r.report_s is None else round(r.report_s / m["wall_s"], 4),
            "report_mb": round(rep.stat().st_size / 2 ** 20, 3) if rep.is_file() else None,
            "bev_kb": round((out / "bev.png").stat().st_size / 1024, 1) if (out / "bev.png").is_file() else None}


def _redraw(out: Path) -> float:
    from vings_core.report import build_report
    t0 = time.perf_counter()
    build_report(out, out_path=out / "report_redrawn.html")
    return round(time.perf_counter() - t0, 3)


def _screenshot(report: Path, png: Path) -> None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        _log("no chromium: screenshot skipped")
        return
    png.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as prof:
        subprocess.run([browser, "--headless=new", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                        f"--user-data-dir={prof}", "--virtual-time-budget=5000", f"--screenshot={png}",
                        "--window-size=1200,2600", report.resolve().as_uri()], check=True, capture_output=True,
                       timeout=180)
    # a small PNG for docs/: half size, 64 colours
    import cv2
    img = cv2.imread(str(png))
    img = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(png), img, [cv2.IMWRITE_PNG_COMPRESSION, 9])


def exp_demo(work: Path, shots: Path | None) -> dict:
    from vings_core.sim import generate
    t0 = time.perf_counter()
    generate("room", work / "room", frames=80)
    _log(f"simulated the demo room in {time.perf_counter() - t0:.0f} s")
    r = _run(work / "room", work / "run")
    r["redraw_s"] = _redraw(work / "run")
    if shots is not None:
        _screenshot(work / "run" / "report.html", shots / "report_demo.png")
    _log("demo:", json.dumps(r))
    return r


def exp_kitti07(work: Path, shots: Path | None) -> dict:
    src = SHARED / "kitti07_160"
    if not src.is_dir():
        return {"incomplete": f"{src} not found"}
    r = _run(src, work / "kitti07")
    r["redraw_s"] = _redraw(work / "kitti07")
    if shots is not None:
        _screenshot(work / "kitti07" / "report.html", shots / "report_kitti07_160.png")
    _log("kitti07:", json.dumps(r))
    return r


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--exp", default="demo,kitti07")
    ap.add_argument("--screenshots", metavar="DIR", help="write report screenshots there")
    ap.add_argument("--work", help="working folder (default: a temporary one under $TMPDIR)")
    args = ap.parse_args()
    work = Path(args.work) if args.work else Path(os.environ.get("TMPDIR", "/tmp")) / "vings_bench_report"
    work.mkdir(parents=True, exist_ok=True)
    shots = Path(args.screenshots) if args.screenshots else None
    fns = {"demo": exp_demo, "kitti07": exp_kitti07}
    names = [e.strip() for e in args.exp.split(",") if e.strip()]
    bad = [n for n in names if n not in fns]
    if bad:
        ap.error(f"unknown experiment(s) {bad}; known: {', '.join(fns)}")
    out: dict = {}
    rc = run_experiments([(n, lambda n=n: fns[n](work, shots)) for n in names], out, log=_log)
    return rc


if __name__ == "__main__":
    sys.exit(main())
