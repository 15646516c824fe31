"""`calibrate --method diff` with the forward model's geometry (the edge and corner field-of-view scales, the mount
tilt) held, the zones' own time scales fitted, or the scales freed from a calibration whose scales were held: how
much of diff's tilt a level sweep's fitted geometry decides.

    python docs/figures/fov_held.py LEVEL.json OUT.json --held 1.0 1.0          # scales held (nominal: the paper's model)
    python docs/figures/fov_held.py LEVEL.json OUT.json --held 0.9405 0.8916    # held at the paper's peak angle scales
    python docs/figures/fov_held.py LEVEL.json OUT.json --start-from HELD.json   # freed, from HELD.json's forward model
    python docs/figures/fov_held.py LEVEL.json OUT.json --held 1 1 --hold-mount --zone-scales   # as peak holds its own
    python docs/figures/fov_held.py LEVEL.json OUT.json --zone-scales           # the time scales with everything free
    place-safe evaluate TILTED.json --calibration OUT.json --methods diff peak --no-fallback

Everything else is `place-safe calibrate FILE --method diff` (without its second fit, ``reconsider_geometry``) (docs/results.md, "The zones' fields of view" and "Each
zone's own time scale").
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
    how = ap.add_mutually_exclusive_group()
    how.add_argument("--held", nargs=2, type=float, metavar=("EDGE", "CORNER"))
    how.add_argument("--start-from", metavar="CAL.json", help="free the scales, starting from this calibration's model")
    ap.add_argument("--hold-mount", action="store_true", help="hold the mount tilt at 0")
    ap.add_argument("--zone-scales", action="store_true", help="fit each zone's time scale (ZONE_SCALE_TERMS)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    fit_forward = ff.fit_forward
    held = (FOV if a.held else ()) + (("mount_tilt",) if a.hold_mount else ())
    fitted = {k: v for k, v in {**ff.FITTED, **(ff.ZONE_SCALE_TERMS if a.zone_scales else {})}.items() if k not in held}
    if a.held:
        edge, corner = a.held

        class Held(ff.ForwardParams):  # the default start, with the scales at the held values
            edge_fov_scale: float = edge
            corner_fov_scale: float = corner

        ff.ForwardParams = Held
    start = Calibration.load(a.start_from).forward() if a.start_from else None
    fit.fit_forward = lambda frames, init=None, progress=True, **kw: fit_forward(frames, start, progress,
                                                                                fitted=fitted, **kw)
    fit.reconsider_geometry = lambda frames, params, report, **kw: (params, report)  # the fit as asked for, kept
    cal = Calibration()
    fit.fit_method(cal, load_frames(a.frames), "diff", progress=True)
    cal.save(a.out)
    f, r = cal.forward(), cal.reports["forward"]
    print(f"{a.out}: edge {f.edge_fov_scale:.4f} corner {f.corner_fov_scale:.4f} mount {list(f.mount_tilt)} "
          f"zone time scales {[round(x, 4) for x in f.zone_bin_scales]} RMS {r['rms_scaled_residual_after']:.3f} "
          f"converged {r['converged']}")


if __name__ == "__main__":
    main()
