"""Synthetic frames from the forward model: random planes, reflectance and Poisson shot noise.

Used by tests, calibration checks and benchmarks. Planes are drawn with ``z0`` uniform in
``z_range`` (m), angle of incidence uniform in ``theta_range`` (rad) and azimuth uniform; albedo
and specular parameters are drawn per frame. Each frame carries its ground-truth plane and, in
``extra["meta"]``, the reflectance used.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from importlib import resources

import numpy as np
import torch

from place_safe.recovery.forward import ForwardModel, ForwardParams, ZoneRays, mount_rotation
from place_safe.geometry import Plane
from place_safe.sensor.frame import N_ZONES, ZONE_DIRECTIONS, Frame, reported_distances


def default_reference() -> np.ndarray:
    """A real TMF8820 reference histogram (128 counts) shipped with the package."""
    data = json.loads(resources.files("place_safe").joinpath("data/reference_hist.json").read_text())
    return np.asarray(data["reference_hist"], dtype=float)


@dataclass
class SyntheticSpec:
    """What to draw. Ranges are (low, high); angles in radians, distances in metres."""

    z_range: tuple[float, float] = (0.02, 0.30)
    theta_range: tuple[float, float] = (0.0, np.deg2rad(30.0))
    albedo_range: tuple[float, float] = (0.5, 1.5)  # times the model's albedo
    specular_weight_range: tuple[float, float] = (0.0, 0.3)
    specular_exponent_range: tuple[float, float] = (1.0, 4.0)
    noise: bool = True
    rays: int = 16  # stratified n x n rays per zone used to render


def make_frames(n: int, params: ForwardParams | None = None, spec: SyntheticSpec | None = None,
                seed: int = 0, reference: np.ndarray | None = None) -> list[Frame]:
    """``n`` frames rendered with ``params`` (default: the published values)."""
    spec = spec or SyntheticSpec()
    params = params or ForwardParams()
    rng = np.random.default_rng(seed)
    ref = default_reference() if reference is None else np.asarray(reference, dtype=float)
    model = ForwardModel(params, ZoneRays.stratified(spec.rays))
    planes = []
    for _ in range(n):
        theta = rng.uniform(*spec.theta_range)
        phi = rng.uniform(-np.pi, np.pi)
        z0 = rng.uniform(*spec.z_range)
        planes.append(Plane.from_angles(theta, phi, z0))
    albedo = params.albedo * rng.uniform(*spec.albedo_range, n)
    ks = rng.uniform(*spec.specular_weight_range, n)
    alpha = rng.uniform(*spec.specular_exponent_range, n)
    # the planes are the ground truth in the reported sensor frame; the model renders in its optical frame (a unit
    # mounted off its nominal orientation: ForwardParams.mount_tilt), about the same origin
    normals = torch.as_tensor(np.array([p.normal for p in planes])) @ mount_rotation(params.mount_tilt)
    offsets = torch.as_tensor(np.array([p.offset for p in planes]))
    with torch.no_grad():
        h = model.render_plane(normals, offsets, torch.as_tensor(albedo), torch.as_tensor(ref)[None].expand(n, -1),
                               specular_weight=torch.as_tensor(ks), specular_exponent=torch.as_tensor(alpha)).numpy()
    if spec.noise:
        h = rng.poisson(np.clip(h, 0, None)).astype(float)
        ref_noisy = rng.poisson(ref, size=(n, ref.size)).astype(float)
    else:
        ref_noisy = np.broadcast_to(ref, (n, ref.size)).copy()
    zone_dirs = ZONE_DIRECTIONS @ mount_rotation(params.mount_tilt).numpy().T  # the zones' centres, reported frame
    frames = []
    for i, p in enumerate(planes):
        # on-sensor distances: range along each zone's centre ray, with 2 mm noise
        pts = p.intersect(zone_dirs)
        dist = np.linalg.norm(pts, axis=1) + (rng.normal(0, 0.002, N_ZONES) if spec.noise else 0)
        meta = {"albedo": float(albedo[i]), "specular_weight": float(ks[i]), "specular_exponent": float(alpha[i])}
        depths, confs = reported_distances(dist, 3, hists=h[i])
        frames.append(Frame(h[i], ref_noisy[i], distances=depths, confidences=confs, truth=p, extra={"meta": meta}))
    return frames
