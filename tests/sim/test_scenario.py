"""Scenario files: schema validation, the hand-written set, calibration required, the mismatched sensor."""

from __future__ import annotations

import json
import math

import pytest

pytest.importorskip("mujoco")

from place_safe.calibration import Calibration, uncalibrated_reason  # noqa: E402
from place_safe.config import parse_config  # noqa: E402
from place_safe.exceptions import ConfigError  # noqa: E402
from place_safe.sim.scenario import (Scenario, home_cup_position, load_scenario,  # noqa: E402
                                     packaged_scenarios)


def test_every_packaged_scenario_validates_and_the_set_covers_the_issue():
    names = {p.stem for p in packaged_scenarios()}
    assert len(names) >= 30
    for must in ("level_10cm", "level_40cm", "tilt_4p9_west", "tilt_5p1_south", "tilt_15_south", "dark_table",
                 "checker_table", "glossy_table", "edge_under_cup", "clutter_under_cup", "dropouts",
                 "latency_spikes", "table_rises", "table_drops", "protective_stop", "level_mismatch_40cm"):
        assert must in names
    for p in packaged_scenarios() + packaged_scenarios(""):
        sc = load_scenario(p)
        sc.scene_config()
    assert load_scenario("place_level").expect.outcome == "released"
    assert load_scenario("place_tilted").expect.outcome == "refused"


def test_degrees_start_height_and_sensor_sections_become_si(tmp_path):
    f = tmp_path / "s.toml"
    f.write_text('[scene]\nstart_height = 0.2\ntable.tilt_deg = 4.9\ntable.tilt_direction_deg = 90\n'
                 '[sensor]\nmodel = "mismatch"\nseed = 5\ndrop_prob = 0.1\n[expect]\noutcome = "any"\n')
    sc = load_scenario(f)
    cfg = sc.scene_config()
    assert cfg.table.tilt == pytest.approx(math.radians(4.9))
    assert cfg.table.tilt_direction == pytest.approx(math.pi / 2)
    # start_height is measured along the vertical under the cup, on the tilted top
    cup, t = home_cup_position(cfg), cfg.table
    n = (math.sin(t.tilt) * math.cos(t.tilt_direction), math.sin(t.tilt) * math.sin(t.tilt_direction), math.cos(t.tilt))
    under = t.height - (n[0] * (cup[0] - t.center[0]) + n[1] * (cup[1] - t.center[1])) / n[2]
    assert cup[2] - under == pytest.approx(0.2)
    tof = sc.sensor.tof_config(seed=99)
    assert tof.seed == 5 and tof.drop_prob == 0.1  # the scenario's own seed is kept
    assert sc.name == "s"


@pytest.mark.parametrize("data, words", [
    ({"scene": {"table": {"tilt": 0.1, "tilt_deg": 5}}}, "not both"),
    ({"scene": {"tabel": {}}}, "scene: tabel: unknown key"),
    ({"sensor": {"drop_prob": 1.5}}, "sensor.drop_prob"),
    ({"sensor": {"model": "perfect"}}, "sensor.model"),
    ({"expect": {"outcome": "maybe"}}, "expect.outcome"),
    ({"placement": {"max_tilt": -1}}, "max_tilt"),
    ({"method": "magic"}, "method"),
    ({"scene": {"start_height": 5.0}}, "start_height"),
    ({"surprise": 1}, "surprise"),
])
def test_bad_scenarios_give_one_line_errors(data, words):
    with pytest.raises(ConfigError) as e:
        parse_config(Scenario, data, "scenario x")
    msg = str(e.value)
    assert "\n" not in msg and words in msg


def test_bad_files_give_one_line_errors(tmp_path):
    f = tmp_path / "bad.toml"
    f.write_text("[scene\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_scenario(f)
    j = tmp_path / "nan.json"
    j.write_text(json.dumps({"scene": {"table": {"height": float("nan")}}}))
    with pytest.raises(ConfigError):
        load_scenario(j)
    with pytest.raises(ConfigError, match="not found"):
        load_scenario(tmp_path / "missing.toml")
    f.write_text("[scene.table]\ntilt_deg = 90\n")  # said in degrees, as given (it was said in rad)
    with pytest.raises(ConfigError, match="tilt_deg must be between -90 and 90 deg"):
        load_scenario(f)
    f.write_text("[scene.table]\ntilt_deg = 2\ntilt_direction_deg = 400\n")  # (it was said in rad: "<= 6.28 rad")
    with pytest.raises(ConfigError, match="tilt_direction_deg must be between -360 and 360 deg, got 400"):
        load_scenario(f)
    for text in ("", "# a comment only\n", 'name = "x"\ndescription = "y"\n'):  # an empty file ran the default scene
        f.write_text(text)
        with pytest.raises(ConfigError, match="sets nothing"):
            load_scenario(f)


@pytest.mark.parametrize("name, bad", [("evil\x1b[31mRED", "\x1b"), ("two\nlines", "\n"), ("bidi\u202eevil", "\u202e"),
                                       ("tab\tname", "\t"), ("nul\x00", "\x00")])
def test_a_name_with_control_characters_is_refused_in_one_line(name, bad, tmp_path, capsys):
    """An escape sequence or a newline in a scenario's name was echoed raw into the scenarios table; it is refused
    when the file is read (the name also goes into file names), and the message shows it escaped."""
    from place_safe.cli.app import main

    f = tmp_path / "s.json"
    f.write_text(json.dumps({"name": name, "scene": {"start_height": 0.25}}))
    with pytest.raises(ConfigError) as e:
        load_scenario(f)
    assert str(e.value) == f"scenario {f}: name: must not contain control characters, got {bad!r} in {name!r}"
    assert main(["scenarios", str(f), "--quiet"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.splitlines() == [f"place-safe: error: {e.value}"]


def test_a_file_name_with_control_characters_is_refused_as_the_scenarios_name(tmp_path):
    """Without a name in the file the file's name is the scenario's: checked the same way; printable names pass."""
    f = tmp_path / "bell\x07.toml"
    f.write_text("[scene]\nstart_height = 0.25\n")
    with pytest.raises(ConfigError, match=r"name: must not contain control characters, got '\\x07' in 'bell\\x07'"):
        load_scenario(f)
    ok = tmp_path / "ok.toml"
    ok.write_text('name = "Café, 30 cm (level)"\n[scene]\nstart_height = 0.25\n')
    assert load_scenario(ok).name == "Café, 30 cm (level)"


def test_calibration_is_required_and_says_how():
    assert "place-safe calibrate" in uncalibrated_reason("diff", None)
    assert "built-in constants" in uncalibrated_reason("peak-naive", Calibration())
    assert uncalibrated_reason("peak", Calibration({"forward": {}})) is not None
    cal = Calibration.load(load_scenario("level_20cm").resolve_calibration()[0] and
                           __import__("place_safe.sim.calibration_capture", fromlist=["x"]).calibration_file())
    for m in ("diff", "peak", "proprietary"):
        assert uncalibrated_reason(m, cal) is None


def test_uncalibrated_placement_refuses_before_moving():
    from place_safe.sim.placement_run import run_placement

    res = run_placement(load_scenario("uncalibrated"))
    assert res.outcome == "refused" and res.frames == 0 and res.cup_held
    assert "place-safe calibrate" in res.reason
    assert res.calibration == "uncalibrated"


def test_default_calibration_is_the_user_calibration_not_the_oracle():
    from place_safe.sim.tof import true_params

    for model in ("nominal", "mismatch"):
        sc = Scenario(sensor={"model": model})
        cal, note = sc.resolve_calibration()
        assert "ORACLE" not in note and f"calibration_{model}" in note
        assert set(cal.sections) >= {"peak", "forward", "diff", "proprietary"}
        fw, tp = cal.forward(), true_params()
        assert fw.to_dict() != tp.to_dict()  # fitted, not copied from the simulator
    cal, note = Scenario(calibration="oracle").resolve_calibration()
    assert note.startswith("ORACLE")
    # diff's start and fallback (peak) is calibrated in the oracle too: a diff calibration without a peak section is
    # refused (round 15), and every --oracle placement was, before it moved (a review, session 85)
    from place_safe.calibration import uncalibrated_reason

    assert uncalibrated_reason("diff", cal) is None and cal.forward().to_dict() == true_params().to_dict()


@pytest.mark.parametrize("table, tilt_deg, direction_deg", [
    ({"tilt_deg": -10.0}, 10.0, 180.0),
    ({"tilt_deg": -10.0, "tilt_direction_deg": 90.0}, 10.0, 270.0),
    ({"tilt_deg": -10.0, "tilt_direction_deg": 300.0}, 10.0, 120.0),
    ({"tilt": -0.1, "tilt_direction": -math.pi}, math.degrees(0.1), 0.0),
    ({"tilt_deg": 10.0, "tilt_direction_deg": 90.0}, 10.0, 90.0),
])
def test_a_negative_table_tilt_leans_towards_the_opposite_azimuth(table, tilt_deg, direction_deg):
    """``table.tilt_deg = -10`` passed validation and failed when the scene was built (the scene builds 0 <= tilt):
    the run was an error row with tilt 'nan' (exit 1) and ``place --sim`` named neither file nor field. The tilt is
    signed along its azimuth, so -10 deg is the same top as 10 deg towards the azimuth + 180 deg."""
    sc = parse_config(Scenario, {"scene": {"table": table}, "expect": {"outcome": "any"}}, "scenario x")
    t = sc.scene_config().table
    assert t.tilt == pytest.approx(math.radians(tilt_deg))
    assert math.cos(t.tilt_direction) == pytest.approx(math.cos(math.radians(direction_deg)), abs=1e-12)
    assert math.sin(t.tilt_direction) == pytest.approx(math.sin(math.radians(direction_deg)), abs=1e-12)


def test_a_negatively_tilted_table_builds_as_the_opposite_lean():
    from place_safe.sim.scene import build_scene

    normals = []
    for table in ({"tilt_deg": -10.0, "tilt_direction_deg": 30.0}, {"tilt_deg": 10.0, "tilt_direction_deg": 210.0}):
        sc = parse_config(Scenario, {"scene": {"table": table}, "expect": {"outcome": "any"}}, "scenario x")
        scene = build_scene(sc.scene_config())
        normals.append(scene.table_plane_world(scene.make_data())[0])
    assert normals[0] == pytest.approx(normals[1], abs=1e-9)
    assert normals[0][2] == pytest.approx(math.cos(math.radians(10)))


def test_an_empty_calibration_name_is_said_to_be_empty(tmp_path):
    """``calibration = ""`` was read as the scenario's own directory ("calibration file  is a directory")."""
    f = tmp_path / "s.toml"
    f.write_text('calibration = ""\n[expect]\noutcome = "any"\n')
    with pytest.raises(ConfigError, match=f"scenario {f}: calibration is empty; expected one of sim, oracle, none") as e:
        load_scenario(f)
    assert "\n" not in str(e.value)


def test_a_table_moved_during_a_run_holds_the_cup_where_it_moved_to():
    """The table of a scenario with ``surface_motion`` rises 3 cm under a cup held 4 cm above its top, and the cup is
    let go: it lands on the risen top (1 cm of fall). (A table geom moved by
    editing the model kept its old place for contacts, and a released cup fell through it by the rise.)"""
    from place_safe.sim.scenario import TruthRecorder
    from place_safe.sim.world import sim_world

    sc = Scenario.model_validate({"scene": {"start_height": 0.04},
                                  "surface_motion": {"start": 0.0, "velocity": 0.03, "duration": 1.0}})
    assert sc.scene_config().table.movable
    world = sim_world(sc, seed=0, attach=False)
    robot = world.robot
    truth = TruthRecorder(sc, world.scene, robot)
    robot.add_step_callback(lambda *_: truth())
    truth()
    assert truth.cup_height() == pytest.approx(0.04, abs=2e-3)
    robot.step(1.1)  # the table has risen its 3 cm, stopping 1 cm under the cup
    assert truth.surface_moved == pytest.approx(0.03)
    assert truth.cup_height() == pytest.approx(0.01, abs=2e-3)
    robot.gripper(open=True)
    robot.step(0.8)
    assert abs(truth.cup_height()) < 3e-3  # standing on the risen top, not 3 cm into it


@pytest.mark.parametrize("edge, under", [(0.08, True), (-0.10, False), (0.02, True)])
def test_the_truth_measures_the_fall_to_a_board_under_the_cup(edge, under):
    """A cup held 30 mm above a level table with an 18 mm board whose edge lies ``edge`` from the cup's axis (beyond it
    the table): where the board reaches under the footprint the cup falls 12 mm onto it, and it ends standing on it;
    elsewhere the truth is the table's as before. (The truth measured the table only: a cup put down on a board read
    as released 20 mm up and "not on the table", so no board or tray scene could be judged safe.)"""
    from place_safe.sim.scenario import TruthRecorder, home_cup_position
    from place_safe.sim.scene import SceneConfig
    from place_safe.sim.world import sim_world

    cup = home_cup_position(SceneConfig())
    start, h, half = 0.03, 0.018, 0.12
    top = float(cup[2] - start)
    board = {"shape": "box", "pos": [float(cup[0] + edge - half), float(cup[1]), top + h / 2], "size": [half, half, h / 2]}
    sc = Scenario.model_validate({"scene": {"start_height": start, "clutter": [board]}})
    world = sim_world(sc, seed=0, attach=False)
    robot = world.robot
    truth = TruthRecorder(sc, world.scene, robot)
    robot.add_step_callback(lambda *_: truth())
    truth()
    assert truth.cup_height() == pytest.approx(start, abs=2e-3)
    expected = start - h if under else start
    assert truth.support_height() == pytest.approx(expected, abs=2e-3)
    robot.gripper(open=True)
    robot.step(0.8)
    assert truth.release_height == pytest.approx(expected, abs=2e-3)
    if under and edge > 0.05:  # wholly on the board: it stands on it
        assert abs(truth.support_height()) < 3e-3 and truth.cup_height() == pytest.approx(h, abs=3e-3)


@pytest.mark.parametrize("words", [[""], ["   "], ["tilt", ""]])
def test_an_empty_reason_word_is_refused(words):
    """An empty word is in every reason, so ``expect.reason = [""]`` was a check that could never fail (an adversarial
    round, session 74)."""
    from place_safe.exceptions import ConfigError

    with pytest.raises((ConfigError, ValueError), match="reason word must be non-empty"):
        Scenario.model_validate({"expect": {"outcome": "refused", "reason": words}})
    assert Scenario.model_validate({"expect": {"outcome": "refused", "reason": ["tilt"]}}).expect.reason == ["tilt"]


def test_a_mismatch_table_for_the_nominal_sensor_is_refused_not_ignored(tmp_path):
    """``[sensor.mismatch]`` without ``model = "mismatch"`` was taken and never read: the run used the nominal sensor
    and released, a scenario that believed it tested a mismatched one (round 14; as an ``uncertainty`` entry that was
    no method family's, round 8). One line saying which setting reads it; with the model the file loads as before."""
    f = tmp_path / "s.toml"
    f.write_text("[sensor.mismatch]\ntemp_start = 30.0\n")
    with pytest.raises(ConfigError, match=r'sensor: mismatch is read only by the mismatched sensor \(model = "mismatch"\)'):
        load_scenario(f)
    f.write_text('[sensor]\nmodel = "mismatch"\n[sensor.mismatch]\ntemp_start = 30.0\n')
    assert load_scenario(f).sensor.mismatch is not None



def test_a_relative_robot_model_is_read_from_the_scenarios_folder_as_its_calibration(tmp_path, monkeypatch):
    """``scene.robot_xml = "arm.xml"`` was looked for in the working folder, while the scenario's ``calibration`` is
    read from the scenario's own: the file next to the scenario ran from its folder and anywhere else ended "robot
    model 'arm.xml' not found or unusable: it does not exist". A relative model is now the scenario folder's."""
    from place_safe.assets import robots_dir

    folder = tmp_path / "scenes"
    folder.mkdir()
    (folder / "arm.xml").write_text((robots_dir() / "ur5" / "ur5.xml").read_text())
    (folder / "s.toml").write_text('[scene]\nrobot_xml = "arm.xml"\nstart_height = 0.1\n')
    monkeypatch.chdir(tmp_path)
    assert load_scenario(folder / "s.toml").scene_config().robot_xml == str(folder / "arm.xml")
    (folder / "s.toml").write_text('[scene]\nrobot_xml = "other.xml"\n')
    with pytest.raises(ConfigError, match=rf"robot model '{folder / 'other.xml'}' not found or unusable: it does not "
                                          "exist"):
        load_scenario(folder / "s.toml")

def test_a_file_that_is_not_a_table_of_settings_says_what_it_is(tmp_path):
    """A frame file given as a scenario (a JSON list) said "Input should be a valid dictionary or instance of
    Scenario" (pydantic's words, naming a class; round 14): it says what a scenario file is and what it got."""
    f = tmp_path / "frames.json"
    f.write_text("[]")
    with pytest.raises(ConfigError, match=r"frames\.json: expected an object of scenario settings \(a TOML table or a "
                                          r"JSON object\), got a JSON list"):
        load_scenario(f)
