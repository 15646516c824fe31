"""The command line's options are declared once (place_safe/cli/options.py): the shared table, the ranges that
come from the parameter models, and the commands built from it."""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

import pytest

from place_safe.cli import options
from place_safe.cli.app import build_parser
from place_safe.config import field_constraints

pytestmark = pytest.mark.fast

CLI_FILES = sorted(Path(options.__file__).parent.glob("*.py")) + [
    Path(options.__file__).parents[1] / "sim" / "cli.py"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    options.add(p, *options._shared())
    return p


def test_every_shared_option_can_be_added_and_keeps_its_default():
    p = _parser()
    args = p.parse_args([])
    assert args.method == "diff" and args.calibration is None and args.quiet is False and args.seed == 0


@pytest.mark.parametrize("name", ["rays", "rate_hz", "noise"])
def test_a_model_field_option_takes_the_range_of_the_model(name):
    option = options._shared()[name]
    model_path, _, field = option.field.rpartition(".")
    module, _, cls = model_path.partition(":")
    model = getattr(__import__(module, fromlist=[cls]), cls)
    c = field_constraints(model, field)
    hi = c.get("le", c.get("lt"))
    p = argparse.ArgumentParser(exit_on_error=False)
    option.add_to(p)
    flag = option.flags[0]
    assert getattr(p.parse_args([flag, str(hi)]), p._actions[-1].dest) == pytest.approx(hi)
    with pytest.raises((argparse.ArgumentError, SystemExit)):
        p.parse_args([flag, str(hi * 2 + 1)])


def test_a_change_to_an_option_that_is_not_added_is_refused():
    with pytest.raises(KeyError):
        options.add(argparse.ArgumentParser(), "quiet", seed={"default": 1})


def test_a_command_keeps_its_own_spelling_of_a_shared_option():
    sub = build_parser(False)._subparsers._group_actions[0].choices
    evaluate = {a.dest: a for a in sub["evaluate"]._actions}
    assert "diff_mode" in evaluate and "mode" not in evaluate
    recover = {a.dest: a for a in sub["recover"]._actions}
    assert recover["method"].required and recover["batch"].default is None


def test_no_command_restates_a_shared_option():
    """A shared option (``--calibration``, ``-q/--quiet``, ``--seed``, ...) is added by name, never spelled again
    with ``add_argument``."""
    shared_flags = {f for o in options._shared().values() for f in o.flags if f.startswith("-")}
    restated = []
    for path in CLI_FILES:
        for node in ast.walk(ast.parse(path.read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "add_argument" and node.args
                    and isinstance(node.args[0], ast.Constant) and node.args[0].value in shared_flags):
                restated.append(f"{path.name}:{node.lineno} {node.args[0].value}")
    assert restated == []
