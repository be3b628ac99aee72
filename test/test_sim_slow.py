"""Full-size simulator runs (minutes on 2 cores): `make test-slow`."""
from __future__ import annotations

import json

import numpy as np
import pytest

from vings_core.sim import generate

pytestmark = pytest.mark.slow


def test_room_default_sequence_with_mcap(tmp_path):
    from vings_core.io import open_source

    out = generate("room", tmp_path / "room", dynamic=True)          # 300 frames, 376x240
    s = json.loads((out / "sim.json").read_text())
    assert s["frames"] == 300 and s["resolution"] == [376, 240] and s["duration_s"] == 14.95
    assert 0.5 <= s["mean_speed_mps"] <= 1.5
    assert s["frames_with_dynamic"] > 30 and s["depth_range_m"][0] > 0.3
    src = open_source(out / "room.mcap")
    euroc = open_source(out)
    assert np.array_equal(src.frame_stamps(), euroc.frame_stamps())
    f_m, f_e = next(iter(src.frames())), next(iter(euroc.frames()))
    assert np.array_equal(f_m.image, f_e.image)
    assert len(src.imu_samples()) == len(euroc.imu_samples()) == 2991


def test_cli_street_loop_full_resolution(tmp_path, capsys):
    from vings_ros.cli import main

    out = tmp_path / "street"
    assert main(["sim", "--scene", "street", "--loop", "--length-m", "400", "--dynamic",
                 "--no-mcap", "--out", str(out)]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["loop"] and s["start_end_distance_m"] < 1.0
    assert s["max_speed_mps"] > 8.0 and s["sky_fraction"] > 0.02
    assert s["frames"] == round(s["duration_s"] * 20) + 1
