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
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("frames", help="calibration frames with ground truth (a level sweep)")
    ap.add_argument("out", help="calibration file to write")
    ap.add_argument("--hold", nargs="+", required=True, metavar="NAME=VALUE", help="terms held, in their own units")
    a = ap.parse_args(argv)
    held = _held(a.hold)
    torch.set_num_threads(1)
    fitted = {k: v for k, v in ff.FITTED.items() if k not in held}
    fit_forward = ff.fit_forward
    # the default start with the held values: fit_forward's coarse starts only run from the default start, so the
    # parameter class's defaults are what must change
    defaults = type("Held", (ff.ForwardParams,), {"__annotations__": {k: float for k in held}, **held})
    ff.ForwardParams = defaults
    fit.fit_forward = lambda frames, init=None, progress=True, **kw: fit_forward(frames, None, progress,
                                                                                fitted=fitted, **kw)
    fit.reconsider_geometry = lambda frames, params, report, **kw: (params, report)  # the fit as asked for, kept
    cal = Calibration()
    fit.fit_method(cal, load_frames(a.frames), "diff", progress=True)
    cal.save(a.out)
    f, r = cal.forward(), cal.reports["forward"]
    got = {k: getattr(f, k) for k in held}
    if any(abs(got[k] - v) > 1e-12 * max(1.0, abs(v)) for k, v in held.items()):
        raise SystemExit(f"held_term: the fit did not hold {held} (got {got})")
    print(f"{a.out}: held {held}; RMS {r['rms_scaled_residual_after']:.3f} (coarse "
          f"{r['solver']['coarse']['rms_scaled_residual']:.4f}), {r['frames_excluded_as_bad']} frames excluded, "
          f"converged {r['converged']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
