"""``place-safe recover``, ``evaluate``, ``stream`` (``place_safe.cli.sensing``): options that go together."""

from __future__ import annotations

import pytest

from place_safe.cli.app import main


@pytest.mark.parametrize("given,said", [(["--no-fallback"], "--no-fallback applies"),
                                        (["--diff-mode", "paper"], "--diff-mode applies"),
                                        (["--no-fallback", "--diff-mode", "fast"], "--no-fallback and --diff-mode apply")])
def test_evaluate_refuses_diff_options_when_diff_is_not_evaluated(sweep_path, tmp_path, capsys, given, said):
    """`evaluate --methods peak --no-fallback` (or `--diff-mode paper`) printed peak's table as if the option had not
    been given, exit 0; so did a calibration without a diff section, which leaves diff out of the default methods.
    Both options set the diff method: without it they are one usage line, exit 2, before any frame is recovered."""
    rep = tmp_path / "r.json"
    assert main(["evaluate", str(sweep_path), "--methods", "peak", "proprietary", "--no-plots", "--json", str(rep),
                 *given]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"place-safe: error: evaluate: {said} to the diff method, which is not among "
                                         "the methods evaluated (peak, proprietary): name it in --methods"]
    assert captured.out == "" and not rep.exists()
