"""`calibrate --method diff` with the forward model's edge and corner field-of-view scales held, or freed from a
calibration whose scales were held: how much of diff's tilt a level sweep's fitted fields of view decide.

    python docs/figures/fov_held.py LEVEL.json OUT.json --held 1.0 1.0          # scales held (nominal: the paper's model)
    python docs/figures/fov_held.py LEVEL.json OUT.json --held 0.9405 0.8916    # held at the paper's peak angle scales
    python docs/figures/fov_held.py LEVEL.json OUT.json --start-from HELD.json   # freed, from HELD.json's forward model
    place-safe evaluate TILTED.json --calibration OUT.json --methods diff peak --no-fallback

Everything else is `place-safe calibrate FILE --method diff` (docs/results.md, "The zones' fields of view").
"""
from __future__ import annotations

import argparse

import torch

import place_safe.calibration.fit as fit
import place_safe.calibration.forward_fit as ff
from place_safe.calibration import Calibration
from place_safe.io.frame_file import load_frames

FOV = ("edge_fov_scale", "corner_fov_scale")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("frames")
    ap.add_argument("out")
    how = ap.add_mutually_exclusive_group(required=True)
    how.add_argument("--held", nargs=2, type=float, metavar=("EDGE", "CORNER"))
    how.add_argument("--start-from", metavar="CAL.json", help="free the scales, starting from this calibration's model")
    a = ap.parse_args()
    torch.set_num_threads(1)
    fit_forward = ff.fit_forward
    if a.held:
        edge, corner = a.held

        class Held(ff.ForwardParams):  # the default start, with the scales at the held values
            edge_fov_scale: float = edge
            corner_fov_scale: float = corner

        ff.ForwardParams = Held
        fitted = {k: v for k, v in ff.FITTED.items() if k not in FOV}
        fit.fit_forward = lambda frames, init=None, progress=True, **kw: fit_forward(frames, init, progress,
                                                                                    fitted=fitted, **kw)
    else:
        start = Calibration.load(a.start_from).forward()
        fit.fit_forward = lambda frames, init=None, progress=True, **kw: fit_forward(frames, start, progress, **kw)
    cal = Calibration()
    fit.fit_method(cal, load_frames(a.frames), "diff", progress=True)
    cal.save(a.out)
    f, r = cal.forward(), cal.reports["forward"]
    print(f"{a.out}: edge {f.edge_fov_scale:.4f} corner {f.corner_fov_scale:.4f} "
          f"RMS {r['rms_scaled_residual_after']:.3f} converged {r['converged']}")


if __name__ == "__main__":
    main()
