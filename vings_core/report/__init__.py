"""What a user looks at after a run (docs/report.md): ``report.html`` (:func:`build_report`), the
bird's-eye view of the map (:mod:`.bev`), the per-keyframe ``timeline.jsonl`` (:mod:`.timeline`)
and the optional rerun log (:mod:`.rerun_log`)."""
from .bev import BevImage, Surfels, UpSource, ViewBasis, splat_bev, splat_bev_reference, surfels_from_ply, view_basis
from .build import REPORT_FILE, build_report, load_run
from .timeline import TIMELINE_FILE, Timeline, read_timeline

__all__ = ["BevImage", "Surfels", "UpSource", "ViewBasis", "splat_bev", "splat_bev_reference", "surfels_from_ply",
           "view_basis", "REPORT_FILE", "build_report", "load_run", "TIMELINE_FILE", "Timeline", "read_timeline"]
