"""Plane recovery by differentiable rendering of the forward model (the paper's method 1).

Two solvers share one forward model (:mod:`place_safe.recovery.forward`) and one initialisation (the
calibrated peak method):

``fast`` (default)
    Levenberg-Marquardt per frame on the plane as slopes and axis crossing ``(a, b, z0)`` (normal ~ ``(a, b, 1)``,
    smooth at normal incidence), ``log albedo`` (one, or one per zone tied to their mean:
    ``SolverOptions.zone_albedo``), specular weight and ``log`` specular exponent, the last two held near the
    calibrated values by a weak prior (a fronto-parallel plane cannot tell them from albedo); where the calibration
    says a level sweep left the unit's crosstalk undetermined (``SolverOptions.crosstalk_std``), also the frame's
    own crosstalk, under a prior about the calibrated one (a tilted plane shows it). Residuals are Poisson-scaled:
    ``(model - observed) / sqrt(observed + 1 + (e observed)^2)`` (Poisson noise and the calibrated relative model
    error ``e``, :func:`~place_safe.recovery.forward.residual_weights`) over the bins that hold the returns.
    Jacobians are the analytic ones of :class:`~place_safe.recovery.plane_renderer.PlaneRenderer`; rays are a
    deterministic stratified quadrature; the laser pulse is prepared once per frame. Frames are solved as a batch.

``paper``
    The paper's procedure: Adam, 100 iterations, 2304 random rays per zone, optimising angle of
    incidence, azimuth, ``z0``, albedo and the specular parameters from the same initialisation.
    Kept so the comparison with the fast solver stays honest.

``residual`` of an estimate is the RMS Poisson-scaled histogram residual at the solution over the bins
up to ``test_window`` after the frame's latest peak (about 1 when the model explains the returns to the
noise level; the solver fits a longer window, ``window_after_peak``, whose faint tail bins would dilute
the test). Its square is a chi-square per bin
against the calibrated noise: above the calibrated ``chi2_limit`` (:class:`~place_safe.recovery.estimator.Uncertainty`)
the fast solver returns the peak estimate instead, with ``method_used = "peak"``; so it does when the two
contradict each other (``consistency_limit``) and where diff's tilt variance is above ``prefer_ratio`` times
peak's (peak reads that slope better; calibrated on held-out frames, :mod:`place_safe.calibration.uncertainty`).
A calibration that blends (``Uncertainty.blend``, what ``calibrate`` writes) returns, where the other gates pass,
diff's plane and peak's blended by their variances (:mod:`place_safe.recovery.blend`, ``method_used =
"diff+peak"``) in place of that choice: on the real sweep held out the blend read better than either plane.
Closer than :data:`NEAR_FALLBACK_RANGE` (peak's offset) a calibrated fast solver always returns peak's plane: the
forward model has no validated near-range terms (internal return, partial illumination), and on the real sweep
its own plane there was off by 10-19 deg where peak's near-range table read 1.7-3.3 deg. Likewise a plane past the
range peak's mapping was calibrated on, where peak's calibration states how its error grows (``_past_range``).
The fast solver's
``covariance`` of ``(n_x, n_y, d)`` is the Gauss-Newton inverse at the solution scaled by that
chi-square (plus the calibrated floor).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from place_safe.recovery.points import PeakParams
from place_safe.exceptions import FrameError, NoPlaneError
# the calibrated settings live without torch (a calibration is read, and peak runs, without the solver)
from place_safe.recovery.diff_settings import (BLENDED, FAR_FALLBACK_PAST, NEAR_FALLBACK_RANGE, RangeCorrection,
                                              SolverOptions)
from place_safe.recovery.forward import (ForwardModel, ForwardParams, PulseMatrices, ZoneRays, mount_rotation,
                                         residual_weights)
from place_safe.geometry import Plane
from place_safe.recovery.plane_renderer import PlaneRenderer, convolution_matrices
from place_safe.sensor.frame import N_BINS, N_ZONES, Frame
from place_safe.recovery.estimator import (Estimator, PlaneEstimate, Uncertainty, check_arguments, checked,
                                          frames_of, is_covariance, tilt_offset)
from place_safe.recovery.blend import blended
from place_safe.recovery.peak import PeakEstimator
from place_safe.sensor.histogram import (arriving_ambient, beyond_count_max, clipped_zones, floor_profile,
                                        reference_problem)


def _positive_definite(cov) -> bool:
    """Whether ``cov`` (3 x 3, or None: no claim made) is finite with eigenvalues above 1e-12 of its
    largest (a covariance of a plane the fit pinned down)."""
    return cov is None or is_covariance(cov, definite=True)


def _fallback(peak: PlaneEstimate, diff: PlaneEstimate | None = None) -> PlaneEstimate:
    """The peak estimate returned in diff's place (``method_used = "peak"``), with diff's albedo and residual
    when it was solved."""
    return PlaneEstimate(peak.plane, albedo=None if diff is None else diff.albedo,
                         residual=None if diff is None else diff.residual, covariance=peak.covariance,
                         method_used="peak")


#: Bounds of the unknowns (a, b, z0 [m], log albedo, specular weight, log specular exponent):
#: slopes up to 80 deg of incidence, planes 1 mm to 5 m away, albedo within 1e-4..1e4 of the model's.
_LOWER = np.array([-5.67, -5.67, 1e-3, math.log(1e-4), 0.0, math.log(0.5)])
_UPPER = np.array([5.67, 5.67, 5.0, math.log(1e4), 1.0, math.log(50.0)])
#: The largest posterior standard deviation of the log albedo (the fast solver's Gauss-Newton covariance, scaled by
#: the residual's chi-square) with which diff reports an albedo; above it the frame does not determine the albedo
#: (a saturated return: its height no longer grows with the albedo) and ``PlaneEstimate.albedo`` is None. Measured
#: (docs/results.md, simulated units, scorecard): at most 0.5 on the tilted frames of mismatched units and of the
#: independent generator that read their albedo; 3e6-8e6 on the generator's saturated 5-7 cm frames, whose albedos
#: ran to 50-1e4 (the bound) against about 4 times the true value elsewhere.
ALBEDO_STD_LIMIT = 1.0


class DifferentiableEstimator(Estimator):
    """Differentiable-rendering recovery; ``mode`` is ``"fast"`` or ``"paper"``."""

    name = "diff"

    def __init__(self, forward: ForwardParams | None = None, peak: PeakParams | None = None,
                 mode: str = "fast", options: SolverOptions | None = None,
                 correction: RangeCorrection | None = None, uncertainty: Uncertainty | None = None,
                 peak_uncertainty: Uncertainty | None = None) -> None:
        if mode not in ("fast", "paper"):
            raise ValueError(f"mode must be 'fast' or 'paper', got {mode!r}")
        check_arguments(type(self).__name__, forward=(forward, ForwardParams), peak=(peak, PeakParams),
                        options=(options, SolverOptions), correction=(correction, RangeCorrection),
                        uncertainty=(uncertainty, Uncertainty), peak_uncertainty=(peak_uncertainty, Uncertainty))
        self.params = forward if forward is not None else ForwardParams()
        self.mode = mode
        self.opt = options or SolverOptions()
        self.correction = correction if correction is not None else RangeCorrection()
        self.uncertainty = uncertainty if uncertainty is not None else Uncertainty()
        self.init = PeakEstimator(peak if peak is not None else PeakParams.default_peak(), peak_uncertainty)
        self.dtype = torch.float64
        self.model = ForwardModel(self.params, ZoneRays.stratified(self.opt.rays, dtype=self.dtype), dtype=self.dtype)
        self._prior = torch.tensor([self.params.specular_weight, math.log(self.params.specular_exponent)],
                                   dtype=self.dtype)
        self._prior_std = torch.tensor([self.opt.prior_specular_weight, self.opt.prior_log_exponent],
                                       dtype=self.dtype)
        self._renderer = PlaneRenderer(self.params, self.model.rays, zone_albedo=self.opt.zone_albedo,
                                       free_crosstalk=self.opt.crosstalk_std > 0.0)
        # optical frame -> reported sensor frame (the calibrated mount tilt; identity by default)
        self._mount = mount_rotation(self.params.mount_tilt).numpy()
        self._pulse: PulseMatrices | None = None  # the fast solver's pulse (:meth:`_kernels`)

    # ------------------------------------------------------------------------------------------
    def _estimate(self, frame: Frame) -> PlaneEstimate:
        return self.estimate_batch([frame])[0]

    def estimate_many(self, frames: list[Frame]) -> list[PlaneEstimate]:
        frames = frames_of(frames)
        out = []
        for i in range(0, len(frames), 16):
            chunk = frames[i:i + 16]
            ests = super().estimate_many(chunk) if self.mode == "paper" else self._timed_batch(chunk)
            out.extend(ests)
        return out

    def _timed_batch(self, frames: list[Frame]) -> list[PlaneEstimate]:
        """Validate each frame (timed alone), solve the valid ones together and share that time."""
        import time

        ests: list[PlaneEstimate | None] = [None] * len(frames)
        good = []
        for i, f in enumerate(frames):
            t0 = time.perf_counter()
            try:
                if not isinstance(f, Frame):
                    raise FrameError(f"expected a Frame, got {type(f).__name__}")
                f.validate()
                good.append(i)
            except FrameError as exc:
                ests[i] = PlaneEstimate(None, reason=str(exc), seconds=time.perf_counter() - t0)
        if good:
            t0 = time.perf_counter()
            try:
                solved = self.estimate_batch([frames[i] for i in good])
            except (ArithmeticError, ValueError, TypeError, IndexError, RuntimeError, np.linalg.LinAlgError):
                solved = [self.estimate(frames[i]) for i in good]  # one by one: each failure gets its reason
            share = (time.perf_counter() - t0) / len(good)
            for i, e in zip(good, solved):
                e.seconds = share
                ests[i] = e
        return ests  # type: ignore[return-value]

    # ------------------------------------------------------------------------------------------
    def estimate_batch(self, frames: list[Frame]) -> list[PlaneEstimate]:
        """Recover frames together. Frames that are not valid frames or have no usable return get a reason."""
        frames = frames_of(frames)
        results: list[PlaneEstimate | None] = [None] * len(frames)
        inits, rows, peaks = [], [], []
        for i, f in enumerate(frames):
            try:
                if not isinstance(f, Frame):
                    raise FrameError(f"expected a Frame, got {type(f).__name__}")
                f.validate()
            except FrameError as exc:
                results[i] = PlaneEstimate(None, reason=str(exc))
                continue
            h = np.asarray(f.hists, dtype=float)
            if (beyond := beyond_count_max(h)) is not None:  # not clipped: counts the sensor cannot have reported
                results[i] = PlaneEstimate(None, reason=beyond)
                continue
            if clipped_zones(h).any():
                results[i] = PlaneEstimate(None, reason="histograms clipped (saturated counts: a flat top or counters "
                                                        "at their maximum)")
                continue
            bad_ref = reference_problem(f.reference)
            if bad_ref:
                results[i] = PlaneEstimate(None, reason=bad_ref)
                continue
            init = self.init.estimate(f)
            if not init.ok:
                results[i] = PlaneEstimate(None, reason=init.reason)
                continue
            inits.append(Plane(self._mount.T @ init.plane.normal, init.plane.offset))  # to the optical frame
            peaks.append(init)
            rows.append(i)
        if rows and self.mode == "fast" and self.uncertainty.chi2_limit == 0.0:
            # calibration found the model no better than peak on this sensor: no frame can pass, skip the solve
            for i, peak in zip(rows, peaks):
                results[i] = checked(_fallback(peak))
            rows = []
        if rows:
            sub = [frames[i] for i in rows]
            solve = self._solve_fast if self.mode == "fast" else self._solve_paper
            try:
                solved = solve(sub, inits)
            except (ArithmeticError, np.linalg.LinAlgError, RuntimeError, ValueError):
                solved = [self._solved_alone(solve, f, p0) for f, p0 in zip(sub, inits)]
            for i, est, peak in zip(rows, solved, peaks):
                results[i] = checked(self._checked(est, peak) if self.mode == "fast" else est)
        return results  # type: ignore[return-value]

    @staticmethod
    def _solved_alone(solve, frame: Frame, init: Plane) -> PlaneEstimate:
        """``frame`` solved on its own after its batch failed numerically; a frame that fails alone too gets no plane
        and the reason (the fast solver's gates then return peak's plane where a fallback is calibrated, as for any
        frame diff cannot read)."""
        try:
            return solve([frame], [init])[0]
        except (ArithmeticError, np.linalg.LinAlgError, RuntimeError, ValueError) as exc:
            return PlaneEstimate(None, reason=f"diff's solve failed numerically: {str(exc).splitlines()[0][:200]}")

    def _checked(self, est: PlaneEstimate, peak: PlaneEstimate) -> PlaneEstimate:
        """The diff estimate, or the peak estimate when diff's residual fails the chi-square test.

        ``residual`` is the RMS Poisson-scaled residual, so its square is the chi-square per bin
        against the calibrated noise; above ``uncertainty.chi2_limit`` the model does not explain the
        frame and the peak estimate (``method_used = "peak"``) is returned, with diff's residual. So it is
        when the two estimates contradict each other beyond ``uncertainty.consistency_limit``, when diff's
        tilt variance is above ``uncertainty.prefer_ratio`` times peak's (peak reads this slope better), closer than
        :data:`NEAR_FALLBACK_RANGE` (with a calibrated fallback), and when
        diff's covariance is not positive definite (a degenerate Jacobian: the fit did not pin the plane
        down, and a zero covariance would claim it did). With ``uncertainty.blend`` a frame that passes the other
        gates gets the two planes blended by their variances (:mod:`place_safe.recovery.blend`,
        ``method_used`` :data:`BLENDED`) in place of ``prefer_ratio``'s choice.
        """
        failed = not est.ok or est.residual is None or not est.residual ** 2 <= self.uncertainty.chi2_limit \
            or not _positive_definite(est.covariance)
        if math.isinf(self.uncertainty.chi2_limit) and not self.uncertainty.blend:
            near = False  # no fallback calibrated: diff's own plane wherever it has one
        else:  # (a blend is never made closer than NEAR_FALLBACK_RANGE, whatever the limit, nor past the range)
            near = peak.ok and (peak.plane.offset < NEAR_FALLBACK_RANGE or self._past_range(peak.plane))
        if not failed and not near and self.uncertainty.consistent(est, peak):
            if self.uncertainty.blend:  # both planes usable: blended by their variances
                mixed = blended(est, peak, BLENDED)
                if mixed is not None:
                    return mixed
            if self.uncertainty.prefers(est, peak):
                return est
        if not est.ok and math.isinf(self.uncertainty.chi2_limit):
            return est  # no fallback calibrated: report diff's own failure
        return _fallback(peak, est)

    def _past_range(self, plane) -> bool:
        """Whether a zone's range to ``plane`` (peak's) lies past the peak mapping's calibrated domain (by more than
        :data:`FAR_FALLBACK_PAST` of its end) where peak's
        calibration states how its error grows there (``far_common_rel``, :mod:`place_safe.calibration.far_range`):
        diff's forward model states no such growth (the real sweep calibrated to 20 cm read 20.75-39.5 cm by diff
        2.3 mm and 0.49 deg off at NEES per dof 32, peak 0.74 mm, 0.26 deg at 0.68), so peak's plane is returned."""
        unc, params = self.init.uncertainty, self.init.params
        if not unc.far_common_rel > 0.0 or not plane.offset > params.far_screen():
            return False
        ranges = np.linalg.norm(plane.intersect(params.directions()), axis=1)  # NaN: a zone's ray misses the plane
        return bool(np.nan_to_num(ranges, nan=np.inf).max() > params.residual_domain[1] * (1.0 + FAR_FALLBACK_PAST))

    # -- data preparation ----------------------------------------------------------------------
    def _observed(self, hists: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """The counts the model is compared with (B, 9, bins) and the ambient as it arrives (B, 9; None): above the
        floor measured after the return (across the bins as the unit's ``ambient_slope`` says), or with
        :attr:`SolverOptions.ambient` above the arriving ambient."""
        if self.opt.ambient:
            amb = arriving_ambient(hists)
            return hists - amb[..., None], amb
        return np.clip(hists - floor_profile(hists, self.params.ambient_slope), 0.0, None), None

    def _prepare(self, frames: list[Frame], inits: list[Plane]):
        hists = np.array([f.hists for f in frames], dtype=float)
        obs, amb = self._observed(hists)
        last_peak = int(obs.argmax(axis=-1).max())
        width = int(min(N_BINS, last_peak + self.opt.window_after_peak))
        ref = torch.as_tensor(np.array([f.reference for f in frames]), dtype=self.dtype)
        with torch.no_grad():
            kernel = self.model.pulse(ref)
        obs_t = torch.as_tensor(obs[..., :width], dtype=self.dtype)
        sigma = 1.0 / torch.as_tensor(residual_weights(hists[..., :width], self.params.model_error), dtype=self.dtype)
        amb_t = None if amb is None else torch.as_tensor(amb, dtype=self.dtype)
        return obs_t, sigma, kernel, width, amb_t

    def _render(self, x: torch.Tensor, kernel: torch.Tensor, width: int,
                ambient: torch.Tensor | None = None) -> torch.Tensor:
        """Histograms (9, width) of one frame's unknowns x = (a, b, z0, log rho, ks, log alpha); ``ambient`` (9,)
        as it arrives, or None."""
        a, b, z0 = x[0], x[1], x[2]
        s = torch.sqrt(1.0 + a * a + b * b)
        n = torch.stack([a, b, torch.ones_like(a)]) / s
        d = z0 / s
        h = self.model.render_plane(n.unsqueeze(0), d.reshape(1), torch.exp(x[3]).reshape(1), None,
                                    specular_weight=x[4].reshape(1), specular_exponent=torch.exp(x[5]).reshape(1),
                                    kernel=kernel.unsqueeze(0), ambient=None if ambient is None else ambient.unsqueeze(0))[0]
        return h[:, :width] - self.model.t["floor"]

    def _initial_x(self, frames: list[Frame], inits: list[Plane], obs, kernel, width, amb=None) -> torch.Tensor:
        x = torch.zeros(len(frames), 6, dtype=self.dtype)
        for i, p in enumerate(inits):
            a, b, z0 = p.slopes
            x[i, 0], x[i, 1], x[i, 2] = a, b, z0
        x[:, 3] = math.log(self.params.albedo)
        x[:, 4] = self.params.specular_weight
        x[:, 5] = math.log(self.params.specular_exponent)
        # albedo by least squares on the rendered shape (exact when saturation is mild); twice,
        # because saturation makes the model sub-linear in albedo
        with torch.no_grad():
            for _ in range(2):
                h = torch.stack([self._render(x[i], kernel[i], width, None if amb is None else amb[i])
                                 for i in range(len(frames))])
                scale = (h * obs).sum(dim=(1, 2)) / torch.clamp((h * h).sum(dim=(1, 2)), min=1e-12)
                x[:, 3] += torch.log(torch.clamp(scale, 1e-3, 1e3))
        return x

    # -- fast solver ---------------------------------------------------------------------------
    def _solve_fast(self, frames: list[Frame], inits: list[Plane]) -> list[PlaneEstimate]:
        """Batched Levenberg-Marquardt with the analytic Jacobian of :class:`PlaneRenderer` (which reuses a render at
        the same values: the Jacobian at an accepted step; its kept arrays are dropped when the solve ends)."""
        try:
            return self._levenberg_marquardt(frames, inits)
        finally:
            self._renderer.forget()

    def _levenberg_marquardt(self, frames: list[Frame], inits: list[Plane]) -> list[PlaneEstimate]:
        """:meth:`_solve_fast`'s solve."""
        hists = np.array([f.hists for f in frames], dtype=float)
        obs_full, amb = self._observed(hists)
        # each frame's own window (bins up to its latest zone peak plus window_after_peak): the batch renders
        # up to the widest, and the bins past a frame's window weigh 0, so no frame depends on its batch
        last_peak = obs_full.argmax(axis=-1).max(axis=-1)
        own = np.minimum(N_BINS, last_peak + self.opt.window_after_peak)
        width = int(own.max())
        obs = obs_full[..., :width]
        inv_sigma = residual_weights(hists[..., :width], self.params.model_error)
        inv_sigma = inv_sigma * (np.arange(width) < own[:, None])[:, None, :]
        n_res_own = N_ZONES * own  # residuals per frame
        kernels = self._kernels(frames)
        conv = self._renderer.responses(convolution_matrices(kernels, width))  # once per frame
        nb = len(frames)
        rd = self._renderer
        nu = rd.n_unknowns
        xt_col = rd.crosstalk_column  # None: the crosstalk held at the calibrated value
        n_xt = 0 if xt_col is None else 1
        n_alb = nu - 5 - n_xt  # 1, or 9 with per-zone albedo
        lower = np.concatenate([_LOWER[:3], np.full(n_alb, _LOWER[3]), np.zeros(n_xt), _LOWER[4:]])
        upper = np.concatenate([_UPPER[:3], np.full(n_alb, _UPPER[3]), np.full(n_xt, 0.5), _UPPER[4:]])
        x = np.zeros((nb, nu))
        for i, p in enumerate(inits):
            x[i, :3] = p.slopes
        x[:, 3:3 + n_alb] = math.log(self.params.albedo)
        if xt_col is not None:
            x[:, xt_col] = self.params.crosstalk
        x[:, -2] = self.params.specular_weight
        x[:, -1] = math.log(self.params.specular_exponent)
        x = np.clip(x, lower, upper)
        for _ in range(2):  # albedo by linear least squares on the rendered shape (saturation: twice)
            h = rd.render(x, conv, ambient=amb)
            axes = (2,) if n_alb > 1 else (1, 2)
            scale = (h * obs).sum(axis=axes) / np.maximum((h * h).sum(axis=axes), 1e-12)
            x[:, 3:3 + n_alb] = np.clip(x[:, 3:3 + n_alb] + np.log(np.clip(scale, 1e-3, 1e3)).reshape(nb, -1),
                                        lower[3], upper[3])
        prior_mu = np.array([self.params.specular_weight, math.log(self.params.specular_exponent)])
        prior_w = 1.0 / np.array([self.opt.prior_specular_weight, self.opt.prior_log_exponent])

        # per-zone albedos (if any) are tied to their mean: (log rho_z - mean) / spread
        spread = self.opt.zone_albedo_spread
        tie = n_alb > 1 and spread is not None and math.isfinite(spread)
        centre = (np.eye(n_alb) - 1.0 / n_alb) / (spread if tie else 1.0)

        n_hist = N_ZONES * width  # histogram residuals; the priors' follow
        Jp = np.zeros((2 + (n_alb if tie else 0) + n_xt, nu))  # the priors' rows of the Jacobian (constant)
        Jp[0, -2], Jp[1, -1] = prior_w
        if tie:
            Jp[2:2 + n_alb, 3:3 + n_alb] = centre
        if xt_col is not None:  # the crosstalk about its calibrated value
            Jp[-1, xt_col] = 1.0 / self.opt.crosstalk_std
        inv_sigma_j = inv_sigma[..., None]

        def residual(xs, rows, jac=False):
            whole = rows.size == nb  # every frame (rows are sorted and distinct): no copies of the frames' arrays
            pick = (lambda v: v) if whole else (lambda v: v[rows])
            out = rd.render(xs, pick(conv), jacobian=jac, ambient=None if amb is None else pick(amb))
            h, dh = (out if jac else (out, None))
            res = np.empty((len(rows), n_hist + len(Jp)))
            hist = res[:, :n_hist].reshape(h.shape)
            np.multiply(np.subtract(h, pick(obs), out=hist), pick(inv_sigma), out=hist)
            res[:, n_hist:n_hist + 2] = (xs[:, -2:] - prior_mu) * prior_w
            if tie:
                res[:, n_hist + 2:n_hist + 2 + n_alb] = xs[:, 3:3 + n_alb] @ centre.T
            if xt_col is not None:
                res[:, -1] = (xs[:, xt_col] - self.params.crosstalk) / self.opt.crosstalk_std
            if not jac:
                return res
            J = np.empty((len(rows), n_hist + len(Jp), nu))
            np.multiply(dh, pick(inv_sigma_j), out=J[:, :n_hist].reshape(dh.shape))
            J[:, n_hist:] = Jp
            return res, J

        all_rows = np.arange(nb)
        # the cost at x comes with each Jacobian (no separate render to start); each frame keeps its residuals at
        # x and its last Jacobian, ``fresh`` where that Jacobian is at x or one converged (small) step from it
        cost = np.full(nb, np.inf)
        res_at: np.ndarray | None = None
        J_at: np.ndarray | None = None
        fresh = np.zeros(nb, dtype=bool)
        lam = np.full(nb, 1e-3)
        active = np.ones(nb, dtype=bool)
        for _ in range(self.opt.max_iterations):
            rows = np.flatnonzero(active)
            if rows.size == 0:
                break
            r, J = residual(x[rows], rows, jac=True)
            if rows.size == nb:  # every frame (always so at first): keep the arrays themselves
                res_at, J_at = r, J
            else:
                res_at[rows], J_at[rows] = r, J
            fresh[rows] = True
            cost[rows] = (r * r).sum(axis=1)
            Jt = J.transpose(0, 2, 1)
            JtJ = Jt @ J  # matmul (BLAS): several times faster than einsum for (B, 9 W, unknowns)
            g = (Jt @ r[..., None])[..., 0]
            diag = np.einsum("bii->bi", JtJ) + 1e-12
            pending = np.ones(rows.size, dtype=bool)
            for _inner in range(8):
                sel = np.flatnonzero(pending)
                if sel.size == 0:
                    break
                rr = rows[sel]
                A = JtJ[sel].copy()
                A[:, np.arange(nu), np.arange(nu)] += lam[rr, None] * diag[sel]
                try:
                    step = -np.linalg.solve(A, g[sel][..., None])[..., 0]
                except np.linalg.LinAlgError:
                    step = -np.stack([np.linalg.lstsq(Ai, gi, rcond=None)[0] for Ai, gi in zip(A, g[sel])])
                xn = np.clip(x[rr] + step, lower, upper)
                rn = residual(xn, rr)
                cn = (rn ** 2).sum(axis=1)
                better = np.isfinite(cn) & (cn < cost[rr])
                acc = rr[better]
                dec = cost[acc] - cn[better]
                rel = dec / np.maximum(cost[acc], 1e-300)
                small = dec < self.opt.chi2_tolerance * np.maximum(cn[better] / n_res_own[acc], 1.0)
                x[acc], cost[acc], res_at[acc] = xn[better], cn[better], rn[better]
                done = (rel < self.opt.tolerance) | small
                fresh[acc] = done  # a converged step leaves the Jacobian good for the covariance
                lam[acc] = np.maximum(lam[acc] * 0.3, 1e-9)
                active[acc[done]] = False
                worse = rr[~better]
                lam[worse] *= 10.0
                active[worse[lam[worse] > 1e8]] = False
                pending[sel[better]] = False
                pending[sel[~better][lam[worse] > 1e8]] = False
        n_res = N_ZONES * width
        # covariance of the unknowns at the solution: the Gauss-Newton inverse (priors included),
        # scaled by the histogram residual's chi-square per degree of freedom; the Jacobian is evaluated again
        # only where the last one is more than a converged step away (the iteration limit)
        stale = np.flatnonzero(~fresh)
        if res_at is None:
            res_at, J_at = residual(x, all_rows, jac=True)
        elif stale.size:
            res_at[stale], J_at[stale] = residual(x[stale], stale, jac=True)
        res, J = res_at, J_at
        chi2_red = (res[:, :n_res] ** 2).sum(axis=1) / np.maximum(n_res_own - nu, 1)
        # the residual reported (and tested against chi2_limit): the bins near the returns
        core = np.arange(width) < np.minimum(N_BINS, last_peak + min(self.opt.test_window,
                                                                     self.opt.window_after_peak))[:, None]
        core_cost = (((res[:, :n_res].reshape(nb, N_ZONES, width) ** 2) * core[:, None, :]).sum(axis=(1, 2))
                     + (res[:, n_res:] ** 2).sum(axis=1))  # and the priors, as in the solver's cost
        n_core = N_ZONES * core.sum(axis=1)
        JtJ = J.transpose(0, 2, 1) @ J
        try:
            inv = np.linalg.inv(JtJ)
            if not np.all(np.isfinite(inv)):
                raise np.linalg.LinAlgError("not finite")
        except np.linalg.LinAlgError:
            inv = np.linalg.pinv(JtJ)
        cov = inv[:, :3, :3] * chi2_red[:, None, None]
        # the reported albedo's spread: the mean log albedo over zones (one albedo: that one)
        albedo_std = np.sqrt(np.abs(inv[:, 3:3 + n_alb, 3:3 + n_alb].sum(axis=(1, 2))) / n_alb ** 2 * chi2_red)
        # report one albedo: the mean log albedo over zones when each zone has its own
        xr = np.concatenate([x[:, :3], x[:, 3:3 + n_alb].mean(axis=1, keepdims=True)], axis=1)
        return [self._finish(xr[i], float(core_cost[i]), int(n_core[i]), cov[i], float(albedo_std[i]))
                for i in range(nb)]

    def _kernels(self, frames: list[Frame]) -> np.ndarray:
        """The frames' pulse kernels (B, K): the model's pulse (:func:`~place_safe.recovery.forward.pulse_kernel`) as
        matrices (:class:`~place_safe.recovery.forward.PulseMatrices`, built on first use)."""
        if self._pulse is None:
            self._pulse = PulseMatrices(self.model.t)
        return self._pulse(np.array([f.reference for f in frames], dtype=float))

    def _reported(self, a: float, b: float, z0: float) -> Plane:
        """The plane of optical-frame unknowns, range-corrected, in the reported sensor frame."""
        return self._reported_many(np.array([a]), np.array([b]), np.array([z0]))[0]

    def _reported_many(self, a: np.ndarray, b: np.ndarray, z0: np.ndarray) -> list[Plane]:
        """:meth:`_reported` of each element of the arrays (the corrections evaluated at once)."""
        da, db = self.correction.slopes(z0, a, b)
        a, b, z = a + da, b + db, z0 + self.correction(z0)
        planes = []
        for i in range(len(z)):
            optical = Plane.from_slopes(float(a[i]), float(b[i]), float(z[i]))
            planes.append(Plane(self._mount @ optical.normal, optical.offset))
        return planes

    #: steps of the numerical Jacobian of the reported plane in (a, b, z0)
    _STEPS = (1e-6, 1e-6, 1e-7)

    def _plane_and_covariance(self, a: float, b: float, z0: float,
                              cov_abz: np.ndarray | None) -> tuple[Plane, np.ndarray | None]:
        """The reported plane (:meth:`_reported`) and the covariance of (a, b, z0) ``cov_abz`` mapped to (n_x, n_y, d) of
        it (numerical Jacobian; None without a finite ``cov_abz``)."""
        if cov_abz is None or not np.all(np.isfinite(cov_abz)):
            return self._reported(a, b, z0), None
        pts = np.tile(np.array([a, b, z0]), (4, 1))  # the solution, and each unknown moved by its step
        for k, h in enumerate(self._STEPS):
            pts[1 + k, k] += h
        planes = self._reported_many(pts[:, 0], pts[:, 1], pts[:, 2])
        f0 = tilt_offset(planes[0])
        jac = np.zeros((3, 3))
        for k, h in enumerate(self._STEPS):
            jac[:, k] = (tilt_offset(planes[1 + k]) - f0) / h
        return planes[0], jac @ cov_abz @ jac.T

    def _finish(self, x: np.ndarray, cost: float, n_res: int, cov_abz: np.ndarray | None = None,
                albedo_std: float | None = None) -> PlaneEstimate:
        """The estimate of the solved unknowns ``x`` (a, b, z0, log albedo); ``albedo_std``: the log albedo's posterior
        spread (None: not known), above :data:`ALBEDO_STD_LIMIT` (or not finite) the albedo is not reported."""
        a, b, z0, lr = (float(v) for v in x[:4].tolist())
        if not all(math.isfinite(v) for v in (a, b, z0, lr)):
            return PlaneEstimate(None, reason="solver diverged (non-finite plane)")
        if z0 <= 0:
            return PlaneEstimate(None, reason="solver found no plane in front of the sensor")
        try:
            plane, cov = self._plane_and_covariance(a, b, z0, cov_abz)
            if cov is not None:
                cov = self.uncertainty.apply(cov, plane.offset, plane.normal)
        except NoPlaneError as exc:
            return PlaneEstimate(None, reason=str(exc))
        determined = albedo_std is None or (math.isfinite(albedo_std) and albedo_std <= ALBEDO_STD_LIMIT)
        return PlaneEstimate(plane, albedo=math.exp(lr + self.correction.log_albedo(z0)) if determined else None,
                             residual=math.sqrt(max(cost, 0.0) / n_res),
                             covariance=cov, method_used=self.name)

    # -- the paper's procedure -----------------------------------------------------------------
    def _solve_paper(self, frames: list[Frame], inits: list[Plane]) -> list[PlaneEstimate]:
        """Adam over (theta, phi, z0, albedo, specular weight, exponent), random rays, per frame."""
        out = []
        rng = np.random.default_rng(self.opt.seed)
        paper_model = ForwardModel(self.params, ZoneRays.random(self.opt.paper_rays, rng, dtype=torch.float32),
                                   dtype=torch.float32)
        for f, p in zip(frames, inits):
            obs, sigma, kernel, width, amb = self._prepare([f], [p])
            obs32 = obs[0].float()
            scale = torch.clamp(obs32.max(), min=1.0)
            x0 = self._initial_x([f], [p], obs, kernel, width, amb)[0]
            theta = torch.tensor(p.theta, dtype=torch.float32, requires_grad=True)
            phi = torch.tensor(p.phi, dtype=torch.float32, requires_grad=True)
            z0 = torch.tensor(p.z0, dtype=torch.float32, requires_grad=True)
            log_rho = torch.tensor(float(x0[3]), dtype=torch.float32, requires_grad=True)
            ks = torch.tensor(self.params.specular_weight, dtype=torch.float32, requires_grad=True)
            log_alpha = torch.tensor(math.log(self.params.specular_exponent), dtype=torch.float32, requires_grad=True)
            # per-parameter step sizes: radians for angles, metres for z0 (a tenth of the lr), log units
            adam = torch.optim.Adam([{"params": [theta, phi, log_rho, ks, log_alpha], "lr": self.opt.paper_lr},
                                     {"params": [z0], "lr": self.opt.paper_lr * 0.1}])
            k32 = kernel.float()
            for _ in range(self.opt.paper_iterations):
                adam.zero_grad()
                n = torch.stack([torch.sin(theta) * torch.cos(phi), torch.sin(theta) * torch.sin(phi), torch.cos(theta)])
                h = paper_model.render_plane(n.unsqueeze(0), (z0 * torch.cos(theta)).reshape(1),
                                             torch.exp(log_rho).reshape(1), None,
                                             specular_weight=ks.reshape(1),
                                             specular_exponent=torch.exp(log_alpha).reshape(1), kernel=k32,
                                             n_bins=width, ambient=None if amb is None else amb.float())[0]
                loss = (((h - paper_model.t["floor"]) - obs32) / scale).pow(2).mean()
                loss.backward()
                adam.step()
                with torch.no_grad():
                    z0.clamp_(min=1e-3)
            with torch.no_grad():
                try:
                    z_corr = float(z0) + self.correction(float(z0))
                    optical = Plane.from_angles(float(theta), float(phi), z_corr)
                    plane = Plane(self._mount @ optical.normal, optical.offset)
                except NoPlaneError as exc:
                    out.append(PlaneEstimate(None, reason=str(exc)))
                    continue
                res = torch.sqrt(loss).item()
            if not math.isfinite(res):
                out.append(PlaneEstimate(None, reason="solver diverged (non-finite loss)"))
            else:
                out.append(PlaneEstimate(plane, albedo=math.exp(float(log_rho.detach())
                                                           + self.correction.log_albedo(float(z0))), residual=res))
        return out
