"""The scenario runner: judging by simulation truth, random scenes, the command (CI subset), Ray."""

from __future__ import annotations

import json
import math
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("mujoco")

from place_safe.sim import suite  # noqa: E402
from place_safe.sim.scenario import Expectation, Scenario, packaged_scenarios  # noqa: E402


def _res(**kw):
    base = dict(scenario="s", sensor="nominal", method="diff", calibration="sim", true_tilt=0.0,
                surface_height=0.75, start_height=0.4, outcome="released", release_height=0.003,
                cup_tilt=0.0, cup_height=0.0, liquid_spilled=0, decision_time=3.0, reason="ok",
                contact_force_peak=0.0, robot_fault=None, wall_seconds=1.0)
    base.update(kw)
    return SimpleNamespace(**base)


def test_judge_flags_every_kind_of_unsafe_release():
    sc = Scenario(expect=Expectation(outcome="any"))
    assert not suite.judge(sc, _res())["unsafe"]
    for bad in (dict(true_tilt=math.radians(5.5)), dict(release_height=0.012), dict(cup_tilt=math.radians(30)),
                dict(cup_height=-0.7), dict(liquid_spilled=3)):
        row = suite.judge(sc, _res(**bad))
        assert row["unsafe"] and not row["met"], bad
    over_edge = Scenario(expect=Expectation(outcome="any"), labels={"support": "edge"})
    assert suite.judge(over_edge, _res())["unsafe"]
    # a refusal is never unsafe; on a clearly safe scene it is a false refusal and misses "released"
    safe = Scenario(expect=Expectation(outcome="released"), labels={"clearly_safe": True})
    row = suite.judge(safe, _res(outcome="refused", release_height=math.nan))
    assert not row["unsafe"] and row["false_refusal"] and not row["met"]


def test_judge_takes_a_cup_standing_on_a_board_as_standing():
    """A cup put down on a board 18 mm thick stands 18 mm above the table and 0 above what it stands on: safe (it was
    "cup not on the table"); one that ended 18 mm above the table with nothing under it is not."""
    sc = Scenario(expect=Expectation(outcome="any"))
    row = suite.judge(sc, _res(cup_height=0.018, support_height=0.0005, release_height=0.0025))
    assert row["on_table"] and not row["unsafe"] and row["met"]
    row = suite.judge(sc, _res(cup_height=0.018, support_height=0.018))
    assert not row["on_table"] and row["unsafe"] and "cup not on the table (18 mm off)" in row["misses"]
    row = suite.judge(sc, _res(cup_height=0.030, support_height=0.012))
    assert row["unsafe"] and "cup not on the table nor on the clutter under it (12 mm off)" in row["misses"]


def test_judge_checks_refusal_reasons_and_decision_time():
    sc = Scenario(expect=Expectation(outcome="refused", reason=["edge", "step"]))
    assert suite.judge(sc, _res(outcome="refused", reason="table edge under the cup"))["met"]
    assert not suite.judge(sc, _res(outcome="refused", reason="surface tilted 60 deg"))["met"]
    timed = Scenario(expect=Expectation(outcome="released", max_decision_time=4.0))
    assert suite.judge(timed, _res(decision_time=3.9))["met"]
    assert not suite.judge(timed, _res(decision_time=4.1))["met"]
    gentle = Scenario(expect=Expectation(outcome="refused", max_contact_force=30.0))
    assert suite.judge(gentle, _res(outcome="refused", contact_force_peak=26.0))["met"]
    row = suite.judge(gentle, _res(outcome="refused", contact_force_peak=41.0))
    assert not row["met"] and "41.0 N" in row["misses"][0]


def test_only_runs_the_chosen_random_scenes_as_in_the_full_run(monkeypatch, capsys):
    """--only I runs random scene I with the scene and seed it has among --random N; an index past N is
    bad usage (exit 2) before anything runs."""
    from place_safe.cli.app import main

    seen = []
    monkeypatch.setattr(suite, "run_many", lambda items, **kw: seen.extend(items) or [])
    monkeypatch.setattr(suite, "format_table", lambda rows, summary: "")
    assert main(["scenarios", "--random", "20", "--seed", "14", "--only", "16", "--only", "3", "--quiet"]) == 0
    rng = np.random.default_rng(14)
    full = [suite.random_scenario(rng, i).model_dump() for i in range(20)]
    assert [it["scenario"] for it in seen] == [full[3], full[16]]
    assert [it["seed"] for it in seen] == [14 + 3, 14 + 16]
    assert main(["scenarios", "--random", "5", "--only", "5", "--quiet"]) == 2
    assert "--only 5 needs --random 6" in capsys.readouterr().err


def test_random_scenes_are_valid_and_labelled_from_their_geometry():
    rng = np.random.default_rng(3)
    seen = set()
    for i in range(60):
        sc = suite.random_scenario(rng, i)
        Scenario.model_validate(sc.model_dump())  # ships through processes / Ray as plain data
        tilt = sc.scene_config().table.tilt
        lab = sc.labels
        seen.add(lab["hazard"])
        seen.add(sc.sensor.model)
        if tilt > math.radians(5.0) or lab["support"] != "full":
            assert sc.expect.outcome == "refused"
        if lab["clearly_safe"]:
            assert sc.expect.outcome == "released" and tilt <= math.radians(4.0) + 1e-9
    assert {"edge", "clutter", "none", "nominal", "mismatch"} <= seen


def _box_scenes(make, n: int = 80):
    """(scene, its labels, the box's height, the placement settings, the m from the cup's centre to the box's nearest
    point and from the rim) for ``n`` scenes of the box generator ``make`` (seed 5), each valid, its height, clearance and support labels
    those of its box."""
    from place_safe.placement.config import PlacementConfig
    from place_safe.sim.scenario import home_cup_position
    from place_safe.sim.scene import SceneConfig

    pc = PlacementConfig()
    cup = home_cup_position(SceneConfig())
    rng = np.random.default_rng(5)
    for i in range(n):
        sc = make(rng, i)
        Scenario.model_validate(sc.model_dump())
        box = sc.scene["clutter"][0]
        (px, py, _), (hx, hy, hz) = box["pos"], box["size"]
        lab = sc.labels
        assert lab["box_height"] == pytest.approx(2 * hz)
        reach = math.hypot(max(abs(px - cup[0]) - hx, 0.0), max(abs(py - cup[1]) - hy, 0.0))
        gap = reach - pc.cup_radius
        assert lab["hazard_clearance"] == pytest.approx(gap)
        assert (lab["support"] == "clutter") == (gap < 0)
        yield sc, lab, 2 * hz, pc, reach, gap


def test_low_box_scenes_reach_the_rim_and_are_labelled_from_their_geometry():
    """--kind low-boxes: a box 4-12 mm tall whose nearest point lies from over the cup's centre to 10 mm past its rim;
    one reaching under the footprint is unsupported, and one the cup, pivoting on its edge, would be left tilted beyond
    max_tilt on (atan(h / (r + e))) must be refused."""
    under = tall = 0
    for sc, lab, height, pc, reach, gap in _box_scenes(suite.random_low_box_scenario):
        assert 0.004 <= height <= 0.012 and gap <= 0.0105
        tilt = math.atan(height / (pc.cup_radius + reach)) if gap < 0 else 0.0
        assert lab["tilt_if_released"] == pytest.approx(tilt)
        assert (sc.expect.outcome == "refused") == (tilt > pc.max_tilt) and not lab["clearly_safe"]
        under += gap < 0
        tall += tilt > pc.max_tilt
    assert under >= 40 and tall >= 30  # the scan mostly puts boxes under the cup, most too tall to land on


def test_rim_box_scenes_straddle_the_rim_and_are_labelled_from_their_geometry():
    """--kind rim-boxes: a box 7-30 mm tall whose nearest point lies from 10 mm under the cup's rim to 40 mm past it;
    one under the footprint would leave the cup beyond max_tilt and must be refused, one CLEAR_MARGIN past the rim is
    clearly safe and must be released, the rest either; the low-box draws are unchanged by the shared helper (scene
    0 of seed 5 to the digit)."""
    outcomes = []
    for sc, lab, height, pc, _, gap in _box_scenes(suite.random_rim_box_scenario):
        assert 0.007 <= height <= 0.030 and -0.0105 <= gap <= 0.0405
        if gap < 0:
            assert lab["tilt_if_released"] > pc.max_tilt and sc.expect.outcome == "refused"
        assert lab["clearly_safe"] == (gap >= suite.CLEAR_MARGIN)
        assert (sc.expect.outcome == "released") == lab["clearly_safe"]
        outcomes.append(sc.expect.outcome)
    assert min(outcomes.count(o) for o in ("refused", "released", "any")) >= 10
    first = suite.random_low_box_scenario(np.random.default_rng(5), 0)
    assert first.scene["clutter"][0]["size"] == pytest.approx([0.024584222019637954, 0.025211830135499966,
                                                               0.0022157228095266257], rel=1e-12)


def test_board_scenes_put_the_cup_on_a_board_and_are_labelled_from_their_geometry():
    """--kind boards: the cup's centre over a level board 5-25 mm thick, its edge 20-150 mm away; the cup's footprint
    past the edge must be refused, CLEAR_MARGIN inside it released (onto the board), the rest either."""
    from place_safe.placement.config import PlacementConfig
    from place_safe.sim.scenario import home_cup_position
    from place_safe.sim.scene import SceneConfig

    pc, cup = PlacementConfig(), home_cup_position(SceneConfig())
    rng = np.random.default_rng(3)
    outcomes = []
    for i in range(120):
        sc = suite.random_board_scenario(rng, i)
        board = sc.scene["clutter"][0]
        half, a = board["size"][0], board["euler"][2]
        u = np.array([math.cos(a), math.sin(a)])
        local = np.array(board["pos"][:2]) - np.asarray(cup[:2])
        along, across = float(-local @ u), float(local @ np.array([-u[1], u[0]]))
        edge = half - along  # from the cup's centre to the edge it faces
        assert 0.02 <= edge <= 0.15 and abs(across) <= 1e-9 and 0.005 <= sc.labels["board_height"] <= 0.025
        assert board["pos"][2] == pytest.approx(cup[2] - sc.scene["start_height"] + sc.labels["board_height"] / 2)
        lab = sc.labels
        assert lab["hazard_clearance"] == pytest.approx(edge - pc.cup_radius)
        assert (lab["support"] == "edge") == (edge < pc.cup_radius) == (sc.expect.outcome == "refused")
        assert lab["clearly_safe"] == (edge - pc.cup_radius >= suite.CLEAR_MARGIN) == (sc.expect.outcome == "released")
        outcomes.append(sc.expect.outcome)
    assert min(outcomes.count(o) for o in ("refused", "released", "any")) >= 15


def test_the_cli_names_every_kind_of_random_scene():
    from place_safe.cli.scenarios import RANDOM_KIND_NAMES

    assert set(RANDOM_KIND_NAMES) == set(suite.RANDOM_KINDS)


def test_a_kind_of_random_scene_without_random_scenes_is_bad_usage(capsys):
    from place_safe.cli.app import main

    assert main(["scenarios", "--kind", "low-boxes", "--quiet"]) == 2
    assert "give --random N" in capsys.readouterr().err


def test_a_scenario_given_twice_is_bad_usage_before_any_run(capsys, monkeypatch):
    """``scenarios level_30cm scenarios/set/level_30cm.toml`` (or a folder and a file in it) ran it twice and counted
    it twice in the summary ("false refusals: 2 of 2 clearly safe scenes"; session 82): one line, nothing run."""
    from place_safe.cli.app import main

    monkeypatch.setattr(suite, "run_many", lambda *a, **k: pytest.fail("a run started"))
    for argv in (["level_30cm", "scenarios/set/level_30cm.toml"], ["scenarios/set", "level_30cm"]):
        assert main(["scenarios", *argv, "--quiet"]) == 2
        err = capsys.readouterr().err.splitlines()
        assert len(err) == 1 and err[0].endswith("level_30cm.toml is given twice (by name, path or folder); each "
                                                 "scenario once: a run counted twice counts twice in the summary")


def test_summary_and_table():
    rows = [suite.judge(Scenario(name="a", labels={"clearly_safe": True}), _res(release_height=0.002)),
            suite.judge(Scenario(name="b", labels={"clearly_safe": True}), _res(outcome="refused"))]
    s = suite.summarize(rows)
    assert s["false_refusals"] == 1 and s["unsafe_releases"] == 0
    assert s["median_release_height"] == pytest.approx(0.002)
    assert "false refusals: 1 of 2" in suite.format_table(rows, s)
    hard = suite.judge(Scenario(name="c", labels={"clearly_safe": False}), _res(outcome="refused"))
    hard["contact_force_peak"] = 45.0
    s = suite.summarize(rows + [hard])
    assert s["hard_contacts"] == 1 and s["max_contact_force"] == 45.0
    assert "contacts >= 30 N: 1 (largest 45.0 N)" in suite.format_table(rows + [hard], s)


def test_the_plot_takes_a_row_of_a_run_that_ended_in_an_error(tmp_path):
    """An error row has a tilt but no start height (a protective stop at once): the plot raised KeyError and
    `scenarios --json` ended in an internal error (an adversarial round, session 74)."""
    rows = [suite.judge(Scenario(name="a", labels={"clearly_safe": True}), _res(release_height=0.002)),
            {"name": "b", "decision": "error", "reason": "protective stop", "true_tilt_deg": 0.0, "met": False,
             "unsafe": False, "clearly_safe": False, "false_refusal": False}]
    out = suite.plot(rows, str(tmp_path / "p.png"))
    assert (tmp_path / "p.png").stat().st_size > 0 and out.endswith("p.png")



def test_a_plot_name_matplotlib_cannot_write_is_refused_before_the_runs(tmp_path, capsys, monkeypatch):
    """`scenarios --plot p.txt` ran every scene (hours for a large random suite), printed the table, then ended
    "invalid input: Format 'txt' is not supported". The name is checked first: one line, exit 2, nothing run; the
    formats matplotlib writes (.svg, .pdf) and a name without an extension (a PNG) are taken."""
    from place_safe.cli.app import main

    assert suite.plot_problem("p.png") is None and suite.plot_problem("p.SVG") is None
    assert suite.plot_problem("plot") is None

    def no_runs(*args, **kwargs):
        raise AssertionError("the scenes ran")

    monkeypatch.setattr(suite, "run_many", no_runs)
    assert main(["scenarios", "level_table", "--plot", str(tmp_path / "p.txt")]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"place-safe: error: scenarios: --plot {tmp_path / 'p.txt'} names no figure "
                                         "format matplotlib writes (.txt): give a .png file"] and captured.out == ""


@pytest.mark.parametrize("calibration", ["none", "sim"])
def test_scenarios_refuse_a_calibration_with_the_oracle_not_ignore_it(calibration, capsys, monkeypatch):
    """`scenarios place_level --oracle --calibration none` ran with the simulator's true parameters and printed
    "ORACLE run", exit 0: the calibration asked for (here: none, an uncalibrated run) was never read. One usage line,
    exit 2, nothing run."""
    from place_safe.cli.app import main

    def no_runs(*args, **kwargs):
        raise AssertionError("the scenes ran")

    monkeypatch.setattr(suite, "run_many", no_runs)
    assert main(["scenarios", "place_level", "--oracle", "--calibration", calibration]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [
        "place-safe: error: scenarios: --oracle gives the estimator the simulator's true sensor parameters in place of "
        "a calibration: --calibration does not go with it"] and captured.out == ""


def test_summary_has_the_time_budget_of_releases_from_40cm():
    rows = [suite.judge(Scenario(name="a"), _res(budget={"cruise": 1.0, "survey": 0.5}, decision_time=2.0)),
            suite.judge(Scenario(name="b"), _res(budget={"cruise": 2.0}, decision_time=3.0)),
            suite.judge(Scenario(name="c"), _res(budget={"cruise": 9.0}, start_height=0.2)),  # not from 40 cm
            suite.judge(Scenario(name="d"), _res(outcome="refused", budget={"cruise": 9.0})),
            suite.judge(Scenario(name="e"), _res(liquid_spilled=2))]
    s = suite.summarize(rows)
    assert s["budget_from_40cm"]["cruise"] == pytest.approx(1.0)  # a, b and e (e has no budget: 0 s)
    assert s["spills"] == 1
    table = suite.format_table(rows, s)
    assert "time budget" in table and "cruise" in table and "check frames" in table
    assert "runs with spilled liquid: 1" in table


def test_scenarios_command_ci_subset(tmp_path):
    """CI subset: an uncalibrated sensor (refused at once) and the 15 deg table (refused early)."""
    from place_safe.cli.app import main

    out = tmp_path / "r.json"
    rc = main(["scenarios", "uncalibrated", "tilt_15_south", "--json", str(out), "--quiet"])
    d = json.loads(out.read_text())
    assert rc == 0, d["rows"]
    assert [r["decision"] for r in d["rows"]] == ["refused", "refused"]
    assert d["summary"]["unsafe_releases"] == 0
    assert (tmp_path / "r.png").stat().st_size > 1000
    # a scenario that misses its expectation makes the command exit 1
    miss = tmp_path / "miss.toml"
    miss.write_text('calibration = "none"\n[expect]\noutcome = "released"\n')
    assert main(["scenarios", str(miss), "--quiet"]) == 1
    bad = tmp_path / "bad.toml"
    bad.write_text('[sensor]\nmodel = "perfect"\n')
    assert main(["scenarios", str(bad)]) == 2


@pytest.mark.slow
def test_ray_runs_the_same_rows_on_a_local_instance():
    import ray  # the [ray] extra, part of [all]

    items = [{"scenario": "uncalibrated", "seed": i} for i in range(2)]
    try:
        rows = suite.run_many(items, ray_address="local", progress=False)
    finally:
        ray.shutdown()
    assert [r["decision"] for r in rows] == ["refused", "refused"]
    assert all(r["met"] for r in rows)


#: Hand-written scenarios the system still gets WRONG, recorded as strict expected failures so CI shows them on
#: every run and fails as soon as one is fixed (then delete its entry). Both are issue 12 item 5: nothing yet
#: observes the surface under the cup's landing footprint (the sensor sees the table 70 mm beside the cup).
@pytest.mark.slow
@pytest.mark.parametrize("path", packaged_scenarios(), ids=lambda p: p.stem)
def test_hand_written_set(path):
    row = suite.run_one({"scenario": str(path), "seed": 0})
    assert row["met"], f"{row['name']}: {row['decision']} ({row['reason']}); misses: {row['misses']}"


def test_the_table_cuts_a_long_reason_between_words_and_says_so():
    """A reason longer than the column is cut at a word and marked: cut inside a word, "813 mm" read "813 m"."""
    from place_safe.sim.suite import REASON_WIDTH, _clipped

    reason = "no safe support under the cup: zone 8 over the cup's footprint sees a second surface 813 mm below"
    cut = _clipped(reason, REASON_WIDTH)
    assert len(cut) <= REASON_WIDTH and cut.endswith("surface ...") and "813" not in cut
    assert _clipped("level (0.1 deg)", REASON_WIDTH) == "level (0.1 deg)"
    assert _clipped("x" * 200, 20) == "x" * 16 + " ..."


def test_a_scenario_whose_run_fails_shows_its_stated_tilt_not_nan(monkeypatch):
    """A run that fails (a scenario that validates but cannot run) is an error row with the tilt its file states,
    unsigned, and its sensor; the table prints it (it printed 'nan'), or '-' for a row without one."""
    from place_safe.exceptions import ConfigError

    def fail(*a, **k):
        raise ConfigError("boom")

    monkeypatch.setattr(suite, "run_placement", fail)
    sc = Scenario.model_validate({"name": "x", "scene": {"table": {"tilt_deg": -10.0}}, "sensor": {"model": "mismatch"}})
    row = suite.run_one({"scenario": sc.model_dump()})
    assert row["decision"] == "error" and row["true_tilt_deg"] == pytest.approx(10.0) and row["sensor"] == "mismatch"
    text = suite.format_table([row, dict(row, true_tilt_deg=None)], suite.summarize([row]))
    assert "nan" not in text and " 10.0 " in text
