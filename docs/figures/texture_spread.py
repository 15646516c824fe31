"""Per frame of simulated placements: the plane's tilt error (deg, against the scene's true table), its stated tilt
std (deg), and a texture statistic from the zones' return heights: the spread over zones of log(height * r^2) less
each zone's mean of that over plain-table frames (the zone's own gain and angle), by range band.
    python docs/figures/texture_spread.py SCENARIO.toml|random:SEED:IDX ...   (the first: a plain table, for the zone profile)"""
import math, sys, numpy as np
from place_safe.fusion import plane_filter, surface_map as sm
from place_safe.sim.placement_run import run_placement
from place_safe.sim.scenario import load_scenario
from place_safe.sim import suite
from place_safe.sensor.histogram import find_returns

def scene_of(arg):
    if arg.startswith("random:"):
        _, seed, idx = arg.split(":"); seed, idx = int(seed), int(idx)
        rng = np.random.default_rng(seed)
        for i in range(idx + 1):
            sc = suite.RANDOM_KINDS["tables"](rng, i)
        return sc, seed + idx
    return load_scenario(arg), 0

def run(arg):
    sc, seed = scene_of(arg)
    rows, pending = [], []
    add, update = sm.SurfaceMap.add, plane_filter.PlaneFilter.update
    def add_rec(self, frame, T, stamp):
        fs = add(self, frame, T, stamp)
        p = self.params
        h = np.asarray(frame.hists, float)
        pos, _, valid, _, ht = find_returns(h, p.pileup, p.subbin, p.subbin_half_width, heights=True)
        r = p.ranges(pos)
        truth = getattr(frame, "truth", None)
        pending.append((ht, r, valid, truth))
        return fs
    def upd_rec(self, est, T, stamp, *a, **k):
        plane = getattr(est, "plane", None)
        s = est.tilt_std() if plane is not None and callable(getattr(est, "tilt_std", None)) else None
        if plane is not None and s is not None and pending:
            ht, r, valid, truth = pending[-1]
            if truth is not None:
                err = math.degrees(math.acos(min(1.0, abs(float(np.dot(plane.normal, truth.normal))))))
                rows.append((float(plane.z0), err, math.degrees(s), ht, r, valid))
        return update(self, est, T, stamp, *a, **k)
    sm.SurfaceMap.add, plane_filter.PlaneFilter.update = add_rec, upd_rec
    try:
        res = run_placement(sc, seed=seed, seconds=30.0, log_frames=True)
    finally:
        sm.SurfaceMap.add, plane_filter.PlaneFilter.update = add, update
    return res, rows

allrows = {}
for arg in sys.argv[1:]:
    res, rows = run(arg)
    allrows[arg] = rows
    print(arg, res.outcome, res.reason[:80], len(rows), "planes")
# zone profile from plain frames (the first argument's)
plain = allrows[sys.argv[1]]
L = np.array([np.where(v & (h > 0), np.log(np.maximum(h, 1e-9) * r ** 2), np.nan) for _, _, _, h, r, v in plain])
L = L - np.nanmean(L, axis=1, keepdims=True)
g = np.nanmedian(L, axis=0)
print("zone profile (log, plain):", np.round(g, 2).tolist())
for arg, rows in allrows.items():
    print("==", arg)
    for lo, hi in ((0.03, 0.08), (0.08, 0.15), (0.15, 0.5)):
        sel = [(e, s, np.nanstd(np.where(v & (h > 0), np.log(np.maximum(h, 1e-9) * r ** 2), np.nan) - g))
               for z0, e, s, h, r, v in rows if lo <= z0 < hi]
        if not sel: continue
        E, S, T = (np.array(x) for x in zip(*sel))
        print(f"  {lo*100:.0f}-{hi*100:.0f} cm: n {len(E):3d} tilt err mean {E.mean():.2f} p90 {np.percentile(E,90):.2f} deg, stated {np.median(S):.3f}, NEES~ {np.mean((E/S)**2)/2:.1f}; texture spread median {np.median(T):.2f} p10 {np.percentile(T,10):.2f} p90 {np.percentile(T,90):.2f}; corr(err, spread) {np.corrcoef(E, T)[0,1]:.2f}")
