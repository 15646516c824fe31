"""End to end in MuJoCo: UR5 + simulated TMF8820 + diff estimator + fusion + state machine."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

pytest.importorskip("mujoco")

from place_safe.cli import main  # noqa: E402
from place_safe.sim.placement_run import run_placement, scenario_path  # noqa: E402

SCENARIOS = Path(__file__).resolve().parents[2] / "scenarios"


@pytest.mark.slow
def test_level_table_is_released_upright_without_spilling():
    res = run_placement(SCENARIOS / "place_level.json", method="diff", seconds=20)
    assert res.outcome == "released", res.summary()
    assert not res.cup_held
    assert res.liquid_spilled == 0
    assert math.degrees(res.cup_tilt) < 2.0
    assert abs(res.cup_height) < 0.003  # standing on the table
    assert res.contact_force_peak < 20.0
    assert "simulated user calibration" in res.calibration and "ORACLE" not in res.calibration
    assert res.planes >= 0.9 * res.frames > 0
    # the per-frame planes agree with the simulator's ground truth while the whole field sees the table
    errs = [abs(f["plane"]["offset"] - f["truth"]["offset"]) for f in res.frame_log if f["plane"] and f["truth"]]
    assert errs and max(errs) < 0.005


def test_tilted_table_is_refused_and_the_cup_kept(tmp_path):
    res = run_placement(SCENARIOS / "place_tilted.json", method="diff", seconds=20)
    assert res.outcome == "refused", res.summary()
    assert "tilted" in res.reason
    assert res.cup_held and res.liquid_spilled == 0
    assert res.final_phase == "aborted"
    assert res.cup_height > 0.2  # retreated, well above the table
    # the command line gives exit status 1 for a refusal and writes the result file
    out = tmp_path / "r.json"
    d = json.loads((SCENARIOS / "place_tilted.json").read_text())
    d["sensor"] = {"drop_prob": 1.0}  # a dead sensor link: refuse without a plane
    scen = tmp_path / "dead.json"
    scen.write_text(json.dumps(d))
    log = ["--json", str(out), "--log", str(tmp_path / "t.jsonl")]
    assert main(["place", "--sim", str(scen), "--timeout", "5", *log]) == 1
    dead = json.loads(out.read_text())
    assert dead["outcome"] == "refused" and dead["cup_held"] and dead["frames"] == 0
    assert "timeout" in dead["reason"] or "no surface plane" in dead["reason"]
    assert main(["place", "--sim", str(tmp_path / "missing.json"), *log]) == 2
    assert scenario_path("place_level").name == "place_level.json"


@pytest.mark.slow
def test_a_sensor_by_the_jaws_releases_from_the_farther_frames_and_never_reads_a_near_frame():
    """The sensor 5 mm above the cup bottom: its last frames are too close to read (no plane, with the reason);
    the release is decided from the fused plane of the farther frames, and no too-close frame carries a plane."""
    from place_safe.recovery.too_close import TOO_CLOSE_REASON

    res = run_placement(SCENARIOS / "set" / "jaw_sensor_level.toml", seconds=20, log_frames=True)
    assert res.outcome == "released", res.summary()
    assert "farther frames" in res.reason
    close = [f for f in res.frame_log if (f.get("reason") or "").find(TOO_CLOSE_REASON) >= 0]
    assert close and all(not f["plane"] for f in close)
    assert abs(res.cup_height) < 0.003
