"""The commands' shared helpers (``place_safe.cli.common``), through the commands that use them."""

from __future__ import annotations

import pytest

from place_safe.cli.app import main


@pytest.mark.parametrize("command", ["recover", "stream"])
@pytest.mark.parametrize("method", ["peak", "proprietary", "peak-naive"])
def test_a_diff_solver_mode_for_another_method_is_refused_not_ignored(synthetic_file, capsys, command, method):
    """`recover FILE --method peak --mode paper` (and `stream`) ran peak as if no --mode had been given, exit 0: the
    mode is the diff method's solver and the others have one. It is now one usage line, exit 2, before any frame."""
    assert main([command, str(synthetic_file), "--method", method, "--mode", "paper"]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"place-safe: error: --mode is the diff method's solver; it goes with "
                                         f"--method diff, not {method}"] and captured.out == ""
    assert main([command, str(synthetic_file), "--method", "diff", "--mode", "fast", "--jsonl"]) == 0
