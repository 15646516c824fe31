"""``place-safe bench`` (``place_safe.cli.bench``): the options of ``bench sim``."""

from __future__ import annotations

import pytest

from place_safe.cli.app import main


@pytest.mark.parametrize("given,said", [(["--scene", "missing.json"], "--scene does"), (["--rig"], "--rig does"),
                                        (["--scene", "s.json", "--rig"], "--scene and --rig do")])
def test_bench_sim_bare_refuses_the_scene_options_it_never_reads(given, said, capsys, monkeypatch):
    """`bench sim --bare --scene missing.json` measured the bare robot and exited 0: a scene file that does not exist
    was never read, nor was --rig. With --bare they are one usage line, exit 2, nothing measured."""
    pytest.importorskip("mujoco")
    import place_safe.sim.bench as sim_bench

    def no_bench(*args, **kwargs):
        raise AssertionError("the benchmark ran")

    monkeypatch.setattr(sim_bench, "benchmark", no_bench)
    assert main(["bench", "sim", "--bare", "--seconds", "0.1", *given]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"place-safe: error: bench sim: --bare measures the bare robot, without a scene or sensor: {said} not go "
        "with it"]
