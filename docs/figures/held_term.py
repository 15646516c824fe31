"""`calibrate --method diff` with some of the forward model's scalar terms held at given values instead of fitted: how
much of diff's reading of tilted planes a level sweep leaves to a term it cannot determine.

    python docs/figures/held_term.py LEVEL.json OUT.json --hold crosstalk=0.0054
    python docs/figures/held_term.py LEVEL.json OUT.json --hold crosstalk=0.0098 beam_power=1.0
    place-safe evaluate TILTED.json --calibration OUT.json --methods diff peak --no-fallback
    python docs/figures/slope_scale.py TILTED.json OUT.json

Everything else is `place-safe calibrate FILE --method diff` without its second fit (``reconsider_geometry``). The
terms are ``ForwardParams`` fields with one number (``crosstalk``, ``beam_power``, ``edge_fov_scale``, ...).
docs/results.md, "What a level sweep leaves to the crosstalk".
"""
from __future__ import annotations

import argparse
from pathlib import Path

import torch

import place_safe.calibration.fit as fit
import place_safe.calibration.forward_fit as ff
from place_safe.calibration import Calibration
from place_safe.io.frame_file import load_frames


def _held(items: list[str]) -> dict[str, float]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep:
            raise SystemExit(f"held_term: --hold takes NAME=VALUE, got {item!r}")
        if name not in ff.FITTED:
            raise SystemExit(f"held_term: {name!r} is not one of the forward fit's terms ({', '.join(ff.FITTED)})")
        if not isinstance(getattr(ff.ForwardParams(), name), float):
            raise SystemExit(f"held_term: {name!r} is not a scalar term")
        try:
            out[name] = float(value)
        except ValueError:
            raise SystemExit(f"held_term: {name}={value!r} is not a number") from None
    try:  # the field's own bounds (a NaN, a crosstalk of 0.6: refused before a minute of fitting)
        ff.ForwardParams(**out)
    except ValueError as exc:
        first = str(exc).splitlines()
        raise SystemExit(f"held_term: {', '.join(f'{k}={v:g}' for k, v in out.items())} is out of range: "
                         f"{first[-1].strip() if first else exc}") from None
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("frames", help="calibration frames with ground truth (a level sweep)")
    ap.add_argument("out", help="calibration file to write")
    ap.add_argument("--hold", nargs="+", required=True, metavar="NAME=VALUE", help="terms held, in their own units")
    a = ap.parse_args(argv)
    held = _held(a.hold)
    out = Path(a.out)
    if not out.parent.is_dir():
        raise SystemExit(f"held_term: cannot write {out}: {out.parent} is not a directory")
    from place_safe.exceptions import PlaceSafeError

    try:
        frames = load_frames(a.frames)
    except PlaceSafeError as exc:
        raise SystemExit(f"held_term: {exc}") from None
    torch.set_num_threads(1)
    fitted = {k: v for k, v in ff.FITTED.items() if k not in held}

    class Held(ff.ForwardParams):
        """Every parameter set the fit builds (its default start among them) carries the held values."""

        def __init__(self, **data):
            super().__init__(**{**data, **held})

    ff.ForwardParams = Held
    fit_forward = ff.fit_forward
    fit.fit_forward = lambda frames, init=None, progress=True, **kw: fit_forward(frames, None, progress,
                                                                                fitted=fitted, **kw)
    fit.reconsider_geometry = lambda frames, params, report, **kw: (params, report)  # the fit as asked for, kept
    fit.spare_cores = lambda: 0  # (and no second fit started beside it, whose result would be thrown away)
    cal = Calibration()
    try:
        fit.fit_method(cal, frames, "diff", progress=True)
        cal.save(str(out))
    except (PlaceSafeError, OSError) as exc:
        raise SystemExit(f"held_term: {exc}") from None
    f, r = cal.forward(), cal.reports["forward"]
    got = {k: getattr(f, k) for k in held}
    if any(abs(got[k] - v) > 1e-12 * max(1.0, abs(v)) for k, v in held.items()):
        raise SystemExit(f"held_term: the fit did not hold {held} (got {got})")
    print(f"{out}: held {held}; RMS {r['rms_scaled_residual_after']:.3f} (coarse "
          f"{r['solver']['coarse']['rms_scaled_residual']:.4f}), {r['frames_excluded_as_bad']} frames excluded, "
          f"converged {r['converged']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
