"""The fake ur_rtde is faithful to the installed one: every fake class and method exists in ur-rtde with the
same parameter names, order and defaults (parsed from the pybind11 signatures in the real docstrings)."""

from __future__ import annotations

import importlib
import inspect
import re

import pytest

from place_safe.drivers.ur5.fake_rtde import FAKES

SIG = re.compile(r"^(?:\d+\. )?(\w+)\(self: [\w.]+(?:, (.*))?\) -> (.+)$")


def _split(params: str) -> list[str]:
    out, depth, cur = [], 0, ""
    for ch in params:
        if ch in "[(<":
            depth += 1
        elif ch in "])>":
            depth -= 1
        if ch == "," and depth == 0:
            out.append(cur.strip())
            cur = ""
        else:
            cur += ch
    if cur.strip():
        out.append(cur.strip())
    return out


def real_signatures(obj) -> list[list[tuple[str, str | None]]]:
    """Every overload of a pybind11 method as [(name, default or None), ...] (self excluded)."""
    sigs = []
    for line in (obj.__doc__ or "").splitlines():
        m = SIG.match(line.strip())
        if not m:
            continue
        params = []
        for p in _split(m.group(2) or ""):
            name, _, rest = p.partition(":")
            default = rest.split(" = ", 1)[1].strip() if " = " in rest else None
            params.append((name.strip(), default))
        sigs.append(params)
    return sigs


def _same_default(fake_default, real: str) -> bool:
    if real.startswith("<"):  # an enum such as <Flags.FLAG_UPLOAD_SCRIPT: 1>
        return str(fake_default) == real.rsplit(":", 1)[1].strip(" >")
    try:
        return fake_default == eval(real, {})  # literals only: 0.25, False, [], 10.0
    except Exception:  # noqa: BLE001
        return False


def _methods(cls):
    """The fake's methods, its own and those it inherits from a shared base (the first definition of each name)."""
    seen: dict = {}
    for klass in cls.__mro__[:-1]:
        for n, f in vars(klass).items():
            if callable(f) and (not n.startswith("_") or n == "__init__"):
                seen.setdefault(n, f)
    return list(seen.items())


@pytest.mark.parametrize("fake, module, name", FAKES, ids=[f[2] for f in FAKES])
def test_fake_methods_match_the_installed_ur_rtde(fake, module, name):
    real_cls = getattr(importlib.import_module(module), name)
    assert fake.__name__ == name
    checked = 0
    for meth, fn in _methods(fake):
        assert hasattr(real_cls, meth), f"{name}.{meth} does not exist in the installed ur_rtde"
        fake_params = [(p.name, p.default) for p in list(inspect.signature(fn).parameters.values())[1:]]
        overloads = real_signatures(getattr(real_cls, meth))
        assert overloads, f"no signature in the docstring of {name}.{meth}"
        ok = any(len(o) == len(fake_params)
                 and all(fn_ == rn and ((fd is inspect.Parameter.empty) == (rd is None))
                         and (rd is None or _same_default(fd, rd))
                         for (fn_, fd), (rn, rd) in zip(fake_params, o))
                 for o in overloads)
        assert ok, f"{name}.{meth}{fake_params} matches none of the real overloads {overloads}"
        checked += 1
    assert checked >= 5


def test_the_driver_uses_only_methods_the_real_classes_have():
    """Every ur_rtde call in rtde_robot.py names a real method (so the fake cannot hide a typo)."""
    import place_safe.drivers.ur5.rtde_robot as mod
    import rtde_control
    import rtde_io
    import rtde_receive

    src = inspect.getsource(mod)
    real = set(dir(rtde_control.RTDEControlInterface)) | set(dir(rtde_receive.RTDEReceiveInterface)) | \
        set(dir(rtde_io.RTDEIOInterface))
    called = set(re.findall(r"\b(?:_control|_receive|_io|r|c|iface)\.([a-z]+[A-Z]\w*)\(", src))
    assert called, "no ur_rtde calls found"
    assert called <= real, f"not in ur_rtde: {sorted(called - real)}"


def test_signature_parser_reads_overloads():
    import rtde_control

    sigs = real_signatures(rtde_control.RTDEControlInterface.moveL)
    assert [p[0] for p in sigs[1]] == ["pose", "speed", "acceleration", "asynchronous"]
    assert sigs[1][1] == ("speed", "0.25")
