"""One input policy for `vings run` and the nodes: undecodable frames skipped and counted (or
`--on-bad-frame abort`), negative stamps refused, `vings info --check`, an empty params file
refused."""
from __future__ import annotations

import json

import pytest


@pytest.fixture(scope="module")
def room(tmp_path_factory):
    from vings_core.sim import generate
    d = tmp_path_factory.mktemp("policy")
    generate("room", d / "room", frames=30, width=160, height=112, seed=2, mcap=False)
    csv = d / "room" / "mav0" / "cam0" / "data.csv"
    names = [ln.split(",")[1] for ln in csv.read_text().splitlines()[1:]]
    (d / "room" / "mav0" / "cam0" / "data" / names[12]).write_bytes(b"\x89PNG\r\n\x1a\n not an image")
    return d, names[12]


def test_a_bad_frame_is_skipped_counted_and_reported(room, capsys):
    from vings_ros.cli import main
    d, bad = room
    assert main(["info", str(d / "room"), "--check", "--json"]) == 1
    info = json.loads(capsys.readouterr().out)
    assert info["check"]["frames_bad"] == 1 and info["check"]["frames_decoded"] == 29
    assert bad in info["check"]["bad"][0]
    p = d / "p.yaml"
    p.write_text("/**:\n  ros__parameters:\n    mapping:\n      iters_per_keyframe: 2\n"
                 "      points_per_keyframe: 500\n      refine_iters: 1\n")
    out = d / "out"
    assert main(["run", str(d / "room"), "--out", str(out), "--params", str(p), "--sync", "--no-progress",
                 "--no-report", "--no-loop", "--no-eraser"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames_bad"] == 1 and m["frames"] == 29
    capsys.readouterr()
    assert main(["run", str(d / "room"), "--out", str(d / "out2"), "--params", str(p), "--sync", "--no-progress",
                 "--on-bad-frame", "abort"]) == 2
    err = capsys.readouterr().err
    assert bad in err and len(err.strip().splitlines()[-1]) < 400


def test_negative_stamps_are_refused(tmp_path):
    from vings_core.io import open_source
    from vings_core.sim import generate
    generate("room", tmp_path / "r", frames=12, width=96, height=64, seed=1, mcap=False)
    csv = tmp_path / "r" / "mav0" / "cam0" / "data.csv"
    lines = csv.read_text().splitlines()
    stamp, name = lines[1].split(",")
    lines[1] = f"-5,{name}"
    csv.write_text("\n".join(lines) + "\n")
    src = open_source(str(tmp_path / "r"))
    st = src.frame_stamps()
    assert len(st) == 11 and (st >= 0).all()
    assert any("negative time stamp" in w for w in src.warnings)


@pytest.mark.parametrize("text", ["", "# only a comment\n\n"])
def test_an_empty_params_file_is_an_error(tmp_path, text, capsys):
    from vings_ros.cli import main
    p = tmp_path / "empty.yaml"
    p.write_text(text)
    assert main(["run", str(tmp_path / "nothing"), "--out", str(tmp_path / "o"), "--params", str(p)]) == 2
    assert "empty" in capsys.readouterr().err


def test_a_recording_without_one_decodable_frame_is_an_error(tmp_path, capsys):
    from vings_core.sim import generate
    from vings_ros.cli import main
    generate("room", tmp_path / "r", frames=6, width=96, height=64, seed=1, mcap=False)
    for f in (tmp_path / "r" / "mav0" / "cam0" / "data").glob("*.png"):
        f.write_bytes(b"garbage")
    assert main(["run", str(tmp_path / "r"), "--out", str(tmp_path / "o"), "--no-progress", "--sync"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "corrupt or unreadable image" in err[0]
