"""Does surface texture within the zones' footprints scatter diff's tilt more than peak's? The real calibration's
forward model (20 x 20 rays a zone, the solver's is 6 x 6) renders a level table swept 5-40 cm below the sensor over one
spot, its albedo flat or textured (a smooth random field, fixed on the table, std given), Poisson noise added; diff's own
plane (the same forward parameters: a perfect model but for the texture) and peak's (calibrated on an untextured level
sweep of the same model); scatter about a cubic in 1/z, deg per slope axis. Uses a real calibration's forward and peak
sections and the real frames' reference histograms (docs/results.md, the unit model, step 11).

    python docs/figures/texture_scatter.py CAL FRAMES STD [STD ...]      # e.g. cal_even.json odd.json 0 0.1 0.3
"""
import sys, copy, math, json
import numpy as np, torch
torch.set_num_threads(1)
from place_safe.calibration import Calibration
from place_safe.recovery.forward import ForwardModel, ZoneRays
from place_safe.recovery.differentiable import DifferentiableEstimator
from place_safe.recovery.peak import PeakEstimator
from place_safe.recovery.estimator import Uncertainty, tilt_offset
from place_safe.io.frame_file import load_frames
from place_safe.geometry import Plane

if len(sys.argv) < 4:
    raise SystemExit(__doc__)
cal = Calibration.load(sys.argv[1])
params, pk = cal.forward(), cal.peak()
real = [f for f in load_frames(sys.argv[2]) if f.reference is not None]
model = ForwardModel(params, ZoneRays.stratified(20, dtype=torch.float64), dtype=torch.float64)
dirs, w = model.ray_geometry()
rng = np.random.default_rng(1)
K = 40
kvec = rng.normal(size=(K, 2)); kvec /= np.linalg.norm(kvec, axis=1, keepdims=True)
kvec *= (2 * math.pi / rng.uniform(0.005, 0.05, K))[:, None]   # wavelengths 5-50 mm
phase = rng.uniform(0, 2 * math.pi, K)

def texture(xy, std):
    f = np.cos(xy @ kvec.T + phase).sum(-1) * math.sqrt(2.0 / K)  # unit variance
    return np.clip(1.0 + std * f, 0.05, None)

def frames(std, seed):
    r = np.random.default_rng(seed)
    out = []
    for i, z in enumerate(np.linspace(0.05, 0.40, 60)):
        n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64); d = torch.tensor([z], dtype=torch.float64)
        ranges, cos, hit = model.plane_returns(n, d)
        pts = (ranges[0, ..., None] * dirs).numpy()  # (9, R, 3)
        alb = torch.as_tensor(params.albedo * texture(pts[..., :2], std), dtype=torch.float64)[None]
        src = real[i % len(real)]
        ref = torch.as_tensor(np.asarray(src.reference, float), dtype=torch.float64)[None]
        with torch.no_grad():
            h = model.render_returns(ranges, cos, alb, ref, hit=hit, light=model.plane_light(n, d, ranges, hit))[0].numpy()
        g = copy.deepcopy(src)
        g.hists = r.poisson(np.maximum(h, 0)).astype(float)
        g.truth = Plane(np.array([0.0, 0.0, 1.0]), float(z))
        out.append(g)
    return out

diff = DifferentiableEstimator(params, pk, uncertainty=Uncertainty())  # no fallback calibrated: own plane
from place_safe.calibration.fit import fit_method
cal2 = Calibration()
fit_method(cal2, frames(0.0, 3), "peak", progress=False, log=None)
peak = PeakEstimator(cal2.peak())
def scatter(fr, est):
    z, t = [], []
    for f in fr:
        e = est.estimate(f)
        if e.ok:
            z.append(f.truth.offset); t.append(tilt_offset(e.plane)[:2])
    z, t = np.array(z), np.array(t)
    X = np.vander(1 / z, 4)
    res = t - X @ np.linalg.lstsq(X, t, rcond=None)[0]
    return np.degrees(res.std(0)), len(z)
for std in [float(v) for v in sys.argv[3:]]:
    fr = frames(std, 7)
    sd, nd = scatter(fr, diff); sp, npk = scatter(fr, peak)
    print(f"texture std {std:.2f}: diff own a/b {sd.round(3)} (n {nd}); peak a/b {sp.round(3)} (n {npk})", flush=True)
