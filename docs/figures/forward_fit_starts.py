"""The forward fit (``forward_fit.fit_forward``, defaults) of FRAMES from its default start, and from the same start
with the pulse's soft-binning blend (``ForwardParams.pulse_soft_bin``, a structural choice fitted from 0.5) starting
at each of ``--pulse-soft-bin`` instead: the soft-bin width, reference time scale and blend each fit ends at, its RMS
scaled residual and why it stopped. Two starts that end in different places show two basins (docs/results.md, "The
forward fit's two basins"). The default start tries the blend at each of ``forward_fit.PULSE_SOFT_BIN_STARTS`` too
(since "The forward fit's two basins, landed"); ``--middle-only`` leaves that out, as the fit was when the table of
"The forward fit's two basins" was measured.

    python docs/figures/forward_fit_starts.py FRAMES [--pulse-soft-bin 0.02 ...] [--middle-only]
"""
from __future__ import annotations

import argparse
import time

import torch
from pydantic import Field

from place_safe.calibration import forward_fit as ff
from place_safe.io.frame_file import load_frames
from place_safe.recovery.forward import ForwardParams


def fit_from(frames, blend: float | None, middle_only: bool = False) -> str:
    """One fit; ``blend`` None: the default start. ``middle_only``: no further blend starts."""
    plain_params, plain_structural, plain_starts = ff.ForwardParams, ff.STRUCTURAL, ff.PULSE_SOFT_BIN_STARTS
    if middle_only or blend is not None:  # (from a given blend, not again from 0.02)
        ff.PULSE_SOFT_BIN_STARTS = ()
    if blend is not None:
        class Start(ForwardParams):
            pulse_soft_bin: float = Field(blend, ge=0.0, le=1.0)
        ff.ForwardParams = Start
        ff.STRUCTURAL = tuple(k for k in plain_structural if k != "pulse_soft_bin")  # (it starts at 0.5 there)
    try:
        t = time.process_time()
        p, rep = ff.fit_forward(frames, progress=False)
    finally:
        ff.ForwardParams, ff.STRUCTURAL, ff.PULSE_SOFT_BIN_STARTS = plain_params, plain_structural, plain_starts
    return (f"soft_bin_sigma {p.soft_bin_sigma:.3f}, ref_time_scale {p.ref_time_scale:.4f}, pulse_soft_bin "
            f"{p.pulse_soft_bin:.3f}: RMS {rep['rms_scaled_residual_after']:.3f} ({rep['why']}), "
            f"{time.process_time() - t:.0f} s CPU")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("frames")
    ap.add_argument("--pulse-soft-bin", type=float, nargs="+", default=[0.02])
    ap.add_argument("--middle-only", action="store_true",
                    help="the default start without its further blend starts (forward_fit.PULSE_SOFT_BIN_STARTS)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    frames = load_frames(a.frames)
    what = "pulse_soft_bin 0.5 only" if a.middle_only else f"pulse_soft_bin 0.5, then {ff.PULSE_SOFT_BIN_STARTS}"
    print(f"default start ({what}): {fit_from(frames, None, a.middle_only)}", flush=True)
    for v in a.pulse_soft_bin:
        print(f"pulse_soft_bin from {v:g}: {fit_from(frames, v, a.middle_only)}", flush=True)


if __name__ == "__main__":
    main()
