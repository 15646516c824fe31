"""``place-safe bench`` (``place_safe.cli.bench``): the options of ``bench sim``."""

from __future__ import annotations

import pytest

from place_safe.cli.app import main


@pytest.mark.parametrize("given,said", [(["--scene", "missing.json"], "--scene does"), (["--rig"], "--rig does"),
                                        (["--scene", "s.json", "--rig"], "--scene and --rig do"),
                                        (["--rate", "1"], "--rate does"), (["--rays", "1"], "--rays does"),
                                        (["--rig", "--rate", "30", "--rays", "8"], "--rig and --rate and --rays do")])
def test_bench_sim_bare_refuses_the_scene_and_sensor_options_it_never_reads(given, said, capsys, monkeypatch):
    """`bench sim --bare --scene missing.json` measured the bare robot and exited 0: a scene file that does not exist
    was never read, nor was --rig; nor `--rate 1 --rays 1`, with no sensor to run at a rate or cast rays (round 15's
    leftover). With --bare each is one usage line, exit 2, nothing measured; the values of the defaults too (given is
    given)."""
    pytest.importorskip("mujoco")
    import place_safe.sim.bench as sim_bench

    def no_bench(*args, **kwargs):
        raise AssertionError("the benchmark ran")

    monkeypatch.setattr(sim_bench, "benchmark", no_bench)
    assert main(["bench", "sim", "--bare", "--seconds", "0.1", *given]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"place-safe: error: bench sim: --bare measures the bare robot, without a scene or sensor: {said} not go "
        "with it"]


def test_bench_sim_runs_the_sensor_at_its_rate_and_rays_given_or_default(capsys, monkeypatch):
    """Without --bare, --rate and --rays are the simulated sensor's (default 30 Hz and 8)."""
    pytest.importorskip("mujoco")
    import place_safe.sim.bench as sim_bench

    calls = []

    def fake(scene, rig, seconds, rate, rays):
        calls.append((rate, rays))
        return {"sim_seconds": seconds, "wall_seconds": 1.0, "real_time_factor": seconds, "frames": 1,
                "physics_steps": 1, "with_robot": not rig}

    monkeypatch.setattr(sim_bench, "bench", fake)
    assert main(["bench", "sim", "--rig", "--seconds", "0.1"]) == 0
    assert main(["bench", "sim", "--rig", "--seconds", "0.1", "--rate", "10", "--rays", "2"]) == 0
    assert calls == [(30.0, 8), (10.0, 2)]
    assert "at 30 Hz" in capsys.readouterr().out
