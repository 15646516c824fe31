"""The task commands in MuJoCo: ``place-safe capture --sim`` writes frames in the shared format (read back by
the frame-file reader) and ``place-safe place --sim`` writes the transition log and the result JSON."""

from __future__ import annotations

import json

import pytest

from place_safe.cli.app import main
from place_safe.io.frame_file import load_frames


@pytest.mark.slow
def test_capture_and_place_commands_in_simulation(tmp_path, capsys):
    cap = tmp_path / "cap.jsonl"
    argv = ["capture", "--sim", "level_table", "--distances", "100,200", "--incidences", "0", "--settle", "0.05",
            "-q", "-o", str(cap)]
    assert main(argv) == 0
    assert main(argv) == 0  # resumed: nothing left to do
    assert "0 poses captured now, 2 already there" in capsys.readouterr().out
    frames = load_frames(cap)
    assert len(frames) == 2 and all(f.truth is not None and len(f.extra["joint_angles"]) == 6 for f in frames)
    assert [round(f.truth.offset, 3) for f in frames] == [0.1, 0.2]

    res, log = tmp_path / "r.json", tmp_path / "t.jsonl"
    code = main(["place", "--sim", "place_tilted", "--method", "peak", "--json", str(res), "--log", str(log),
                 "--timeout", "20"])
    out = json.loads(res.read_text())
    assert code == 1 and out["outcome"] == "refused" and out["cup_held"], out["reason"]
    assert [json.loads(x)["to"] for x in log.read_text().splitlines()][-1] == "aborted"
    # one way to place in simulation (issue 27): the scenario's calibration, the simulated user calibration
    assert out["calibration"].startswith("simulated user calibration") and out["calibrated"] is True
    code = main(["place", "--sim", "place_level", "--method", "peak", "--calibration", "none", "--json", str(res),
                 "--log", str(log)])
    out = json.loads(res.read_text())  # no calibration: refused before anything moved, and it says why
    assert code == 1 and out["calibrated"] is False and out["reason"].startswith("sensor not calibrated")
