"""place-safe bench robot / contact-bench: the rest noise measured and written to a robot file, one-line errors,
and a refused connection is one line with ur_rtde's own chatter kept off the terminal."""

from __future__ import annotations

import pytest

from place_safe.cli.app import main
from place_safe.drivers.ur5 import URConfig, packaged_config


def test_bench_on_the_fake_measures_cb3_noise_and_writes_the_setting(tmp_path, capsys):
    out = tmp_path / "mine.toml"
    assert main(["bench", "robot", "--fake", "--robot", str(packaged_config("real")), "--seconds", "1",
                 "--cycles", "20000", "--write", str(out)]) == 0
    text = capsys.readouterr().out
    assert "spread" in text and "false alarms" in text and "threshold" in text
    cfg = URConfig.load(out)
    assert 2.5 < cfg.contact.noise_std < 5.0 and cfg.contact.measured["controller"] == "cb3"
    assert cfg.connection.host == URConfig.load(packaged_config("real")).connection.host  # the rest is kept


def test_bench_write_keeps_the_robot_files_comments_and_changes_only_the_contact_section(tmp_path, capsys):
    """The robot file was rewritten from the model: the user's comments were lost."""
    mine = tmp_path / "mine.toml"
    mine.write_text(packaged_config("real").read_text())
    before = mine.read_text().splitlines()
    assert main(["bench", "robot", "--fake", "--robot", str(mine), "--seconds", "1", "--cycles", "2000",
                 "--write", str(mine)]) == 0
    after = mine.read_text().splitlines()
    assert after[:len(before)] == before  # every line kept, the [contact] section last
    assert after[len(before)].startswith("noise_std = ") and "[contact.measured]" in after


def test_bench_needs_a_robot_file(capsys):
    assert main(["bench", "robot"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--robot" in err[0]


def test_the_fakes_robot_file_is_read_and_checked_before_measuring(tmp_path, capsys):
    """With --fake the --robot file went unread: a missing, empty or NaN one measured and exited 0 (an adversarial
    round, session 74)."""
    bad = tmp_path / "nan.toml"
    bad.write_text(packaged_config("sim").read_text().replace("max_linear_speed = 0.5", "max_linear_speed = nan"))
    assert bad.read_text() != packaged_config("sim").read_text()
    for path in (tmp_path / "missing.toml", bad):
        assert main(["bench", "robot", "--fake", "--robot", str(path), "--seconds", "0.2", "--cycles", "1000"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(path) in err[0]


def test_a_refused_connection_is_one_line(tmp_path, capfd):
    cfg = URConfig.load(packaged_config("real"))
    cfg.connection.host = "127.0.0.1"
    cfg.connection.connect_timeout_s = 3.0
    path = tmp_path / "local.toml"
    path.write_text(cfg.to_toml())
    code = main(["bench", "robot", "--robot", str(path), "--seconds", "0.1"])
    out, err = capfd.readouterr()
    assert code != 0
    lines = [ln for ln in (out + err).splitlines() if ln.strip()]
    assert len(lines) == 1, lines
    assert "connect: Connection refused" not in lines[0] or lines[0].startswith("place-safe")


def test_contact_bench_small_run_reports_every_figure(capsys):
    assert main(["bench", "contact", "--descents", "1", "--touch-trials", "2", "--cycles", "20000",
                 "--height", "0.1", "-q"]) == 0
    text = capsys.readouterr().out
    assert "false alarms" in text and "guarded touches" in text and "1 descents of 10 cm" in text
    assert "watchdog stops 0, script errors 0" in text


def test_bench_write_without_a_robot_file_is_refused_before_measuring(tmp_path, capsys):
    """--write to a new file with --fake and no --robot has nothing to start the file from: a usage error before the
    measurement (it came after it), and no output printed."""
    assert main(["bench", "robot", "--fake", "--seconds", "1", "--write", str(tmp_path / "new.toml")]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "give --robot ROBOT.toml" in captured.err


def test_bench_write_to_an_existing_robot_file_keeps_it_and_sets_the_noise(tmp_path, capsys):
    """With --fake and no --robot, the file written to is the one started from (the stand-in's own settings, host
    127.0.0.1, overwrote it)."""
    out = tmp_path / "mine.toml"
    out.write_text(URConfig.load(packaged_config("real")).to_toml())
    assert main(["bench", "robot", "--fake", "--seconds", "1", "--cycles", "2000", "--write", str(out)]) == 0
    cfg = URConfig.load(out)
    assert cfg.connection.host == URConfig.load(packaged_config("real")).connection.host and cfg.contact.noise_std > 0


@pytest.mark.parametrize("given,said", [
    (["--descents", "0", "--height", "0.1"], "--height goes with --descents, and --descents 0"),
    (["--descents", "0", "--seed", "3", "--jobs", "2"], "--seed and --jobs go with --descents, and --descents 0"),
    (["--touch-trials", "0", "--stiffness", "5000"], "--stiffness goes with --touch-trials, and --touch-trials 0")])
def test_contact_bench_refuses_options_of_a_part_it_does_not_run(given, said, capsys, monkeypatch):
    """`bench contact --descents 0 --height 0.1` (or --seed, --jobs) and `--touch-trials 0 --stiffness 5000` printed
    the detector's report, exit 0: the part the option sets ran not at all. One usage line, exit 2, before anything
    runs; where the part runs they are read (defaults 0.4 m, seed 0, 1 job, 20000 N/m)."""
    import place_safe.evaluation.contact as contact

    def ran(*args, **kwargs):
        raise AssertionError("the bench ran")

    monkeypatch.setattr(contact, "settings_report", ran)
    assert main(["bench", "contact", *given, "--cycles", "1000"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == [f"place-safe: error: bench contact: {said} runs none"]
    seen = []
    monkeypatch.setattr(contact, "settings_report", lambda *a, **k: {})
    monkeypatch.setattr(contact, "format_settings_report", lambda rep: "report")
    monkeypatch.setattr(contact, "touches", lambda **k: seen.append(("touches", k["stiffness"])) or [])

    class Descents:
        reasons: list = []

        def summary(self):
            return "descents"

    monkeypatch.setattr(contact, "descents", lambda n, **k: seen.append((k["height"], k["seed"], k["jobs"]))
                        or Descents())
    assert main(["bench", "contact", "--descents", "1", "--touch-trials", "1", "--cycles", "1000", "-q"]) == 0
    assert main(["bench", "contact", "--descents", "1", "--touch-trials", "1", "--cycles", "1000", "-q", "--height",
                 "0.1", "--seed", "3", "--jobs", "2", "--stiffness", "5000"]) == 0
    assert seen == [("touches", 20000.0), (0.4, 0, 1), ("touches", 5000.0), (0.1, 3, 2)]


def test_bench_robot_refuses_a_controller_for_the_arm(tmp_path, capsys, monkeypatch):
    """`bench robot --robot real.toml --controller e-series` went on to connect to the arm as the file's cb3:
    --controller chooses the fake (--fake) and was never read for the arm. One usage line, exit 2, before connecting;
    with --fake it is read (default cb3)."""
    import place_safe.drivers.ur5 as ur5

    def no_arm(*args, **kwargs):
        raise AssertionError("the arm was connected")

    monkeypatch.setattr(ur5, "URRobot", no_arm)
    assert main(["bench", "robot", "--robot", str(packaged_config("real")), "--controller", "e-series",
                 "--seconds", "0.1"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "place-safe: error: bench robot: --controller is the fake controller's (with --fake); the arm's is its robot "
        "file's [connection] controller"]
    monkeypatch.undo()  # (the fake's stand-in is a URRobot too)
    assert main(["bench", "robot", "--fake", "--controller", "e-series", "--seconds", "0.1", "--cycles", "1000"]) == 0
    assert capsys.readouterr().out.startswith("fake e-series at ")
