"""The texture statistic of docs/figures/texture_spread.py on real level frames: each zone's profile from PROFILE (5 cm on),
the spread on TEST by range band.  python docs/figures/texture_spread_real.py CAL.json PROFILE.json TEST.json"""
import sys, numpy as np
from place_safe.io.frame_file import load_frames
from place_safe.calibration import Calibration
from place_safe.sensor.histogram import find_returns
p = Calibration.load(sys.argv[1]).peak()
prof_frames = load_frames(sys.argv[2]); test_frames = load_frames(sys.argv[3])
def logs(frames):
    out = []
    for f in frames:
        h = np.asarray(f.hists, float)
        pos, _, valid, _, ht = find_returns(h, p.pileup, p.subbin, p.subbin_half_width, heights=True)
        r = p.ranges(pos)
        L = np.where(valid & (ht > 0), np.log(np.maximum(ht, 1e-9) * r ** 2), np.nan)
        out.append((f.truth.z0, L - np.nanmean(L)))
    return out
P = logs(prof_frames)
g = np.nanmedian(np.array([L for z, L in P if z >= 0.05]), axis=0)
print("zone profile (real, from 5 cm on):", np.round(g, 2).tolist())
for lo, hi in ((0.02, 0.05), (0.05, 0.08), (0.08, 0.15), (0.15, 0.5)):
    S = [np.nanstd(L - g) for z, L in logs(test_frames) if lo <= z < hi]
    if S: print(f"{lo*100:.0f}-{hi*100:.0f} cm: n {len(S)} spread median {np.median(S):.2f} max {np.max(S):.2f}")
