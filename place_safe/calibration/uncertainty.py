"""Calibrating how far to trust a method: its model-error floor and, for ``diff``, when to fall back to peak.

Concept
-------
A method's own covariance (its fit linearised at the solution, scaled by the residual; see
:mod:`place_safe.recovery.estimator`) describes noise. What the method's model gets wrong is not noise:
it is measured here on frames with ground truth and added as a floor
(:class:`~place_safe.recovery.estimator.Uncertainty`: a constant and a distance-dependent variance for
the tilt components and for the offset), chosen by maximum likelihood of the frames' errors under the
Gaussian with the estimate's covariance plus the floor; then one ``scale`` of the covariance makes the
mean normalised estimation error squared (NEES, per degree of freedom; about 1 when the covariances are
honest) 1 on these frames. NEES is reported before and after.

For ``peak`` closer than the near-range table's end (9 cm) the zones' range errors grow by orders of
magnitude (the real sweep: 0.1 mm at 8 cm, 2 mm at 2 cm, 4-6 mm at 1 cm) and the zones' lever arm
shrinks with the distance: no floor of the far-range form describes both. There each zone's error in the
plane fit's covariance is at least the zones' cross-validated range error at that distance
(:meth:`~place_safe.recovery.estimator.Uncertainty.near_std`,
:func:`~place_safe.calibration.near_range.near_range_std`,
:func:`~place_safe.recovery.points.plane_covariance`), and the floor and scale are fitted on the frames
beyond it. Held out on the real sweep's halves the 1-5 cm mean NEES per dof went from 42 / 8.7 to 16 / 4.4
and the 5-40 cm one from 1.28 / 1.07 to 1.34 / 0.98. The 1.25 cm frame stays 7 sigma off: its zones' errors
are correlated (a distortion that looks like a tilt), which independent zone errors do not describe.

A level sweep cannot show what a tilt does to ``peak``: each zone's return spreads over its footprint and
the peak method reads the slope short (on mismatched units 0.06-0.08 rad per unit ``tan(tilt)``, 1.4 deg mean
at 0-30 deg, where its level-calibrated covariance said 0.03 deg). Its covariance gets the stated tilt term
``Uncertainty.tilt_rel =`` :data:`PEAK_TILT_REL` per tilt component when the calibration frames are level (with 8 or
more tilted frames among them, sized on those: :func:`size_tilt_term`); mostly tilted frames fit the edge and corner
scales behind it, and the floor fitted on them holds the rest (as diff's below). Diff's level-calibrated covariance is
overconfident on tilts too (mean NEES per dof 4.7-30 on tilted frames of level-calibrated units): its covariance
gets a stated tilt term when the calibration frames are level (their tilts spread less than
:data:`~place_safe.calibration.points.MIN_TILT_SPREAD`), sized by the unit's relative model error, the share of each
bin's counts the fitted forward model misses at the calibration frames' true planes (:func:`diff_tilt_term`: a
model that misses the return's shape by more misreads a tilted plane's spread return by more; one fixed term left
the NEES per dof of 7 level-calibrated units at 0.38-3.5, the model-error law 0.32-1.65; with the forward fit in each
unit's own basin, floors on both parts: :data:`DIFF_TILT_FLOOR`, :data:`DIFF_TILT_OFFSET_FLOOR`); calibration frames with
tilts show the tilt error, and the floor and scale fitted on them hold it (with the stated term on top as well, the
independent generator's tilted calibration gave a held-out NEES per dof of 0.64). A level sweep with a few tilted
frames (at least :data:`TILT_TERM_MIN_FRAMES`, fewer than :data:`DIFF_TILTED_SHARE` of the frames) keeps the stated
term, sized on those frames (:func:`size_tilt_term`: one factor on its tilt part, one on its offset part), with the
floor fitted on the level frames: the model error says how wrong the model is, the tilted frames how much of that a
tilt turns into a plane error (unit 32, whose heavy tails the model-error law under-states: NEES per dof 4.3 with a
level sweep alone).

For ``diff`` the fallback to peak is a safety net chosen on held-out frames (:func:`select_fallback`): a
frame falls back when its residual chi-square is above ``chi2_limit``, when the two estimates contradict each
other (:data:`CONSISTENCY_LIMIT`), or when diff's tilt variance is above ``prefer_ratio`` times peak's (peak
reads this slope better). The calibration frames are split in :data:`CV_FOLDS` folds interleaved in distance;
for each, diff's floor is fitted on the others and every candidate pair (chi2_limit, prefer_ratio) returns a
plane for each held-out frame. Each pair is scored over all held-out frames by its returned planes: the
worse of the mean angular and mean point error, each per frame in units of peak's median error and capped at
10 (so frames on which both methods fail do not decide). Of the pairs within one standard error of the best score
(:data:`FALLBACK_SCORE_SE`, paired: each against the best on the same frames) and keeping diff on some frame (where
the best does), the one with the largest chi-square limit wins, then the one that keeps diff on the most frames,
then the ratio nearest 1. There is no "always fall back" candidate: where
diff's own covariance says it reads the slope better, a level sweep cannot tell otherwise, and the
per-frame comparison already returns peak where peak reads better.

With :data:`BLEND` (the default) the preference is not a choice: a frame that passes the chi-square limit and the
consistency test returns diff's plane blended with peak's by their variances (:mod:`place_safe.recovery.blend`),
so only ``chi2_limit`` is chosen, on the blended planes' held-out errors (the floor of the other folds sizes diff's
weight), and ``prefer_ratio`` is written null; unless the best choice between the two planes scores clearly better
on these frames (:func:`_blend_holds`), which is then kept as before. Pairs within :data:`FALLBACK_SCORE_REL` of the
best score count as within whatever their standard error. Units: rad, m.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from place_safe.evaluation.metrics import angular_errors, nees, point_errors  # noqa: F401 (nees: re-exported)
from place_safe.recovery.estimator import MAX_SCALE, MIN_SCALE, NEAR_MAX_STD, PlaneEstimate, Uncertainty, tilt_offset
from place_safe.calibration.far_range import far_growth
from place_safe.recovery.too_close import OVERLAP_RANGE, TOO_CLOSE_REASON, plane_overlap_reason
from place_safe.sensor.frame import Frame
from place_safe.sensor.histogram import find_peaks
from place_safe.calibration.near_range import held_out_fits, near_range_std
from place_safe.calibration.point_errors import true_ranges
from place_safe.exceptions import CalibrationError, FrameError, NoPlaneError
from place_safe.recovery.points import PlaneFitGeometry, plane_fit_geometry, plane_through
from place_safe.calibration.points import (MIN_CALIBRATION_RANGE, MIN_TILT_SPREAD, level_frames, refit_mapping,
                                          tilt_angles)
from place_safe.recovery.blend import blended
from place_safe.recovery.diff_settings import BLENDED, CROSSTALK_LEFT_SHARE, NEAR_FALLBACK_RANGE
from place_safe.recovery.peak import (ZONE_TILT_SCATTER, PeakEstimator, near_applies, near_covariances,
                                     zone_tilt_variance)


def _nll(errors: np.ndarray, covs: np.ndarray, extra: np.ndarray) -> float:
    """Mean negative log-likelihood of errors (F, k) under covariances covs (F, k, k) + extra (F, k, k)."""
    rows = _nll_rows(errors, covs + extra)
    return math.inf if rows is None else float(np.mean(rows))


def _nll_rows(errors: np.ndarray, covs: np.ndarray) -> np.ndarray | None:
    """Each row's negative log-likelihood (F,) of errors (F, k) under covariances (F, k, k); None where a covariance
    is not positive definite."""
    sign, logdet = np.linalg.slogdet(covs)
    if np.any(sign <= 0):
        return None
    quad = np.einsum("fi,fi->f", errors, np.linalg.solve(covs, errors[..., None])[..., 0])
    return 0.5 * (quad + logdet)


def _fit_two(errors: np.ndarray, covs: np.ndarray, basis: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """Maximum-likelihood variances (v0, v1) >= 0 of ``v0 * basis[0] + v1 * basis[1]`` (each (F,) scaling I)."""
    from scipy.optimize import minimize

    k = errors.shape[1]
    eye = np.eye(k)
    scale = np.array([max(float(np.mean(errors ** 2) / np.mean(b)), 1e-20) for b in basis])

    def f(logv: np.ndarray) -> float:
        v = np.exp(logv) * scale
        extra = (v[0] * basis[0] + v[1] * basis[1])[:, None, None] * eye
        return _nll(errors, covs, extra)

    best = None
    for start in ((0.0, -6.0), (-6.0, 0.0), (-1.0, -1.0)):
        res = minimize(f, np.array(start), method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-6, "maxiter": 400})
        if best is None or res.fun < best.fun:
            best = res
    v = np.exp(best.x) * scale
    v[v < 1e-6 * scale] = 0.0  # a term the data do not want
    return float(v[0]), float(v[1])


#: m: the offset floor an uncertainty entry states when its frames want no floor term at all (their covariances
#: already cover their errors; diff's on the whole real sweep, NEES per dof 0.59 without one): a micrometre, far
#: below any plane's error, so that the entry still states a model error (one stating none is refused on load,
#: :meth:`~place_safe.recovery.estimator.Uncertainty.states_no_floor`).
MIN_OFFSET_FLOOR = 1e-6


def fit_floor(estimates: Sequence[PlaneEstimate], truths: Sequence, base: Uncertainty | None = None) -> tuple[Uncertainty, dict]:
    """The floors of :class:`Uncertainty` for estimates whose covariances hold no floor yet (maximum likelihood;
    ``base``'s tilt term counts as known)."""
    base = base or Uncertainty()
    rows = [(tilt_offset(e.plane) - tilt_offset(t), np.asarray(e.covariance, dtype=float) + base.tilt_floor(e.plane.normal, e.plane.offset),
             e.plane.offset) for e, t in zip(estimates, truths) if e.ok and e.covariance is not None and t is not None]
    if len(rows) < 3:
        return base, {"frames": len(rows), "why": "fewer than 3 estimates with a covariance"}
    err = np.array([r[0] for r in rows])
    cov = np.array([r[1] for r in rows])
    d = np.maximum(np.array([r[2] for r in rows]), 1e-3)
    one = np.ones(len(d))
    t0, t1 = _fit_two(err[:, :2], cov[:, :2, :2], (one, 1.0 / d ** 2))
    o0, o1 = _fit_two(err[:, 2:], cov[:, 2:, 2:], (one, d ** 2))
    unc = base.replace(tilt_std=math.sqrt(t0), tilt_range_std=math.sqrt(t1), offset_std=math.sqrt(o0),
                       offset_rel=math.sqrt(o1))
    held = unc.states_no_floor()  # the covariances already cover the errors: no term wanted
    if held:  # ... an entry states a floor all the same (a file stating none is refused on load)
        unc = unc.replace(offset_std=MIN_OFFSET_FLOOR)
    before = float(np.mean([e @ np.linalg.solve(c, e) for e, c in zip(err, cov)]) / 3.0)
    ml = float(np.mean([e @ np.linalg.solve(c + unc.floor(dd), e) for e, c, dd in zip(err, cov, d)]) / 3.0)
    unc = unc.replace(scale=float(np.clip(ml, MIN_SCALE, MAX_SCALE)))  # mean NEES per dof 1 on these frames
    after = float(np.mean([e @ np.linalg.solve(unc.apply(c, dd), e) for e, c, dd in zip(err, cov, d)]) / 3.0)
    return unc, {"frames": len(rows), "tilt_std_deg": math.degrees(unc.tilt_std), "scale": unc.scale,
                 "nees_per_dof_maximum_likelihood": ml,
                 "tilt_range_std_mm": unc.tilt_range_std * 1e3, "offset_std_mm": unc.offset_std * 1e3,
                 "offset_rel": unc.offset_rel, "nees_per_dof_before": before, "nees_per_dof_after": after,
                 **({"floor_held": f"no floor term wanted by these frames; offset_std held at "
                                   f"{MIN_OFFSET_FLOOR * 1e6:.0f} um"} if held else {})}


#: Squared Mahalanobis distance between the diff and peak estimates of (n_x, n_y, d) above which diff falls
#: back to peak: the 99.9 % point of chi-square with 3 degrees of freedom (honest covariances: 1 frame in 1000).
CONSISTENCY_LIMIT = 16.27


#: Tilt term of peak's covariance (:attr:`~place_safe.recovery.estimator.Uncertainty.tilt_rel`): each tilt
#: component's std per unit tan(tilt). Measured per component (RMS over frames tilted 3-30 deg, 5-30 cm):
#: mismatched units A and B 0.047 and 0.048; the unit A's own calibrated forward model, rendered tilted, 0.046;
#: the independent generator 0.023. A level sweep shows none of it, so it is stated, not fitted; calibration frames
#: mostly tilted (as diff's: :data:`DIFF_TILTED_SHARE`) fit the edge and corner scales that cause it, and the floor
#: fitted on them holds what is left (the packaged mismatched calibration, rig sweep tilted to 12 deg, read on 80
#: frames tilted 0-12 deg: NEES per dof 2.56 with the term on top, its full 0.05 where the frames' errors are 0.01;
#: 1.44 without). A level sweep with a few tilted frames keeps it, sized on them (:func:`size_tilt_term`): those
#: frames also fitted the edge and corner scales, so in sample they read 0.003 per unit tan(tilt); sized to that, new
#: tilted frames of mismatched units A and 32 (12 tilts) erred 1.3 times their stated tilt std (each tilt component's
#: NEES 1.6-1.7) and diff fell back to peak on 99 % of them, where its own plane is 3 times better in range. With diff's
#: lower bound (half the stated term) their NEES per dof is 1.40-1.44 (tilt components 0.05-0.07: cautious).
PEAK_TILT_REL = 0.05
#: The offset part of peak's stated tilt term (:attr:`~place_safe.recovery.estimator.Uncertainty.tilt_offset_rel`,
#: its std per unit z0 tan(tilt)) per radian of the mount tilt the unit's forward model holds (:func:`peak_tilt_term`).
#: A level sweep cannot tell a sensor mounted off its nominal orientation from zones that each keep their own time:
#: both make the zones' ranges on a level table differ in proportion to the distance. The peak method reads it the
#: second way (its zone gains absorb it, its zone directions are held), and a forward fit that keeps its geometry
#: (:func:`~place_safe.calibration.second_fit.reconsider_geometry`) reads it the first. On a tilted plane the two
#: readings part: peak's offset moves by a share of ``mount tilt * z0 tan(tilt)`` that does not follow its tilt error,
#: where its stated term has none (it turns the plane about the point it crosses the axis). Measured (mismatched unit A
#: with a true mount tilt of 0.94 deg, and with 0.59 deg and fields of view 0.93 / 0.88; 150 frames tilted 5-30 deg,
#: 5-30 cm): peak's z0 error over ``z0 tan(tilt)``, RMS, 0.0122 and 0.0075 (unit A without the tilt: 0.0025), 0.74 and
#: 0.73 of the fitted mount tilt; peak's NEES per dof there was 25 and 127, and diff, whose own plane read 0.06 deg,
#: fell back to peak's (1.4 deg) on 54 % and 26 % of the frames as "inconsistent" (docs/results.md, "A sensor mounted
#: off its nominal orientation").
PEAK_MOUNT_OFFSET_REL = 0.75
#: The peak report's note (``calibrate`` prints it) when a peak-only calibration takes the mount of a forward model
#: already in the file.
PEAK_MOUNT_NOTE = ("peak's covariance on tilted planes widens by the mount tilt ({deg:.2f} deg) of the forward model "
                   "already in this file (or, where it holds the mount level, of its level sweep's other reading); that "
                   "holds only if the file was calibrated on this unit (calibrate --method diff on this sweep fits the "
                   "mount again)")

#: The peak report's note (``calibrate --method peak`` prints it) when its frames are level (too few tilted ones to size
#: its tilt term): peak reads each zone's range on its nominal direction, and a level table cannot show how far the
#: unit's zones look from those directions, which scales every slope it reads. A simulated unit calibrated on a level
#: sweep in MuJoCo read 12 and 24 deg planes at 12.9-13.0 and 25.6-25.7 deg (7 % steep; its NEES per dof 0.74: the
#: stated term, :data:`PEAK_TILT_REL`, holds it). Diff's calibration prints its own note on the same capture.
PEAK_TILT_NOTE = ("peak's slopes on tilted planes are not calibrated: a level table cannot show how far the unit's "
                  "zones look from their nominal directions, which scales every slope peak reads (a few per cent: on "
                  "a simulated unit 7 % steep, 24 deg read as 25.7); its covariance states "
                  f"{PEAK_TILT_REL:.0%} of the slope; capture about 20 tilted poses too (capture --distances "
                  "80,150,220 --incidences 12,24 --azimuths 0,90,180,270) and calibrate on both files")

#: Tilt term of diff's covariance (:meth:`~place_safe.recovery.estimator.Uncertainty.tilt_floor`) for level
#: calibration frames whose unit's model error is not known (:func:`diff_tilt_term`; the values before the model-error
#: law): each tilt component's std per unit tan(tilt), the plane turning about the sensor (pivot 0: the offset's error
#: on tilted frames follows the tilt's only in part, a fitted pivot of 0.3-0.9 z0 leaves 0.06-0.17 mm of it over), and
#: an independent offset std per unit z0 tan(tilt). Measured RMS over frames tilted 3-30 deg, 5-30 cm, of
#: level-calibrated units (per tilt component / offset): the independent generator 0.017 and 0.012 / 0.0031,
#: mismatched unit A 0.006 and 0.006 / 0.0022, unit B 0.007 and 0.009 / 0.0041.
#: Where the tilt error comes from: each zone's footprint is wide (std 0.05 rad about a centre 0.18 rad off axis);
#: a level sweep shows the zones' mean squared off-axis angle, the slope needs their mean angle, and the two differ
#: by the footprint's spread, which the model weighs differently from a unit (the generator's pixels, fill factor
#: and cos^4 fall-off: the fitted fields of view read its tilts 2 % short); and a tilted plane spreads each zone's
#: return over a range of depths, whose shape the model renders only as well as it renders the unit's pulse.
DIFF_TILT_REL = 0.015
DIFF_TILT_OFFSET_REL = 0.0015
DIFF_TILT_PIVOT = 0.0
#: The tilt term from the unit's relative model error ``e`` (:func:`diff_tilt_term`; the forward fit's
#: ``model_error_chi2``: the share of each bin's counts, beyond shot noise, that the fitted model misses at the true
#: planes of the calibration frames): each tilt component's std per unit tan(tilt) ``hypot(DIFF_TILT_FLOOR,
#: DIFF_TILT_PER_ERROR e)``, the offset's std per unit z0 tan(tilt) ``hypot(DIFF_TILT_OFFSET_FLOOR,
#: DIFF_TILT_OFFSET_PER_ERROR e)``. A tilted plane
#: spreads each zone's return over ``z0 tan(tilt)`` times the footprint's width; a model that misses the return's
#: shape by ``e`` misreads where that spread return sits by a share of the spread that grows with ``e``. Measured on 7
#: level-calibrated simulated units (docs/results.md, "Diff's covariance on tilted frames of other units"): the
#: offset std each unit's tilted frames need (NEES 1 on the offset) over its ``e`` is 0.062-0.075 on 6 of 7 units
#: (mismatched A 0.037: conservative there), against a spread of 0.0015-0.0055 in the std itself; the tilt's need
#: follows ``e`` less closely (0.056-0.14 on the mismatched units); the floor is for what no level sweep shows (the
#: footprint's weighting: the independent generator with sensor seed 0 needs 0.013 at ``e`` = 0.04). Chosen over the 7
#: units (with the tilt floor at 0.008 and no offset floor, the fit as it was then): mean NEES per dof 0.32-1.65 on
#: them (6 in 0.5-2; before 0.38-3.5, 3 in the band).
#: Since the forward fit finds each unit's own pulse (:data:`~place_safe.calibration.forward_fit.PULSE_SOFT_BIN_STARTS`)
#: the model errors are 0.006-0.038 instead of 0.04, and the offset's need no longer follows ``e``: unit 33
#: (``e`` 0.006) needs 0.0021 per z0 tan(tilt), A (0.009) 0.0009, B (0.011) 0.0017, 32 (0.033) 0.0058, the
#: generator (0.038) 0.0023; the tilt's need is 0.0025-0.0045 (32: 0.0088). So both parts have a floor now, each the
#: hypot with its model-error part: :data:`DIFF_TILT_FLOOR` 0.008 -> 0.005 and :data:`DIFF_TILT_OFFSET_FLOOR` 0.001.
#: Mean NEES per dof of diff's own planes on the six units' tilted frames (A, B, 31, 32, 33, generator): 0.79, 1.86,
#: 0.36, 4.31, 4.52, 0.67 with the old law and the new fit -> 0.29, 0.77, 0.33, 4.01, 1.33, 0.75 (docs/results.md,
#: "The forward fit's two basins, landed"): fewer overconfident, more cautious ones. A level sweep does not show which
#: a unit needs; 12 tilted frames size it (``unit_scorecard.py --few-tilts 12``).
#: Re-sized 0.005 -> 0.003 (2026-12-01, session 61) once the simulator rendered each zone's time scale before the bins
#: (docs/results.md, "Diff's stated tilt floor re-sized"): with every stated term off, the tilt part each unit's tilted
#: frames need is 0.0005-0.0013 on units whose zones keep their own time with no mount, 0.0012-0.0032 on units without
#: time scales, 0.0020-0.0042 on units with both (a level sweep does not tell these apart); the floor is the least of
#: 0.0025-0.004 at which no one of 51 training units read NEES per dof above 1.5 (unit 43: 1.47) or its returned angle
#: 0.01 deg worse; five units set before (70-74) read 0.15-1.60 (were 0.09-1.27).
DIFF_TILT_FLOOR = 0.003
DIFF_TILT_PER_ERROR = 0.1
#: Each tilt component's std per unit tan(tilt) per unit of the forward fit's crosstalk (:func:`diff_tilt_term`), added
#: in quadrature: a level sweep trades the crosstalk between zones against the zones' fields of view
#: (:data:`~place_safe.calibration.forward_fit.LEVEL_SWEEP_TRADED`), and the crosstalk sets how steep diff reads a
#: slope. Measured on the independent generator (docs/results.md, "What a level sweep leaves to the crosstalk"): a
#: crosstalk 0.0117 too high read seed 1's slopes 4.7-6.6 % steep, 0.0127 too high seed 7's 3-7 %: about 4.5 per unit
#: of crosstalk. What the level sweep leaves of the crosstalk is taken as half its fitted value (seeds 0 and 3 fitted
#: 0.012 and 0.0065 against 0.0098 and true values near; 1 and 7 2.5-3 times the truth), so 4.5 / 2. A unit whose
#: fit finds no crosstalk (the mismatched units 1e-6-1e-4, the real unit 1e-5) gets nothing from it.
DIFF_TILT_PER_CROSSTALK = 4.5 * CROSSTALK_LEFT_SHARE
#: The offset's std per unit z0 tan(tilt) per unit of the forward fit's crosstalk (:func:`diff_tilt_term`), added in
#: quadrature to the offset part: the same trade moves where diff reads a tilted plane along the optical axis. With
#: each frame solving its own crosstalk (``SolverOptions.crosstalk_std``) the generator's sensor seeds 1, 2, 7 and 8
#: (level sweeps, fitted crosstalk 0.014-0.021) needed 0.21-0.47 for NEES 1 on the offset; without it their offsets
#: read NEES 2.5-26 (docs/results.md, "Each frame's own crosstalk").
DIFF_TILT_OFFSET_PER_CROSSTALK = 0.3
DIFF_TILT_OFFSET_FLOOR = 0.001
DIFF_TILT_OFFSET_PER_ERROR = 0.05
#: the share of calibration frames tilted MIN_TILT_SPREAD or more (from the least tilted) from which the fitted floor
#: holds diff's tilt error without the stated term: a level sweep of 150 frames with 30 tilted ones (17 %) held
#: out NEES per dof 2.65 on the independent generator's tilted frames without it (10 tilted: 6.7)
DIFF_TILTED_SHARE = 0.5
#: Tilted frames (MIN_TILT_SPREAD or more from the least tilted, read by diff under its chi-square limit) among mostly
#: level calibration frames from which the stated tilt term is sized on them (:func:`size_tilt_term`): "a few tilts"
#: added to a level sweep. Held out on the
#: other tilted frames of 7 level-calibrated simulated units, 10 such frames took the NEES per dof from 0.52-3.62 to
#: a median 0.77-1.22 over 20 random draws of the ten, 95-100 % of draws in 0.5-2 (20 frames: 0.73-0.99, 95-100 %).
TILT_TERM_MIN_FRAMES = 8
#: Bounds of the factors on the stated term's tilt and offset parts that the tilted frames may choose: at most
#: halved (a few frames that happen to read well do not take the term away), at most ten times.
TILT_TERM_SCALES = (0.5, 10.0)
#: The diff report's note (``calibrate`` prints it last) when the stated tilt term is not sized on tilted frames. The
#: slopes too: a level sweep trades the crosstalk between zones against the zones' fields of view
#: (:data:`~place_safe.calibration.forward_fit.LEVEL_SWEEP_TRADED`), and the crosstalk sets how steep diff reads a
#: slope; diff read the independent generator's seeds 1 and 7 3-7 % steep after a level sweep (their fits' crosstalk
#: 2.5-3 times the truth), 0.07-0.10 deg with 12 tilted frames added (docs/results.md, "The independent generator's other
#: sensors, by a level sweep alone" and "What a level sweep leaves to the crosstalk"); with each frame's own crosstalk
#: solved, seed 2 still reads 0.23 deg against peak's 0.21 ("Each frame's own crosstalk").
TILT_TERM_NOTE = ("diff's covariance on tilted planes is stated from the unit's model error, not measured: diff read "
                  "{n} of the calibration frames tilted 5 deg or more from the least tilted ({need} needed, and "
                  "fewer than half of all frames), and a level table cannot tell the crosstalk between zones from their "
                  "fields of view (diff solves each tilted frame's own crosstalk, but what the fit's other terms took "
                  "up of it stays), so on some units diff misreads slopes by a few per cent; capture about 20 tilted "
                  "poses too (capture --distances 80,150,220 --incidences 12,24 --azimuths 0,90,180,270) and "
                  "calibrate on both files for slopes and a covariance sized on them")

#: Added to :data:`TILT_TERM_NOTE` where diff's tilt term holds the two readings of a level sweep
#: (:func:`reading_disagreement`).
READINGS_NOTE = ("; this sweep also left two readings of the zones' geometry (fields of view and mount, or each zone's "
                 "own time scale) that read tilted planes {slope:.1%} apart in slope ({angle:.2f} deg on average at "
                 "5-30 deg), and diff's covariance there holds that difference: tilted poses tell the readings apart")
#: What :data:`READINGS_NOTE` adds where no tilted frames without ground truth were compared (``calibrate
#: --readings-from``, :mod:`place_safe.calibration.readings`), and where they were but chose neither reading.
READINGS_FROM_NOTE = (" (or, for the slopes alone, 20 or more frames of tilted surfaces without ground truth: calibrate "
                      "--readings-from FILE)")
READINGS_NEITHER_NOTE = " (the tilted frames without ground truth chose neither: {why})"


def _share(value) -> float | None:
    """``value`` as a number in [0, 1], or None where it is not a finite number >= 0."""
    if value is None or isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or value < 0.0:
        return None
    return min(float(value), 1.0)


def _magnitude(value):
    """``abs(value)`` of a real number (not a bool), else None."""
    return abs(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None


def diff_tilt_term(model_error: float | None = None, crosstalk: float | None = None,
                   disagreement: dict | None = None, mount_left: float | None = None) -> Uncertainty:
    """The stated tilt term of diff's covariance for level calibration frames, from the unit's relative model error
    ``model_error`` (dimensionless, the forward fit's ``model_error_chi2``; module constants
    :data:`DIFF_TILT_FLOOR`, :data:`DIFF_TILT_PER_ERROR`, :data:`DIFF_TILT_OFFSET_FLOOR`,
    :data:`DIFF_TILT_OFFSET_PER_ERROR`; taken at most 1): a unit
    the model fits worse gets a wider covariance on tilted planes, and none more on level ones (the term grows with
    tan(tilt)). Not known (None, not a finite number >= 0): :data:`DIFF_TILT_REL` and :data:`DIFF_TILT_OFFSET_REL`.
    ``crosstalk`` (the forward fit's, a fraction; None: not known, nothing added) adds
    :data:`DIFF_TILT_PER_CROSSTALK` times it to the tilt part in quadrature: what a level sweep leaves undetermined of
    the crosstalk turns into a slope scale; and :data:`DIFF_TILT_OFFSET_PER_CROSSTALK` times it to the offset part.
    ``disagreement`` (:func:`reading_disagreement`; None: the sweep told its readings apart, or had one) adds its
    ``slope_scale`` to the tilt part and its ``offset_bias`` to the offset part, both in quadrature: how differently
    diff reads a tilted plane under the other reading of the level sweep, which the sweep could not rule out.
    ``mount_left`` (rad; None: nothing added): the mount the free reading saw where the sweep adopted each zone's own
    time scale with the mount held level (:func:`mount_left`); :data:`ADOPTED_MOUNT_OFFSET_REL` times it goes into the
    offset part in quadrature. Pivot :data:`DIFF_TILT_PIVOT` either way."""
    e, xt = _share(model_error), _share(crosstalk)
    tilt, offset = ((DIFF_TILT_REL, DIFF_TILT_OFFSET_REL) if e is None else
                    (math.hypot(DIFF_TILT_FLOOR, DIFF_TILT_PER_ERROR * e),
                     math.hypot(DIFF_TILT_OFFSET_FLOOR, DIFF_TILT_OFFSET_PER_ERROR * e)))
    if xt is not None:  # (at most 1: Uncertainty's bound; the forward fit allows a crosstalk up to 0.5)
        tilt = min(math.hypot(tilt, DIFF_TILT_PER_CROSSTALK * xt), 1.0)
        offset = min(math.hypot(offset, DIFF_TILT_OFFSET_PER_CROSSTALK * xt), 1.0)
    if disagreement is not None:
        k, c = (_share(_magnitude(disagreement.get(key))) for key in ("slope_scale", "offset_bias"))
        tilt = min(math.hypot(tilt, k or 0.0), 1.0)
        offset = min(math.hypot(offset, c or 0.0), 1.0)
    if (m := _share(_magnitude(mount_left))) is not None:
        offset = min(math.hypot(offset, ADOPTED_MOUNT_OFFSET_REL * m), 1.0)
    return Uncertainty(tilt_rel=tilt, tilt_offset_rel=offset, tilt_pivot=DIFF_TILT_PIVOT)


#: Diff's offset std per unit ``z0 tan(tilt)`` per radian of the mount the free reading of a level sweep saw, where the
#: sweep adopted each zone's own time scale with the mount held level (:func:`mount_left`): the time scales take up as
#: much of a real mount as a level table shows, and leave the rays pointing off by what they did not, which on a tilted
#: plane moves the offset by ``z0 tan(tilt)`` times that pointing error. How much of the free reading's mount is real, a
#: level sweep cannot say: anywhere from none to all of it, whose RMS is ``1 / sqrt(3)`` of it. Measured (docs/results.md,
#: "Two readings of a level sweep"): units 39 and 42 (zones' own time and a mount of 1.0 and 1.2 deg; the free reading
#: 2.4 and 1.3 deg; 39's rays left 0.57 deg off) read their tilted frames at NEES per dof 4.8 and 8.6 without the term
#: and 0.35 and 0.57 with it (and peak's mount term from the same reading); units 34 and 36 (no mount; the free reading
#: 1.4 and 0.5 deg) 0.55 and 0.26 -> 0.22 and 0.18. Those units were simulated before 2026-11-30, with zone time scales
#: that also blurred each return; without the blur (docs/results.md, "Each zone's own time scale rendered before the
#: bins") 39 and 42 read 0.31 and 0.48, 34 and 36 0.08 and 0.12 (offset components far below 1): not re-sized.
ADOPTED_MOUNT_OFFSET_REL = 1.0 / math.sqrt(3.0)


def _forward_geometry(cal) -> dict:
    """``cal``'s ``reports.forward.geometry`` (:func:`~place_safe.calibration.second_fit.reconsider_geometry`), or an
    empty dict where the report has none or one of another shape."""
    forward = cal.reports.get("forward")
    geometry = forward.get("geometry") if isinstance(forward, dict) else None
    return geometry if isinstance(geometry, dict) else {}


def mount_left(cal) -> float | None:
    """The size (rad) of the mount tilt the free reading of ``cal``'s level sweep saw, where ``calibrate`` adopted the
    other reading, each zone's own time scale with the mount held level (``reports.forward.geometry.adopted``
    ``nominal_time_scales``; ``free.mount_tilt_deg``); else None (a report of another shape, too)."""
    geometry = _forward_geometry(cal)
    if geometry.get("adopted") != "nominal_time_scales":
        return None
    free = geometry.get("free")
    deg = free.get("mount_tilt_deg") if isinstance(free, dict) else None
    if not (isinstance(deg, list) and len(deg) == 2 and all(_magnitude(v) is not None for v in deg)):
        return None
    size = math.radians(math.hypot(*deg))
    return size if math.isfinite(size) else None


#: The tilted planes on which :func:`reading_disagreement` compares a level sweep's two readings: how many, their
#: heights (m, the axis crossing) and tilts (rad), and the seed that draws them. Rendered without noise, each reading
#: with its own pulse scale and albedo, the calibration frames' mean reference histogram as the pulse.
DISAGREEMENT_FRAMES = 48
DISAGREEMENT_HEIGHTS = (0.05, 0.30)
DISAGREEMENT_TILTS = (math.radians(5.0), math.radians(30.0))
DISAGREEMENT_SEED = 5


def reading_disagreement(frames: Sequence[Frame], forward, other, peak_params, correction=None,
                         options=None) -> dict:
    """How differently diff reads tilted planes under the two readings of a level sweep that the sweep did not tell
    apart (:data:`~place_safe.calibration.second_fit.TOLD_APART_GAIN`): the kept forward model ``forward`` and the
    ``other`` (:class:`~place_safe.recovery.forward.ForwardParams`) each render the same :data:`DISAGREEMENT_FRAMES`
    tilted planes, and diff with the kept model (``peak_params``, ``correction``, ``options``: the calibration's) reads
    both. Returns ``slope_scale`` (least squares ``k`` in ``delta_t = k t``: ``delta_t`` the difference of the two
    readings' planes in ``(n_x, n_y)``, ``t`` the true ``(n_x, n_y)``; dimensionless) and ``offset_bias`` (``c`` in
    ``delta_d = c z0 tan(tilt)``), with the frames compared. Where the unit is the other reading, diff's plane errs by
    about these; the stated tilt term takes them (:func:`diff_tilt_term`). ``frames``: the calibration's (their mean
    reference histogram is the pulse)."""
    from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
    from place_safe.recovery.differentiable import DifferentiableEstimator

    refs = [f.reference for f in frames if f.reference is not None][:20]
    reference = np.mean(refs, axis=0) if refs else None
    spec = SyntheticSpec(z_range=DISAGREEMENT_HEIGHTS, theta_range=DISAGREEMENT_TILTS, albedo_range=(1.0, 1.0),
                         specular_weight_range=(0.0, 0.0), noise=False)
    est = DifferentiableEstimator(forward, peak_params, correction=correction, options=options)
    kept = make_frames(DISAGREEMENT_FRAMES, params=forward, spec=spec, seed=DISAGREEMENT_SEED, reference=reference)
    alt = make_frames(DISAGREEMENT_FRAMES, params=other, spec=spec, seed=DISAGREEMENT_SEED, reference=reference)
    rows = []
    for a, b, f in zip(est.estimate_many(kept), est.estimate_many(alt), kept):
        if a.ok and b.ok:
            t, n = tilt_offset(f.truth), f.truth.normal
            rows.append((*(tilt_offset(b.plane) - tilt_offset(a.plane)), t[0], t[1],
                         f.truth.z0 * math.sqrt(max(1.0 - n[2] * n[2], 0.0)) / n[2]))
    if len(rows) < DISAGREEMENT_FRAMES // 2:
        return {"frames": len(rows), "why": "diff read too few of the rendered planes to compare the readings"}
    a = np.array(rows)
    t, dt = a[:, 3:5], a[:, 0:2]
    k, c = slope_scale_offset_bias(t, dt, a[:, 2], a[:, 5])
    return {"frames": len(rows), "slope_scale": k, "offset_bias": c,
            "angle_deg": float(np.degrees(np.mean(np.hypot(dt[:, 0], dt[:, 1]))))}


def slope_scale_offset_bias(t: np.ndarray, dt: np.ndarray, dd: np.ndarray,
                            lever: np.ndarray) -> tuple[float, float]:
    """The least-squares ``k`` in ``dt = k t`` (``t`` (n, 2) true ``(n_x, n_y)``, ``dt`` (n, 2) a difference in them:
    slopes read ``1 + k`` times as steep) and ``c`` in ``dd = c lever`` (``dd`` (n,) a difference in ``d``, m;
    ``lever`` (n,) ``z0 tan(tilt)``, m)."""
    return float(np.sum(dt * t) / np.sum(t * t)), float(np.sum(dd * lever) / np.sum(lever ** 2))


def _usable_tilted(e: PlaneEstimate, t) -> bool:
    """Whether a tilted frame's estimate can size the term: a plane, a truth, a finite fit covariance."""
    return (e.ok and t is not None and e.covariance is not None
            and bool(np.all(np.isfinite(np.asarray(e.covariance, dtype=float)))))


def size_tilt_term(estimates: Sequence[PlaneEstimate], truths: Sequence, floor: Uncertainty) -> tuple[Uncertainty, dict]:
    """``floor`` (with a stated tilt term, :func:`diff_tilt_term`) with the term's tilt part and offset part each
    times the factor (on the standard deviations ``tilt_rel`` and ``tilt_offset_rel``) that makes the tilted frames'
    mean NEES 1 on those components (the mean over the frames of ``e_k^2 / C_kk``; a moment match, which is the
    maximum likelihood only where the term's share of the variance is alike in every frame), the tilt part first (it
    also moves the offset through the pivot), each factor within :data:`TILT_TERM_SCALES`. A part that is 0 (peak's
    offset part; a term stated without floors) starts from the value for a model error not known
    (:data:`DIFF_TILT_REL`, :data:`DIFF_TILT_OFFSET_REL`), so the frames can size it. ``estimates``: the method's own
    planes of tilted calibration frames with their fit covariances (no floor yet); frames without a plane, a truth or
    a finite covariance are left out, and with none left ``floor`` is returned as it is. The report gives the
    factors and the frames' per-component NEES before and after (in sample)."""
    from scipy.optimize import brentq

    rows = [(tilt_offset(e.plane) - tilt_offset(t), np.asarray(e.covariance, dtype=float), e.plane.normal,
             e.plane.offset) for e, t in zip(estimates, truths) if _usable_tilted(e, t)]
    if not rows:
        return floor, {"frames": 0, "why": "no tilted frame with a plane and a finite covariance"}
    base = floor.replace(tilt_rel=floor.tilt_rel or DIFF_TILT_REL,
                         tilt_offset_rel=floor.tilt_offset_rel or DIFF_TILT_OFFSET_REL)

    def components(unc: Uncertainty) -> tuple[float, float]:
        c = [unc.apply(cov, d, n) for _, cov, n, d in rows]
        tilt = np.mean([(r[0][0] ** 2 / ci[0, 0] + r[0][1] ** 2 / ci[1, 1]) / 2.0 for r, ci in zip(rows, c)])
        return float(tilt), float(np.mean([r[0][2] ** 2 / ci[2, 2] for r, ci in zip(rows, c)]))

    def with_factors(kt: float, ko: float) -> Uncertainty:
        return base.replace(tilt_rel=min(base.tilt_rel * kt, 1.0), tilt_offset_rel=min(base.tilt_offset_rel * ko, 1.0))

    def factor(which: int, kt: float = 1.0) -> float:
        lo, hi = (math.log(v) for v in TILT_TERM_SCALES)

        def excess(lk: float) -> float:
            k = math.exp(lk)
            return components(with_factors(k, 1.0) if which == 0 else with_factors(kt, k))[which] - 1.0

        if not excess(lo) > 0.0:  # (a NaN, from a covariance that is not positive, keeps the least factor)
            return TILT_TERM_SCALES[0]
        if excess(hi) >= 0.0:
            return TILT_TERM_SCALES[1]
        return math.exp(brentq(excess, lo, hi, xtol=1e-4))

    before = components(floor)
    kt = factor(0)
    ko = factor(1, kt)
    sized = with_factors(kt, ko)
    after = components(sized)
    return sized, {"frames": len(rows), "tilt_factor": kt, "offset_factor": ko,
                   "tilt_rel_sized": sized.tilt_rel, "tilt_offset_rel_sized": sized.tilt_offset_rel,
                   "nees_tilt_before": before[0], "nees_offset_before": before[1],
                   "nees_tilt_after": after[0], "nees_offset_after": after[1]}


def _tilt_regime(normals: np.ndarray) -> tuple[np.ndarray, bool]:
    """Of calibration frames with true unit ``normals`` (n, 3): which are tilted :data:`MIN_TILT_SPREAD` or more from
    the least tilted (n,), and whether they are level for the stated tilt term (their tilts spread less than that, or
    fewer than :data:`DIFF_TILTED_SHARE` of them are tilted)."""
    tilts = tilt_angles(np.asarray(normals, dtype=float).reshape(-1, 3))
    tilted = tilts - tilts.min() >= MIN_TILT_SPREAD if tilts.size else np.zeros(0, dtype=bool)
    return tilted, level_frames(tilts) or float(np.mean(tilted)) < DIFF_TILTED_SHARE


#: A mean slope below this (about 0.0001 deg) counts as level: a sweep of a level table centres its tilt term nowhere
#: (:func:`sweep_slopes`; ``Uncertainty.tilt_about`` stays at its default and out of the file).
LEVEL_SLOPE = 1e-6


def sweep_slopes(normals: np.ndarray, tilted: np.ndarray) -> list[float]:
    """``Uncertainty.tilt_about`` of calibration frames with true unit ``normals`` (n, 3): the mean slopes ``(n_x / n_z,
    n_y / n_z)`` of those not ``tilted`` (n,; all of them where every one is), each 0 below :data:`LEVEL_SLOPE` and
    within -1 .. 1. A stated tilt term counts the tilt from there: the sweep read planes at its own tilt as it was
    calibrated on them (the real sweep's table sat 0.3-0.8 deg off the sensor's axis)."""
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    keep = ~np.asarray(tilted, dtype=bool)
    n = n[keep] if keep.any() else n
    if n.size == 0:
        return [0.0, 0.0]
    slopes = np.clip((n[:, :2] / n[:, 2:]).mean(axis=0), -1.0, 1.0)
    return [float(v) if abs(v) >= LEVEL_SLOPE else 0.0 for v in slopes]


def _floor_with_tilt_term(estimates: Sequence[PlaneEstimate], truths: Sequence, tilted: np.ndarray, level: bool,
                          base: Uncertainty) -> tuple[Uncertainty, dict, int]:
    """:func:`fit_floor` of the estimates (fit covariances, no floor yet) with ``base``'s stated tilt term, and with
    :data:`TILT_TERM_MIN_FRAMES` or more usable ``tilted`` ones among ``level`` frames, the floor from the others (from
    all the method reads when fewer than 3 are left) and the term sized on those (:func:`size_tilt_term`; report
    ``tilt_term_sized``). Also the number of usable tilted frames (0 unless ``level``)."""
    few = [i for i, (e, t) in enumerate(zip(estimates, truths)) if tilted[i] and _usable_tilted(e, t)] if level else []
    sizing = len(few) >= TILT_TERM_MIN_FRAMES
    read = [i for i, e in enumerate(estimates) if e.ok and e.covariance is not None]
    rows = [i for i in read if not (sizing and tilted[i])]
    rows = rows if len(rows) >= 3 else read
    unc, report = fit_floor([estimates[i] for i in rows], [truths[i] for i in rows], base)
    if sizing:
        unc, report["tilt_term_sized"] = size_tilt_term([estimates[i] for i in few], [truths[i] for i in few], unc)
    return unc, report, len(few)


#: Folds of the cross-validation that chooses diff's fallback limits (:func:`select_fallback`).
CV_FOLDS = 3

#: Candidate ratios of diff's to peak's tilt variance under which diff keeps its plane.
PREFER_RATIOS = (0.25, 0.5, 1.0, 2.0, 4.0)
#: :func:`select_fallback` takes, among the pairs whose held-out score is within this many standard errors of the best
#: (the "one standard error" rule of cross-validation, paired) and that keep diff on some frame where the best does,
#: the one with the largest chi-square limit, then the one that keeps diff on the most frames. A level sweep reads
#: both methods' planes to a few hundredths of a degree, and a difference in score smaller than its own scatter over
#: the frames says nothing about the tilted planes the sweep does not contain; on a level sweep the calibration
#: frames' chi-square grows as they come closer (brighter), so a limit at its median is a distance cut, not a test of
#: the fit. With the best score alone (before), simulated units whose forward model fits (RMS 0.8-1.1) were given the
#: median chi-square as their limit by a score 1 % better (unit 31: 1.093 against 1.103 for 5.0) and fell back on
#: 59-81 % of their tilted frames, where diff's own plane read 0.07 deg and peak's 1.36 (docs/results.md, "The forward
#: fit's two basins, landed"). The most frames first instead (tried) chose unit B's median chi-square with ratio 1
#: over the largest limit with ratio 0.5 (77 % fallback). The standard error is paired (each pair against the best on
#: the same frames): the two score the same frames, whose errors they share, so their difference scatters far less
#: than either score. With the best score's own standard error instead (tried) the real odd half's calibration kept
#: diff on 96 % of the even half's frames, 0.161 deg against peak's 0.156; paired, on 43 %, 0.132 deg; the units'
#: picks are the same. Two stricter forms were weighed and not taken: within one standard error on every metric
#: (measured: the generator with sensor seed 0, whose level frames diff reads 0.030 mm against peak's 0.026, then kept
#: its median chi-square as the limit, 90 % fallback on its tilted frames, where diff reads 0.11 deg and peak 0.21);
#: and at least half the best's frames on diff, which would exclude that generator's pick as it is (the open limit with
#: ratio 0.25: diff on 4 of its level frames against the best's 69, and on 96 % of its tilted frames, where peak's
#: stated tilt term grows; not measured further).
#: The standard error is the sample one (``ddof = 1``). With the population's, a pair that parts from the best on a
#: single frame always lay outside it (its mean difference ``d / n`` against ``d sqrt(n - 1) / n^1.5``), so one level
#: frame decided: mismatched unit B with a mount tilt of 1.5 deg took the median chi-square as its limit over the open
#: one, which differed from it on one of 138 frames, and fell back on 73 % of its tilted frames, where diff's own plane
#: read 0.07 deg and peak's 1.4 (docs/results.md, "A sensor mounted off its nominal orientation"); the real halves'
#: and the other units' picks are the same either way. With the sample one such a pair sits exactly one standard error
#: off, so :func:`select_fallback` also says it outright: a pair that parts from the best on fewer than two frames is
#: within.
FALLBACK_SCORE_SE = 1.0
#: ... or within this fraction of the best score, whatever its standard error: a difference too small to matter. The
#: scores are mean errors in units of peak's median error on the calibration frames (a few hundredths of a degree on
#: a level sweep), so 2 % of one is a few ten-thousandths of a degree. Measured with the blend
#: (:data:`BLEND`): without it, simulated unit 32 and the generator's sensor seed 2 took their median-like
#: chi-square as the limit by scores 0.3-0.4 % better, paired standard errors smaller still (the closest, brightest
#: level frames blend a trace worse than peak reads them), and fell back to peak on their tilted frames above it:
#: unit 32 read 0.195 deg against 0.098 (docs/results.md, "Diff and peak blended").
FALLBACK_SCORE_REL = 0.02


def _paired_se(d: np.ndarray) -> float:
    """The standard error of the mean of per-frame differences ``d`` between two rules' errors on the same frames
    (sample std, ``ddof = 1``; 0 for fewer than two frames)."""
    return float(np.std(d, ddof=1) / math.sqrt(len(d))) if len(d) > 1 else 0.0


def chi2_candidates(chi2: np.ndarray) -> list[float]:
    """Candidate chi-square limits from the calibration frames' diff chi-squares (``inf``: diff failed): their
    median, 90th percentile, largest, and twice the largest (a frame the model explains twice as badly as any
    calibration frame is not one it was calibrated for). No finite chi-square: ``[inf]`` (nothing to go by)."""
    c = np.asarray(chi2, dtype=float)
    c = c[np.isfinite(c)]
    if c.size == 0:
        return [math.inf]
    return sorted({float(np.median(c)), float(np.percentile(c, 90)), float(c.max()), 2.0 * float(c.max())})


def _keeps_diff(chi2: np.ndarray, consistent: np.ndarray, var_ratio: np.ndarray, chi2_limit: float,
                prefer_ratio: float) -> np.ndarray:
    """Per frame (F,), whether the fallback keeps diff's plane (or, with a blend, its blend with peak's): ``chi2`` at
    most ``chi2_limit``, ``consistent`` with peak, and ``var_ratio`` (diff's tilt variance over peak's; NaN: no
    comparison) at most ``prefer_ratio`` (``inf``: any). The rule :func:`select_fallback` scores and the calibration
    reports."""
    return (np.asarray(chi2, dtype=float) <= chi2_limit) & np.asarray(consistent, dtype=bool) \
        & ~(np.asarray(var_ratio, dtype=float) > prefer_ratio)


def select_fallback(chi2: np.ndarray, consistent: np.ndarray, var_ratio: np.ndarray, diff_errors: np.ndarray,
                    peak_errors: np.ndarray, chi2_limits: Sequence[float],
                    ratios: Sequence[float] = PREFER_RATIOS) -> tuple[float, float, list[dict]]:
    """The (chi2_limit, prefer_ratio) whose returned planes score best on held-out frames.

    Per frame (F,): ``chi2`` diff's chi-square per bin (``inf``: failed), ``consistent`` whether diff agrees
    with peak, ``var_ratio`` diff's tilt variance over peak's (NaN: no comparison, diff kept), all as seen on
    the frame held out; ``diff_errors``, ``peak_errors`` (F, M): errors on M metrics in comparable units.
    A frame returns diff's plane when ``chi2 <= chi2_limit``, it is consistent and ``var_ratio <=
    prefer_ratio``; the score is the worse metric's mean error of the planes returned. Among the pairs scoring within
    one standard error of the best (:data:`FALLBACK_SCORE_SE`; the standard error of the mean difference, frame by
    frame, between the pair's returned errors and the best's, on the metric that gives the pair its score), or within
    :data:`FALLBACK_SCORE_REL` of its score, the one
    with the largest limit wins (of those that keep diff on some frame, where the best does); then the one that keeps
    diff on the most frames, then the ratio nearest 1.
    Returns the pair and every candidate's score (``within_se``: whether it was within).
    """
    chi2 = np.asarray(chi2, dtype=float)
    vr = np.asarray(var_ratio, dtype=float)
    n = len(chi2)
    table, returned = [], []
    for lim in chi2_limits:
        for r in ratios:
            use = _keeps_diff(chi2, consistent, vr, lim, r)
            sel = np.where(use[:, None], diff_errors, peak_errors)
            score = float(np.max(np.mean(sel, axis=0))) if n else 0.0
            table.append({"chi2_limit": float(lim), "prefer_ratio": float(r), "score": score,
                          "frames_using_diff": int(use.sum())})
            returned.append(sel)
    if not all(math.isfinite(t["score"]) for t in table):  # errors that cannot be compared: the stated defaults
        for t in table:
            t["within_se"] = None
        return float(max(chi2_limits)), 1.0, table
    k = min(range(len(table)), key=lambda i: (table[i]["score"], -table[i]["frames_using_diff"]))  # the best
    for t, sel in zip(table, returned):
        # the pair against the best on the same frames: the standard error of the mean of their difference, frame by
        # frame, on the metric that gives this pair its score
        m = int(np.argmax(np.mean(sel, axis=0))) if n else 0
        d = sel[:, m] - returned[k][:, m]
        se = _paired_se(d)
        # a pair that parts from the best on one frame is one standard error off by construction (sample std): one
        # frame cannot tell them apart, whatever FALLBACK_SCORE_SE says
        t["within_se"] = bool(np.count_nonzero(d) < 2 or t["score"] - table[k]["score"] <= max(
            FALLBACK_SCORE_SE * se, FALLBACK_SCORE_REL * table[k]["score"]) + 1e-12 * max(1.0, t["score"]))
    # (never a pair that keeps diff on no frame where the best keeps it on some: a larger limit with a ratio that
    # returns peak's plane everywhere is not the more open pair; fewer frames than the best is allowed: unit 31's best
    # kept 69 frames with the median chi-square as its limit and ratio 4, the open limit with ratio 1 kept 50)
    pick = max((t for t in table if t["within_se"] and (t["frames_using_diff"] > 0 or
                                                        table[k]["frames_using_diff"] == 0)),
               key=lambda t: (t["chi2_limit"], t["frames_using_diff"], -abs(math.log(t["prefer_ratio"]))))
    return pick["chi2_limit"], pick["prefer_ratio"], table


def _blend_holds(blend: np.ndarray, choice: np.ndarray) -> tuple[bool, dict]:
    """Whether the blend's returned errors (F, M; per frame, each metric in units of peak's median error) hold
    against those of the best choice between diff's plane and peak's: it does unless the choice's score (the worse
    metric's mean) is lower by more than both the paired standard error (:data:`FALLBACK_SCORE_SE`) and
    :data:`FALLBACK_SCORE_REL` of the blend's score. Also the two scores and that standard error."""
    sb, sc = np.mean(blend, axis=0), np.mean(choice, axis=0)
    score_b, score_c = float(np.max(sb)), float(np.max(sc))
    m = int(np.argmax(sc))
    se = _paired_se(choice[:, m] - blend[:, m])
    holds = not (score_b - score_c > max(FALLBACK_SCORE_SE * se, FALLBACK_SCORE_REL * score_b))
    return holds, {"blend_score": score_b, "choice_score": score_c, "paired_se": se}


#: Whether calibration makes diff blend its plane with peak's where its gates pass (``Uncertainty.blend``,
#: :mod:`place_safe.recovery.blend`; ``prefer_ratio`` then null and only the chi-square limit chosen) instead of
#: choosing one of the two by ``prefer_ratio``, where the blend holds its own against that choice on the held-out
#: calibration frames (:func:`_blend_holds`; the independent generator's tilted calibration set does not).
#: Measured (docs/results.md, "Diff and peak blended"): on the real sweep held out at 5-40 cm (``calibrate`` on one
#: half, ``evaluate`` on the other) 0.116 / 0.133 deg, 0.087 / 0.068 mm, NEES per dof 1.04 / 0.81, against the
#: choice's 0.179 / 0.142 deg (NEES 2.17 / 1.10) and peak's 0.126 / 0.156 deg, 0.135 / 0.082 mm; four interleaved
#: folds 0.115 deg / 0.083 mm pooled against peak's 0.125 / 0.118; on the tilted frames of 15 simulated units
#: calibrated by a level sweep the weights go to diff (about 0.99) and the angle moves by -0.011 to +0.007 deg.
BLEND = True

#: m: depth at which :func:`near_std_law`'s scale is stated.
NEAR_REFERENCE_DEPTH = 0.05
#: m: :func:`near_std_law` holds its value closer than this beyond the overlap (a return there is too close).
NEAR_LAW_MIN_GAP = 0.002
#: Largest power of :func:`near_std_law` (bounds the fit with few frames).
NEAR_MAX_POWER = 4.0
#: Largest part of the near law's variance :func:`fit_near_law` may call common to all zones: the rest stays
#: independent, so each zone keeps at least half the law's std and the tilt at least half its spread. A level
#: sweep shows the common part through the offset only; tilted near frames (not in a level sweep) may read their
#: tilt worse. Fitted values: 0.57 on the whole real sweep, 0.21 / ~0 on its halves, 0.00-0.06 on simulated units.
NEAR_MAX_SHARED = 0.75
#: Near frames with a plane that the near-range law needs; with fewer, the cross-validated zone errors stand.
NEAR_LAW_MIN_FRAMES = 3
#: Calibration frames closer than the near-range table's end (9 cm) read with a plane, below which the near-range
#: covariance rests on too few of them and ``calibrate`` says so (:data:`NEAR_FEW_NOTE`). Held out on the independent
#: generator's sensor 13 (tilted frames at 5-9 cm): a 20-frame level sweep with 4 such frames stated peak's planes with
#: a NEES per dof of 4.9 (diff's blend 1.8), 40 frames with 9 of them 1.2 (0.8); 150 frames 1.7 (0.5) on sensor 5.
NEAR_LAW_FEW_FRAMES = 6
#: The near-range report's note where fewer than :data:`NEAR_LAW_FEW_FRAMES` near frames were read.
NEAR_FEW_NOTE = ("near range from few frames: peak's covariance closer than 9 cm (and the blend's that leans on it) "
                 "rests on {n} calibration frames read there (fewer than {few}); on so few it states planes more precisely "
                 "than new frames read (a 20-frame level sweep with 4: NEES per dof about 5 at 5-9 cm); capture 8 or "
                 "more level poses closer than 9 cm (e.g. capture --incidences 0 --azimuths 0 --distances "
                 "20:90:8,100:400:20) and calibrate again")
#: Depths at which the law is tabulated (``Uncertainty.near_depths``; linear between them): spaced evenly in
#: the logarithm of the gap to the overlap, so a steep law is followed where it is steep.
NEAR_LAW_DEPTHS = 24


#: The near law's least power closer than the nearest frame it was fitted on (:func:`near_std_law`'s
#: ``nearest``). How fast the peak's error grows as the return runs into the internal return is measured only by
#: frames near the overlap: the real sweep (planes down to 1.5 cm) gives 0.97 (1.07 / 1.56 on its halves), a
#: simulated unit swept from 2 cm 1.07, while a sweep that starts at 5 cm sees 5-9 cm only and fitted 0.29 on a
#: simulated unit, whose law then put 2 cm at twice its 5 cm error where other units read 2.4-6 deg planes there
#: (2.4 deg 3-sigma). Beyond its frames the law is not measured, so it grows at least as the real sensor's did.
NEAR_PRIOR_POWER = 1.0
#: The power of the near law a calibration states where none of its frames lies closer than the near-range table's end
#: (9 cm) to fit one (:func:`near_prior`): closer than its nearest frame the zones' range error grows from what that
#: frame's zones err by (read by a mapping fitted without it) as the gap to the overlap to this power. Read by the far
#: mapping alone, the real sweep's zones err 20 times more at 2.75 cm than at 5-9 cm (8.3 against 0.35-0.67 deg:
#: docs/results.md, "Near range"), over a gap 6 times narrower: a power of 1.7. Without such a law, a simulated unit
#: calibrated at 10-40 cm stated its planes at 2-5 cm with a NEES per dof of 32.
NEAR_UNCALIBRATED_POWER = 2.0
#: The part of :func:`near_prior`'s variance common to the zones (an offset; the most a fitted law may take,
#: :data:`NEAR_MAX_SHARED`): the far mapping read closer than its nearest frame errs most in the offset it extrapolates
#: (the real sweep calibrated from 9.5 cm on, read at 5-9 cm: 1.5 mm, 0.4 deg). With half, NEES per dof 5.2 there; 3.9.
NEAR_UNCALIBRATED_SHARED = NEAR_MAX_SHARED
#: The calibration's nearest frames whose zone errors, each read by a mapping fitted without it, set :func:`near_prior`.
NEAR_PRIOR_FRAMES = 3
#: The note of a calibration that states :func:`near_prior` (``{cm}``: its nearest frame's depth).
NEAR_PRIOR_NOTE = ("near range not calibrated: no calibration frame lies closer than {cm:.1f} cm, so peak's covariance "
                   "closer than that is a prior that grows fast towards the internal return (planes there are "
                   "extrapolated, and state so); capture level poses down to 2 cm (e.g. capture --incidences 0 "
                   "--azimuths 0 --distances 20:90:8,100:400:20) and calibrate again")


def near_std_law(depth, scale: float, power: float, nearest: float | None = None) -> np.ndarray:
    """Zone range error (m) at ``depth`` (m, along the optical axis): ``scale`` (m) at
    :data:`NEAR_REFERENCE_DEPTH`, growing as ``(gap / reference gap)^-power`` where the gap is the depth's distance
    beyond the overlap with the internal return (:data:`~place_safe.recovery.too_close.OVERLAP_RANGE`, at least
    :data:`NEAR_LAW_MIN_GAP`). ``nearest`` (m; None: no limit): the nearest depth the law was fitted on (the least
median zone depth of its frames); closer,
    it continues from its value there with the power at least :data:`NEAR_PRIOR_POWER` (an extrapolation the
    fitted frames cannot bound)."""
    ref = NEAR_REFERENCE_DEPTH - OVERLAP_RANGE
    gap = np.maximum(np.asarray(depth, dtype=float) - OVERLAP_RANGE, NEAR_LAW_MIN_GAP)
    std = scale * (gap / ref) ** (-power)
    if nearest is None or power >= NEAR_PRIOR_POWER:
        return std
    g0 = max(float(nearest) - OVERLAP_RANGE, NEAR_LAW_MIN_GAP)
    beyond = scale * (g0 / ref) ** (-power) * (np.minimum(gap, g0) / g0) ** (-NEAR_PRIOR_POWER)
    return np.where(gap < g0, beyond, std)


def near_law_depths(end: float, knots: Sequence[float] = ()) -> np.ndarray:
    """:data:`NEAR_LAW_DEPTHS` depths (m) from :data:`NEAR_LAW_MIN_GAP` beyond the overlap to ``end`` (m), evenly
    spaced in the logarithm of the gap, with a near-range table's ``knots`` (m) among them (where
    :func:`interpolation_measure` is 0) and, in each gap between two of them, its midpoint (where the measure is
    largest) and its quarter points: the tabulated law is read linearly between depths, and without these a gap
    whose midpoint fell between two depths of the logarithmic grid was stated up to a third narrower there than the
    law says (4 mm gaps, a factor that grows mid-gap). A grid depth within 10 um of one of these gives way to it."""
    gaps = np.geomspace(NEAR_LAW_MIN_GAP, max(end - OVERLAP_RANGE, 2 * NEAR_LAW_MIN_GAP), NEAR_LAW_DEPTHS)
    k = np.array(sorted(v for v in knots if OVERLAP_RANGE < v <= end), dtype=float)
    fixed = np.concatenate([k, *(k[:-1] + f * np.diff(k) for f in (0.25, 0.5, 0.75))]) if len(k) > 1 else k
    fixed = fixed[(fixed > OVERLAP_RANGE) & (fixed < end - 1e-5)]
    grid = OVERLAP_RANGE + gaps[:-1]
    if fixed.size:
        grid = grid[np.min(np.abs(grid[:, None] - fixed[None, :]), axis=1) > 1e-5]
    d = np.unique(np.concatenate([grid, fixed]))
    d = d[d < end - 1e-5]
    return np.concatenate([d, [max(end, OVERLAP_RANGE + 2 * NEAR_LAW_MIN_GAP)]])


def near_law_parameters(x: Sequence[float]) -> tuple[float, float, float]:
    """The near law's (scale (m), power, part of the variance shared by the zones) from :func:`fit_near_law`'s free
    parameters (log scale, then logits). Finite for any finite ``x``: the optimiser's simplex may step far out (a
    math.exp logistic overflowed there and stopped ``calibrate`` on a simulated unit)."""
    from scipy.special import expit

    return (math.exp(min(float(x[0]), 0.0)), NEAR_MAX_POWER * float(expit(x[1])),
            NEAR_MAX_SHARED * float(expit(x[2])))


def near_law_uncertainty(unc: Uncertainty, depths: np.ndarray, scale: float, power: float, shared: float,
                         factor=1.0, nearest: float | None = None) -> Uncertainty:
    """``unc`` with the near law tabulated at ``depths`` (m): :func:`near_std_law` (``nearest``: see there) times
    ``sqrt(factor)`` (one value or one per depth), clipped to (1e-7 m, :data:`NEAR_MAX_STD`), its variance split
    into the part ``shared`` common to the zones (``near_common_std``) and the rest (``near_range_std``)."""
    std = np.clip(near_std_law(depths, scale, power, nearest) * np.sqrt(factor), 1e-7, NEAR_MAX_STD)
    return unc.replace(near_depths=[float(v) for v in depths],
                       near_range_std=[float(v) for v in np.maximum(std * math.sqrt(1.0 - shared), 1e-7)],
                       near_common_std=[float(v) for v in std * math.sqrt(shared)])


def interpolation_measure(depth, knots: Sequence[float]) -> np.ndarray:
    """How far ``depth`` (m, any shape) lies from a near-range table's ``knots`` (m), as the error of a smooth
    curve interpolated between them grows: ``delta (H - delta)`` (m^2) in a gap of ``H`` at ``delta`` from its
    lower knot, 0 at a knot; before the first knot (where the table holds its first value)
    ``delta (H + delta)`` with ``H`` the first gap; 0 from the last knot on (no table there)."""
    k = np.asarray(knots, dtype=float)
    x = np.asarray(depth, dtype=float)
    j = np.clip(np.searchsorted(k, x, side="right") - 1, 0, len(k) - 2)
    gap = k[j + 1] - k[j]
    delta = x - k[j]
    with np.errstate(invalid="ignore"):
        m = np.where(x < k[0], (k[0] - x) * (k[1] - k[0] + k[0] - x), delta * (gap - delta))
        return np.where(x >= k[-1], 0.0, np.maximum(m, 0.0))


def new_frame_measure(knots: Sequence[float]) -> float:
    """The :func:`interpolation_measure` (m^2) of a new frame mid-way between two of a near-range table's ``knots``
    (m): ``(H / 2)^2`` for the median gap ``H`` (0 with fewer than two knots)."""
    k = np.sort(np.asarray(knots, dtype=float))
    return float(np.median(np.diff(k)) / 2.0) ** 2 if k.size > 1 else 0.0


#: A held-out near frame counts as read "at a new frame's gap" (:func:`fit_near_law`'s report) when its
#: interpolation measure is at most this many times :func:`new_frame_measure` of the calibration's own table
#: (left out alone from a plain sweep, a frame sits mid-way in a gap twice as wide: 4 times the measure).
NEW_FRAME_GAP_FACTOR = 1.5
#: Below this part of the held-out rows at a new frame's gap the report notes that the law's error there is extrapolated
#: from wider gaps (:data:`NARROW_GAP_NOTE`; a plain sweep
#: has one or two such rows at the table's end: simulated units, 1 of 38; with a second near pass 27 of 76)
NEW_FRAME_GAP_SHARE = 0.1


def knot_factor(measure, m_ref: float, share: float):
    """The factor on the near law's variance (:func:`fit_near_law`) for a depth whose
    :func:`interpolation_measure` among a table's knots is ``measure`` (m^2, any shape; None: read without a table,
    factor 1): ``share + (1 - share) min(measure / m_ref, 4)^2``."""
    if measure is None:
        return 1.0
    return share + (1.0 - share) * np.minimum(np.asarray(measure, dtype=float) / m_ref, 4.0) ** 2


def near_law_table(unc: Uncertainty, end: float, knots: Sequence[float], scale: float, power: float,
                   shared: float, share: float, m_ref: float, nearest: float | None = None) -> Uncertainty:
    """``unc`` with the near law tabulated up to ``end`` (m) at :func:`near_law_depths` (a table's ``knots``, their
    gaps' midpoints and quarter points among them), each depth's variance times :func:`knot_factor` among the
    ``knots`` (none: factor 1); ``nearest``: see :func:`near_std_law`."""
    depths = near_law_depths(end, knots)
    factor = knot_factor(interpolation_measure(depths, knots), m_ref, share) if len(knots) > 1 else 1.0
    return near_law_uncertainty(unc, depths, scale, power, shared, factor, nearest)


#: :func:`fit_near_law`'s report note when no held-out near frame lay in a gap as narrow as a new frame's
NARROW_GAP_NOTE = ("near range from wider gaps: the held-out near frames lay in gaps wider than a new frame's, so the "
                   "law's error at a new frame's gap is extrapolated (NEAR_KNOT_SHARE); capture a second level pass "
                   "closer than 9 cm, half a step above the first, for a covariance measured at the table's own "
                   "spacing")

#: The part of the near law's variance that does not shrink as a frame comes closer to a table's knot (the zones'
#: own variation from frame to frame; the rest is the table's interpolation error, which does): :func:`knot_factor`'s
#: ``share``, held, not fitted. Held-out frames of a calibration sweep lie in gaps two and three times the table's
#: spacing, and the share is what carries their error to a new frame's gap, an extrapolation they barely determine:
#: fitted (until 2026-11-28), it came out 0.32-1 on 14 simulated units whose held-out likelihoods at 0.5 and at the
#: fitted value were alike, and their 2-5 cm frames of another sweep read at NEES per dof 0.24-2.41 (9 of 14 in
#: 0.5-2, unit 23 overconfident); held at 0.5, 0.55-1.77 (14 of 14), and on 10 units not used to choose it 0.54-1.70
#: (10 of 10; fitted: 0.26-1.07, 5 of 10); with a second near pass (fitted 0.92-1) 0.66-1.31 on six units
#: (fitted: 0.52-0.82). docs/results.md, "The near law's share held".
NEAR_KNOT_SHARE = 0.5


def fit_near_law(rows: Sequence[tuple], unc: Uncertainty, peak_params, end: float) -> tuple[Uncertainty, dict]:
    """``unc`` with its near-range errors tabulated up to ``end`` (m; :func:`near_law_depths`) from
    :func:`near_std_law` times an interpolation factor, chosen by maximum likelihood of held-out planes' errors
    under the covariance the peak estimator reports with them (:meth:`PeakEstimator.covariance
    <place_safe.recovery.peak.PeakEstimator.covariance>`: they replace the fit's residual). ``rows``: (zone points
    (9, 3), used (9,), plane, error of (n_x, n_y, d) (3,), interpolation measure of the frame's median zone depth
    among the knots of the table that read it (m^2, :func:`interpolation_measure`; None: no table)), each plane
    read by a near-range table fitted without its frame (and, for some rows, without its neighbour too).

    The factor: a frame read by a table is in error by the zones' own variation from frame to frame and by the
    table's interpolation between knots, an error (not a variance) that grows with the measure. The zone variance
    is the law's square times ``share + (1 - share) (m / m_ref)^2``, ``m_ref`` the median measure of the rows
    that lie in a gap (the ratio at most 4), ``share`` the part that does not depend on the knots: :data:`NEAR_KNOT_SHARE` where
    there is a table (held: the rows, in gaps two and three times the table's spacing, barely determine how much
    of their error a new frame's narrower gap keeps), 1 where there is none. (Until round 34 the factor was linear
    in the measure, as if the interpolation's variance grew with it: on the real sweep left out a distance at a
    time that put 2-9 cm NEES/dof at 0.48 / 1.26 against 0.51 / 1.09.)

    The variance is split further: the part ``shared_by_zones`` of it is one range error common to all zones of a
    frame (``Uncertainty.near_common_std``: mostly the offset), the rest independent from zone to zone
    (``near_range_std``: the tilt). On the real sweep the table's errors at 5-9 cm are mostly common (held out,
    offsets up to 3.4 sigma off under independent zones, while the tilts had NEES 0.0-0.5: the zones' errors were
    over-stated to make up for the offset); the fit puts half the variance there. The simulated units have none
    (0.00-0.06).

    Held out from a plain sweep, a frame lies mid-way in a gap twice the table's spacing (4 times a new frame's
    measure), so the law's error at a new frame's gap rests on the held share. A second level pass half a step
    above the first below 9 cm halves the spacing, so a frame left out still has neighbours as near as a new
    frame's and is read across a gap about as wide: the law is then measured where new frames fall. The report's
    ``held_out_at_new_frame_gaps`` counts the rows within :data:`NEW_FRAME_GAP_FACTOR` of :func:`new_frame_measure`;
    with fewer than :data:`NEW_FRAME_GAP_SHARE` of the rows there, ``note`` says so and how to capture for a law
    measured there.

    The report's ``held_out_rows``: each row's median zone depth (mm) and NEES per dof under the law."""
    from scipy.optimize import minimize

    measured = [r[4] for r in rows if r[4] is not None]
    knots = list(peak_params.near_depths) if peak_params.near_depths and measured else []
    # the rows' median measure in a gap (rows on a knot, or past the table's end, have none: were most of them there,
    # the median would be 0 and every factor 0 / 0); a new frame's mid-gap measure when no row lies in a gap
    m_new = new_frame_measure(knots) if knots else None
    gaps = [m for m in measured if m > 0.0]
    m_ref = float(np.median(gaps)) if gaps else (m_new or 1.0)
    share = NEAR_KNOT_SHARE if knots else 1.0

    def unc_for(depths: np.ndarray, theta: tuple, factor) -> Uncertainty:
        return near_law_uncertainty(unc, depths, theta[0], theta[1], theta[2], factor)

    plain = near_law_depths(end)

    # The covariance the peak estimator reports for each held-out row under a law (its own factor: its table's
    # knots), PeakEstimator.covariance for all rows at once (a row through fewer zones than the grid is read as through
    # all nine here: without the zones' scatter it gets at run time, which only widens; the real sweep's
    # near rows have every zone; a tilted row is read without the tilt scatter it gets at run time too, so a sweep's
    # tilted near rows widen the law: with that scatter subtracted here, the packaged nominal sensor's rows, tilted
    # 6-12 deg and scattering less than ZONE_TILT_SCATTER, left a law of zero for its level frames): the fits' own
    # parts are the same for every law, and
    # Uncertainty.apply is affine in the fit's covariance (unc.scale times it, plus what it adds to none); the near
    # law's end (the depths ``plain``) is the same for every law, so is which rows it reads.
    first = unc_for(plain, (1e-4, 0.0, 0.0), 1.0)
    near_rows = np.array([near_applies(first, r[0], r[1]) for r in rows])
    geometry = PlaneFitGeometry(*(np.stack(parts) for parts in zip(*(plane_fit_geometry(r[0], r[1], r[2])
                                                                        for r in rows))))
    depths = np.array([r[0][:, 2] for r in rows])
    added = np.array([unc.apply(np.zeros((3, 3)), r[2].offset, r[2].normal) for r in rows])
    own = geometry.sigma2[:, None, None] * geometry.inverse  # the fit's own covariance: rows the law does not read
    groups: dict = {}  # the rows it reads, by measure (read without a table, or at the same measure: one law)
    for i, r in enumerate(rows):
        if near_rows[i]:
            groups.setdefault(r[4], []).append(i)
    groups = {m: (np.array(i), PlaneFitGeometry(*(part[i] for part in geometry))) for m, i in groups.items()}

    def row_covariances(theta: tuple) -> np.ndarray:
        """Each row's reported covariance (rows, 3, 3) under the law ``theta``."""
        fit = own.copy()
        for m, (i, fits) in groups.items():
            fit[i] = near_covariances(unc_for(plain, theta, knot_factor(m, m_ref, share)), fits, depths[i])
        return unc.scale * fit + added

    errors = np.array([r[3] for r in rows])

    def nll(x: np.ndarray) -> float:
        each = _nll_rows(errors, row_covariances(near_law_parameters(x)))
        return math.inf if each is None else sum(each.tolist()) / len(rows)  # (summed in order, as row by row)

    starts = [(math.log(2e-4), 0.0, 0.0), (math.log(5e-4), -2.0, -2.0), (math.log(1e-4), 2.0, 2.0)]
    best = None
    for start in starts:
        x0 = np.array(start)
        simplex = np.vstack([x0, x0 + np.eye(len(x0))])  # unit steps: scipy's default moves a 0 start by 2.5e-4
        res = minimize(nll, x0, method="Nelder-Mead",
                       options={"xatol": 1e-3, "fatol": 1e-6, "maxiter": 1500, "initial_simplex": simplex})
        if best is None or res.fun < best.fun:
            best = res
    theta = near_law_parameters(best.x)
    scale, power, shared = theta

    # the nearest depth the law is fitted on (the rows' median zone depths): closer, it is an extrapolation
    nearest = min(float(np.median(r[0][r[1], 2])) for r in rows)
    narrow = sum(m <= NEW_FRAME_GAP_FACTOR * m_new for m in measured) if knots else 0
    covs = row_covariances(theta)
    held = errors * errors / np.diagonal(covs, axis1=1, axis2=2)  # per component
    per_row = [float(e @ np.linalg.solve(c, e)) / 3.0 for e, c in zip(errors, covs)]
    return near_law_table(unc, end, knots, scale, power, shared, share, m_ref, nearest), {
        "frames": len(rows), "std_at_reference_mm": scale * 1e3, "reference_depth_mm": NEAR_REFERENCE_DEPTH * 1e3,
        "power": power, "shared_by_zones": shared, "nearest_fitted_mm": nearest * 1e3,
        "power_closer": max(power, NEAR_PRIOR_POWER),
        "table_knots": len(knots), "reference_measure_mm2": m_ref * 1e6 if knots else None,
        "share_independent_of_knots": share,
        "share_how": "held (NEAR_KNOT_SHARE)" if knots else "1: no table, nothing to interpolate",
        "new_frame_measure_mm2": None if m_new is None else m_new * 1e6, "held_out_at_new_frame_gaps": narrow,
        **({"note": NARROW_GAP_NOTE} if knots and narrow < NEW_FRAME_GAP_SHARE * len(measured) else {}),
        "nees_per_dof_held_out": float(np.mean(per_row)),
        "nees_tilt_per_dof_held_out": float(held[:, :2].mean()), "nees_offset_held_out": float(held[:, 2].mean()),
        "held_out_rows": [[round(float(np.median(r[0][r[1], 2])) * 1e3, 2), round(float(v), 3)]
                          for r, v in zip(rows, per_row)]}


def peak_tilt_term(mount_tilt=None) -> Uncertainty:
    """The stated tilt term of peak's covariance for level calibration frames: :data:`PEAK_TILT_REL` on each tilt
    component, and with the unit's forward model's ``mount_tilt`` (rad, ``(rx, ry)``; None or not finite: none) an
    offset part :data:`PEAK_MOUNT_OFFSET_REL` times its size: where the forward model reads the level sweep as a sensor
    mounted off its nominal orientation, peak's zone gains read the same sweep as the zones' own time scales, and the
    two readings part on a tilted plane."""
    size = 0.0
    if mount_tilt is not None:
        try:
            size = float(np.hypot(*np.asarray(mount_tilt, dtype=float).reshape(2)))
        except (TypeError, ValueError, OverflowError):
            size = 0.0
        size = size if math.isfinite(size) else 0.0
    return Uncertainty(tilt_rel=PEAK_TILT_REL, tilt_offset_rel=PEAK_MOUNT_OFFSET_REL * size)


def near_prior(frames: Sequence[Frame], peak_params, unc: Uncertainty,
               min_range: float = MIN_CALIBRATION_RANGE) -> tuple[Uncertainty, dict]:
    """``unc`` with a near law stated, not fitted, for a calibration with no frame closer than the near-range table's
    end to fit one: closer than its nearest frame (``min_range`` or farther, with ground truth), each zone's range
    error grows from ``s0`` there as the gap to the overlap to :data:`NEAR_UNCALIBRATED_POWER`
    (:func:`near_std_law`), :data:`NEAR_UNCALIBRATED_SHARED` of its variance common to the zones; ``s0`` is the RMS
    zone range error of the :data:`NEAR_PRIOR_FRAMES` nearest frames, each read by the far mapping fitted without it
    (:func:`~place_safe.calibration.points.refit_mapping`). ``unc`` unchanged where there are too few frames; the
    report gives the depth, ``s0`` and the note (:data:`NEAR_PRIOR_NOTE`)."""
    use = sorted((f for f in frames if f.truth is not None and f.truth.z0 >= min_range), key=lambda f: f.truth.z0)
    if len(use) <= NEAR_PRIOR_FRAMES:
        return unc, {"why": f"{len(use)} calibration frames: too few to read {NEAR_PRIOR_FRAMES} of them held out"}
    errs = []
    for f in use[:NEAR_PRIOR_FRAMES]:
        mapping = refit_mapping([g for g in use if g is not f], peak_params, min_range)
        h = np.asarray(f.hists, dtype=float)[None]
        pos, valid, _ = find_peaks(h, mapping.pileup, mapping.subbin, mapping.subbin_half_width)
        with np.errstate(invalid="ignore", divide="ignore"):
            err = mapping.ranges(pos[0]) - true_ranges(f.truth.normal[None], np.array([f.truth.offset]),
                                                       mapping.directions())[0]
        errs.extend(err[valid[0] & np.isfinite(err)])
    if not errs:
        return unc, {"why": "the nearest calibration frames have no zone reading"}
    s0 = max(float(np.sqrt(np.mean(np.square(errs)))), 1e-6)
    nearest = float(use[0].truth.z0)
    ref = NEAR_REFERENCE_DEPTH - OVERLAP_RANGE
    g0 = max(nearest - OVERLAP_RANGE, NEAR_LAW_MIN_GAP)
    scale = s0 * (g0 / ref) ** NEAR_UNCALIBRATED_POWER  # near_std_law(nearest) = s0
    unc = near_law_uncertainty(unc, near_law_depths(nearest), scale, NEAR_UNCALIBRATED_POWER,
                               NEAR_UNCALIBRATED_SHARED)
    return unc, {"nearest_mm": nearest * 1e3, "zone_error_there_mm": s0 * 1e3, "power": NEAR_UNCALIBRATED_POWER,
                 "shared_by_zones": NEAR_UNCALIBRATED_SHARED, "note": NEAR_PRIOR_NOTE.format(cm=nearest * 100)}


#: The fewest full-grid fits whose residuals :func:`pooled_zone_std` pools (fewer: no ``zone_std`` stated).
ZONE_STD_MIN_FRAMES = 3
#: rad: :func:`pooled_zone_std` pools the frames whose planes are tilted less than this from the optical axis where
#: there are :data:`ZONE_STD_MIN_FRAMES` of them (a tilted plane's residual holds the zones' tilt scatter, which the
#: stated ``ZONE_TILT_SCATTER`` describes only on average: on 60 of the independent generator's planes tilted 15-30
#: deg the pooled scatter read 0.22 mm with it removed, 60 level planes of the same sensor 0.041 mm).
ZONE_STD_MAX_TILT = math.radians(5.0)


def pooled_zone_std(frames: Sequence[Frame], peak_params) -> tuple[float, dict]:
    """The zones' own scatter about the plane (m; ``Uncertainty.zone_std``) and its report: the root of the mean
    residual variance (sum of squares over 9 - 3) of peak's fits through all nine zones of ``frames``, each plane its
    own least-squares one (no ground truth needed), over the frames tilted less than :data:`ZONE_STD_MAX_TILT` where
    there are enough, less the little a tilted plane adds there (:func:`~place_safe.recovery.peak.zone_tilt_variance`,
    which a partial fit states besides); in a sweep with too few such frames, the intercept of a line through every
    frame's residual variance against ``(z0 tan(tilt))^2`` (both terms >= 0: the generator's planes tilted 15-30 deg
    read 0.055 mm, its level sweep 0.044; a nominal unit's sweep at 0 / 6 / 12 deg 0.028 mm, where removing the stated
    tilt part on average left nothing). 0 with fewer than :data:`ZONE_STD_MIN_FRAMES` fits. On the real halves
    0.103 / 0.108 mm, about flat over 5-40 cm; read back on frames of the other half 0.11-0.12 mm."""
    from scipy.optimize import nnls

    est = PeakEstimator(peak_params)
    s2, x2, level = [], [], []
    for f in frames:
        try:
            points, valid = est.zone_points(f)
            if not valid.all():
                continue
            plane, _ = plane_through(points, valid)
        except (NoPlaneError, FrameError):
            continue
        v, t = float(plane_fit_geometry(points, valid, plane).sigma2), zone_tilt_variance(plane)
        if math.isfinite(v) and math.isfinite(t):
            s2.append(v)
            x2.append(t / ZONE_TILT_SCATTER ** 2)
            level.append(float(plane.normal[2]) >= math.cos(ZONE_STD_MAX_TILT))
    if len(s2) < ZONE_STD_MIN_FRAMES:
        return 0.0, {"frames": len(s2), "why": f"fewer than {ZONE_STD_MIN_FRAMES} fits through all nine zones"}
    s2, x2, level = np.array(s2), np.array(x2), np.array(level)
    if level.sum() >= ZONE_STD_MIN_FRAMES:
        var, used, how = float(np.mean(s2[level] - ZONE_TILT_SCATTER ** 2 * x2[level])), int(level.sum()), \
            "frames tilted less than ZONE_STD_MAX_TILT"
    else:  # a tilted sweep: the scatter at no tilt and the sweep's own growth with z0 tan(tilt), both >= 0
        (var, _), _ = nnls(np.column_stack([np.ones_like(x2), x2]), s2)
        used, how = len(s2), ("every frame (too few near level): the residual variance at no tilt of a line in "
                              "(z0 tan)^2")
    std = min(math.sqrt(max(var, 0.0)), NEAR_MAX_STD)
    return std, {"frames": used, "zone_std_mm": std * 1e3, "from": how}


def fit_peak_uncertainty(frames: Sequence[Frame], peak_params, min_range: float | None = None,
                         mount_tilt=None) -> tuple[Uncertainty, dict]:
    """The peak method's floor from frames with ground truth at ``min_range`` (m, axis distance) or farther:
    the range its mapping was calibrated on (default
    :data:`~place_safe.calibration.points.MIN_CALIBRATION_RANGE`). ``mount_tilt``: the unit's forward model's (rad,
    ``(rx, ry)``; None: no forward model), which sizes the offset part of the stated tilt term (:func:`peak_tilt_term`).

    Why not closer frames: the mapping is not fitted there and its errors are of another kind (the real
    sweep at 0.5-2 cm: 10-60 deg). With them in, the floor's two terms and the scale could describe neither
    regime: held out at 5-40 cm the NEES per dof was 0.3-0.4 (covariances 3x too large), at 1-5 cm 5-8.
    Those frames get the zones' near-range errors instead (module doc); where there are some, the floor and
    scale are fitted on the frames beyond their last depth.

    The near-range errors: each near frame (closer than the table's end) is read by the near-range table
    fitted without it (:func:`~place_safe.calibration.near_range.held_out_fits`: knots, penalty and whether to
    keep a table chosen again, so the frame lies between other frames' knots as a new frame does), on the far-range
    mapping fitted again without it (:func:`~place_safe.calibration.points.refit_mapping`); the zone
    error law :func:`near_std_law` (a scale at 5 cm growing as a power of the gap to the internal return) is
    fitted by maximum likelihood of those planes' errors under the covariance the estimator reports with it
    (:func:`fit_near_law`). With fewer than :data:`NEAR_LAW_MIN_FRAMES` such planes, the zones' cross-validated
    range errors (:func:`~place_safe.calibration.near_range.near_range_std`) stand. The report's ``near_range``
    holds the errors per depth, ``law`` (scale, power, frames, the floor at the knots and
    ``nees_per_dof_held_out``, the held-out planes under the law alone), ``too_close`` (how many near frames the
    peak method reads as too close, :mod:`place_safe.recovery.too_close`: no plane, no part in the means) and
    ``nees_per_dof_closer`` (the calibration's own near frames read by its table: in sample). ``zone_std``, the zones'
    scatter that a fit through fewer zones states at least, is pooled from the same far frames
    (:func:`pooled_zone_std`; report ``zone_scatter``).

    An earlier factor on the cross-validated errors, chosen so that the held-out mean is 1 with tables that kept
    the frame's own knot, was biased: such a frame sits on a knot that lost its own data and reads worse than a
    new frame (on the real halves it took 5-9 cm below 0.5)."""
    lo = MIN_CALIBRATION_RANGE if min_range is None else float(min_range)
    depths, stds, near = near_range_std(frames, peak_params)
    far = max(lo, depths[-1]) if depths else lo  # the floor and scale from the frames the near term leaves alone
    use = [f for f in frames if f.truth is not None and f.truth.z0 >= far]
    # the stated tilt term where the frames cannot show peak's tilt error (as diff's: fit_diff_uncertainty); the
    # tilted frames counted here lie beyond the near table's end (about 9 cm), diff's from NEAR_FALLBACK_RANGE (5 cm)
    normals = np.array([f.truth.normal for f in use])
    tilted, level = _tilt_regime(normals)
    stated = peak_tilt_term(mount_tilt) if level else Uncertainty(tilt_rel=0.0)
    zone_std, zone_report = pooled_zone_std(use, peak_params)
    base = Uncertainty(near_depths=depths, near_range_std=stds, tilt_rel=stated.tilt_rel,
                       tilt_offset_rel=stated.tilt_offset_rel,
                       tilt_about=sweep_slopes(normals, tilted) if level else [0.0, 0.0], zone_std=zone_std)
    own = Uncertainty(zone_std=zone_std)  # (the fits' own part: a frame with fewer zones states at least the scatter)
    ests = [PeakEstimator(peak_params, own).estimate(f) for f in use]
    unc, report, n_few = _floor_with_tilt_term(ests, [f.truth for f in use], tilted, level, base)
    report["zone_scatter"] = zone_report
    sizing = n_few >= TILT_TERM_MIN_FRAMES
    report["tilt_term"] = (("stated (PEAK_TILT_REL): the frames' tilts spread less than MIN_TILT_SPREAD, or too few "
                            "frames are tilted (DIFF_TILTED_SHARE)" + (", sized by the tilted frames (tilt_term_sized; "
                                                                        "the floor from the others)" if sizing else ""))
                           if level else
                           "none: the frames' tilts spread MIN_TILT_SPREAD or more, the floor holds the tilt error")
    if level:
        mount_deg = math.degrees(stated.tilt_offset_rel / PEAK_MOUNT_OFFSET_REL)
        report["tilt_offset_rel"] = unc.tilt_offset_rel
        report["tilt_offset_mount_deg"] = mount_deg
        report["tilt_offset_from"] = (f"PEAK_MOUNT_OFFSET_REL x the forward model's mount tilt ({mount_deg:.2f} deg)"
                                      if mount_deg > 0 else "no forward model, or no mount tilt") + (
            "; sized by the tilted frames (tilt_term_sized)" if sizing else "")
    report["min_range_m"] = far
    closer = [f for f in frames if f.truth is not None and f.truth.z0 < far]
    report["frames_closer"] = len(closer)
    report["near_range"] = near
    if closer and depths:
        read = []  # (id of the frame, its row)
        for width in (1, 2):  # left out alone, and with a neighbour (wider gaps: more rows for the law)
            held = held_out_fits(frames, peak_params, width, mapping=lambda rest, base: refit_mapping(rest, base, lo))
            read += [(id(f), r) for f in closer if (r := _near_row(f, held.get(id(f)), depths[-1])) is not None]
        # read as new frames are: by a table where the calibration keeps one, by the mapping alone where not
        read = [(k, r) for k, r in read if (r[4] is not None) == bool(peak_params.near_depths)]
        rows = [r for _, r in read]
        report["near_range"]["frames_read"] = n_read = len({k for k, _ in read})
        if n_read < NEAR_LAW_FEW_FRAMES:
            report["near_range"]["note"] = NEAR_FEW_NOTE.format(n=n_read, few=NEAR_LAW_FEW_FRAMES)
        if len(rows) >= NEAR_LAW_MIN_FRAMES:
            unc, report["near_range"]["law"] = fit_near_law(rows, unc, peak_params, depths[-1])
            report["near_range"]["std_mm"] = [v * 1e3 for v in unc.near_range_std]
        ests = [PeakEstimator(peak_params, unc).estimate(f) for f in closer]
        report["near_range"]["nees_per_dof_closer"] = _mean_nees(ests, [f.truth for f in closer])
        report["near_range"]["too_close"] = sum(1 for e in ests if (e.reason or "").startswith(TOO_CLOSE_REASON))
    if not unc.near_depths:  # no near frame to fit a law on: closer than the nearest frame, a stated one
        unc, report["near_range"]["prior"] = near_prior(frames, peak_params, unc, lo)
    common, zone, report["far_range"] = far_growth(frames, peak_params, lo, unc)  # past the farthest frame: a growth
    return unc.replace(far_common_rel=common, far_zone_rel=zone), report


def _near_row(frame: Frame, params, end: float) -> tuple | None:
    """(zone points, used, plane, error of (n_x, n_y, d), interpolation measure of the median zone depth among
    ``params``'s table knots or None) of ``frame`` read by peak with ``params``; None where there is no plane,
    no such params, or no zone closer than ``end`` (m)."""
    if params is None:
        return None
    try:
        frame.validate()
        points, valid = PeakEstimator(params).zone_points(frame)
    except (FrameError, NoPlaneError):
        return None
    if not points[valid, 2].min() < end:
        return None
    plane, _ = plane_through(points, valid)
    if plane_overlap_reason(points, valid, plane.offset) is not None:  # as PeakEstimator: no plane in the overlap
        return None
    m = (float(interpolation_measure(np.median(points[valid, 2]), params.near_depths)) if params.near_depths
         else None)
    return points, valid, plane, tilt_offset(plane) - tilt_offset(frame.truth), m


def _mean_nees(estimates: Sequence[PlaneEstimate], truths: Sequence) -> float | None:
    """Mean NEES per dof of the estimates with a plane and covariance (None: none)."""
    v = nees(estimates, truths)
    v = v[np.isfinite(v)]
    return float(np.mean(v)) if v.size else None


#: m: calibration frames farther than this take no part in choosing diff's fallback limits and floor (unless fewer than
#: :data:`FALLBACK_MIN_FRAMES` are left). A level sweep out to 0.6-1 m reads the crosstalk between zones, which a sweep
#: to 0.4 m trades against the fields of view, better on most units (docs/results.md, "A level sweep out to 1 m"), but
#: its dim far frames have a low chi-square, so the limits chosen on all of them became a distance cut: the
#: generator's sensor seeds 1
#: and 8 calibrated on 2-100 cm took the median chi-square (1.1) as their limit and fell back to peak on 100 % of
#: their tilted frames at 5-30 cm, where diff's own plane read 0.31 and 0.13 deg against peak's 0.47 and 0.23; chosen
#: on their frames up to 0.45 m, 5-6 % (0.31 and 0.13 deg as returned). The default sweep (2-40 cm) and the real one
#: (5 mm-39.5 cm) lie within it: their limits are unchanged.
FALLBACK_MAX_RANGE = 0.45
#: ... the fewest frames in range for that (else every frame from NEAR_FALLBACK_RANGE on).
FALLBACK_MIN_FRAMES = 10


def fit_diff_uncertainty(frames: Sequence[Frame], forward, peak_params, correction=None,
                         peak_uncertainty: Uncertainty | None = None, options=None,
                         model_error: float | None = None, crosstalk: float | None = None,
                         other_reading=None, mount_left: float | None = None,
                         readings_tail: str = "") -> tuple[Uncertainty, dict]:
    """The diff method's floor and fallback limits (chi-square, consistency, preference) from frames with ground
    truth, for the solver ``options`` (:class:`~place_safe.recovery.differentiable.SolverOptions`; default: the
    solver's defaults): they depend on the bins the solver fits. The limits are chosen on held-out frames
    (module doc); the report gives the held-out figures (``angular_deg``, ``point_mm``: diff's own plane, peak's
    and the one returned; ``frames_using_diff``) and every candidate's score. ``model_error``: the unit's relative
    model error at the frames' true planes (the forward fit's ``model_error_chi2``; None: not known), which sizes the
    stated tilt term of level frames (:func:`diff_tilt_term`), with ``crosstalk`` (the forward fit's, where a level
    sweep left it undetermined; None: nothing added), ``other_reading`` (:func:`other_reading`: where the sweep did not
    tell its two readings apart, their :func:`reading_disagreement` on ``frames``, unless enough tilted frames size the
    term; None: nothing added; ``readings_tail`` ends the note that says so: :func:`readings_note_tail`) and
    ``mount_left`` (:func:`mount_left`; None: nothing added). Frames closer than
    ``NEAR_FALLBACK_RANGE`` take no
    part, nor do those beyond :data:`FALLBACK_MAX_RANGE` (reported as ``frames_beyond_range``) while at least
    :data:`FALLBACK_MIN_FRAMES` are left. With :data:`BLEND` the section blends (``blend`` true, ``prefer_ratio``
    inf) and the report's ``angular_deg`` / ``point_mm`` give the blend's held-out figures too."""

    from place_safe.recovery.differentiable import DifferentiableEstimator  # (torch: a peak calibration never gets here)

    # closer frames always get peak's plane (NEAR_FALLBACK_RANGE): they take no part in choosing the limits; nor do
    # frames beyond FALLBACK_MAX_RANGE while enough are left (a far sweep's dim frames: see the constant)
    near_on = [f for f in frames if f.truth is not None and f.truth.z0 >= NEAR_FALLBACK_RANGE]
    in_range = [f for f in near_on if f.truth.z0 <= FALLBACK_MAX_RANGE]
    every_frame = len(in_range) < min(FALLBACK_MIN_FRAMES, len(near_on))  # too few in range: the far ones too
    use = near_on if every_frame else in_range
    truths = [f.truth for f in use]
    peak_unc = peak_uncertainty if peak_uncertainty is not None else Uncertainty()
    est = DifferentiableEstimator(forward, peak_params, correction=correction, peak_uncertainty=peak_unc,
                                  options=options)  # no floor, no fallback: diff's own plane and fit covariance
    diff = est.estimate_many(use)
    peak = [est.init.estimate(f) for f in use]
    own = [e.ok and e.method_used == est.name and e.residual is not None for e in diff]

    def errs(e: PlaneEstimate, t) -> tuple[float, float]:
        if not e.ok:
            return math.inf, math.inf
        return (float(angular_errors(e.plane.normal, t.normal)[0]),
                float(point_errors(e.plane.normal, e.plane.offset, t.normal, t.offset)[0]))

    e_diff = np.array([errs(e, t) if ok else (math.inf, math.inf) for e, t, ok in zip(diff, truths, own)]).reshape(-1, 2)
    e_peak = np.array([errs(e, t) for e, t in zip(peak, truths)]).reshape(-1, 2)
    # each error in units of peak's median error, capped at 10, so a few hopeless frames (both methods
    # far off) do not decide; the score is the worse of the two metrics' means
    finite = np.where(np.isfinite(e_peak), e_peak, np.nan)  # peak's median over the frames it read (all NaN: 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a column without a finite error
        unit = np.maximum(np.nan_to_num(np.nanmedian(finite, axis=0), nan=1.0), 1e-12)
    n_diff, n_peak = np.minimum(e_diff / unit, 10.0), np.minimum(e_peak / unit, 10.0)
    chi2 = np.array([e.residual ** 2 if ok else math.inf for e, ok in zip(diff, own)])
    test = Uncertainty(consistency_limit=CONSISTENCY_LIMIT)

    def held_out(floor: Uncertainty, i: int) -> tuple[bool, float, PlaneEstimate | None]:
        """Whether frame i's diff estimate (with ``floor``) agrees with peak's, its tilt variance over peak's, and the
        two blended (:mod:`place_safe.recovery.blend`; None: no blend)."""
        if not own[i] or diff[i].covariance is None:
            return True, math.nan, None
        e = replace(diff[i], covariance=floor.apply(diff[i].covariance, diff[i].plane.offset, diff[i].plane.normal))
        mine, theirs = e.tilt_std(), peak[i].tilt_std()
        ratio = (mine / theirs) ** 2 if mine is not None and theirs else math.nan
        return test.consistent(e, peak[i]), ratio, blended(e, peak[i], BLENDED)

    # the stated tilt term where the frames cannot show diff's tilt error (a level sweep, or one with a few tilted
    # frames: the floor, fitted on all, would follow the level ones); frames whose tilts spread MIN_TILT_SPREAD or
    # more, at least DIFF_TILTED_SHARE of them tilted that far from the least, show it, and the floor and scale
    # fitted on them hold it
    normals = np.array([t.normal for t in truths])
    tilted, level = _tilt_regime(normals)

    def floor_from(rows: np.ndarray) -> Uncertainty:
        # the folds' floors without the stated term: the limits follow what the calibration frames show, not the size of
        # a term for tilted planes they do not contain (sized by the model error, it flipped the real even half's
        # prefer_ratio 2 -> 1 through its frames' 0.3-0.8 deg tilts); the reported covariance has the term
        return fit_floor([diff[i] for i in rows if own[i]], [truths[i] for i in rows if own[i]], Uncertainty())[0]

    n = len(use)
    folds = min(CV_FOLDS, n // 2)
    consistent, ratio = np.ones(n, dtype=bool), np.full(n, math.nan)
    e_blend = e_diff.copy()  # the blended plane's errors (diff's own where there is no blend)
    fold = np.empty(n, dtype=int)
    fold[np.argsort([t.z0 for t in truths], kind="stable")] = np.arange(n) % max(folds, 1)
    for k in range(folds):  # each fold's limits tested with the floor fitted on the other folds
        floor = floor_from(np.flatnonzero(fold != k))
        for i in np.flatnonzero(fold == k):
            consistent[i], ratio[i], mixed = held_out(floor, int(i))
            if mixed is not None:
                e_blend[i] = errs(mixed, truths[i])
    n_blend = np.minimum(e_blend / unit, 10.0)
    candidates = chi2_candidates(chi2)
    blend, choice = False, None
    if folds >= 2:
        limit, prefer, table = select_fallback(chi2, consistent, ratio, n_diff, n_peak, candidates)
        if BLEND:  # the blend where the gates pass (only the chi-square limit to choose), unless the choice beats it
            b_limit, _, b_table = select_fallback(chi2, consistent, ratio, n_blend, n_peak, candidates,
                                                  ratios=(math.inf,))
            kept_blend = _keeps_diff(chi2, consistent, ratio, b_limit, math.inf)
            kept_switch = _keeps_diff(chi2, consistent, ratio, limit, prefer)
            blend, choice = _blend_holds(np.where(kept_blend[:, None], n_blend, n_peak),
                                         np.where(kept_switch[:, None], n_diff, n_peak))
            if blend:
                limit, prefer, table = b_limit, math.inf, b_table
    else:  # too few frames to hold any out: the most permissive finite limit, equal variances (no blend tested)
        limit, prefer, table = max(candidates), 1.0, []
    under = [i for i in range(n) if own[i] and chi2[i] <= limit]
    # the stated term (level frames): with enough tilted frames diff reads they size it (_floor_with_tilt_term), and
    # show its slopes themselves, so the two readings are compared only without them
    disagreement = None
    if other_reading is not None and level and \
            sum(tilted[i] and _usable_tilted(diff[i], truths[i]) for i in under) < TILT_TERM_MIN_FRAMES:
        disagreement = reading_disagreement(frames, forward, other_reading, peak_params, correction, options)
    tilt_term = (diff_tilt_term(model_error, crosstalk, disagreement, mount_left).replace(
        tilt_about=sweep_slopes(normals, tilted)) if level else Uncertainty())
    # a few tilted frames among level ones: the level ones size the floor, the tilted ones the stated term
    base = tilt_term.replace(chi2_limit=limit, consistency_limit=CONSISTENCY_LIMIT, prefer_ratio=prefer, blend=blend)
    unc, rep, n_few = _floor_with_tilt_term([diff[i] for i in under], [truths[i] for i in under], tilted[under],
                                            level, base)
    sizing = n_few >= TILT_TERM_MIN_FRAMES
    if level and not sizing:
        if n_few:
            rep["tilt_term_sized"] = {"frames": n_few, "why": f"fewer than {TILT_TERM_MIN_FRAMES} tilted frames: "
                                      "the stated term as the model error sizes it"}
        rep["note"] = TILT_TERM_NOTE.format(n=n_few, need=TILT_TERM_MIN_FRAMES)
        if _share(_magnitude((disagreement or {}).get("slope_scale"))) is not None:
            rep["note"] += READINGS_NOTE.format(slope=abs(disagreement["slope_scale"]),
                                                angle=disagreement.get("angle_deg", math.nan)) + readings_tail
    use_diff = _keeps_diff(chi2, consistent, ratio, limit, prefer)
    sel = np.where(use_diff[:, None], e_blend if blend else e_diff, e_peak)

    def mean_finite(a: np.ndarray, scale: float) -> float:
        return float(np.mean(a[np.isfinite(a)])) * scale if np.any(np.isfinite(a)) else math.nan

    rep.update({"chi2_limit": None if math.isinf(limit) else limit, "prefer_ratio": prefer, "folds": folds,
                "frames_beyond_range": len(near_on) - len(use),
                "frames_choosing": (f"all {len(use)} frames from {NEAR_FALLBACK_RANGE:g} m on (fewer than "
                                    f"{FALLBACK_MIN_FRAMES} within {FALLBACK_MAX_RANGE:g} m)" if every_frame else
                                    f"the {len(use)} frames from {NEAR_FALLBACK_RANGE:g} m to {FALLBACK_MAX_RANGE:g} m"),
                "tilt_term": ("stated: the frames' tilts spread less than MIN_TILT_SPREAD, or too few frames are tilted "
                              "(DIFF_TILTED_SHARE); sized by the unit's model error (diff_tilt_term)"
                              + (", then by the tilted frames (tilt_term_sized; the floor from the others)"
                                 if sizing else "") if level else
                              "none: the frames' tilts spread MIN_TILT_SPREAD or more, the floor holds the tilt error"),
                "tilt_model_error": model_error, "tilt_crosstalk": crosstalk, "tilt_readings": disagreement,
                "tilt_mount_left_deg": None if mount_left is None else math.degrees(mount_left),
                "tilt_rel": unc.tilt_rel,
                "tilt_offset_rel": unc.tilt_offset_rel,
                "held_out": "frames_using_diff, angular_deg and point_mm: each frame with the floor of the other folds",
                "blend": (f"diff's plane blended with peak's where the gates pass ({BLENDED}; recovery.blend)" if blend
                          else "none: diff's plane or peak's, as prefer_ratio chooses"
                          + (" (it scored better than the blend on these frames)" if choice else "")),
                "blend_against_choice": choice,
                "frames_using_diff": int(np.sum(use_diff)), "frames_using_peak": int(np.sum(~use_diff)),
                "frames_inconsistent_with_peak": int(np.sum(~consistent)),
                "frames_peak_reads_better": int(np.sum(ratio > prefer)),
                "angular_deg": {k: mean_finite(v[:, 0], 180 / math.pi) for k, v in
                                (("diff", e_diff), ("peak", e_peak), ("blend", e_blend), ("selected", sel))},
                "point_mm": {k: mean_finite(v[:, 1], 1e3) for k, v in
                             (("diff", e_diff), ("peak", e_peak), ("blend", e_blend), ("selected", sel))},
                "candidates": table})
    return unc, rep


def update_calibration(cal, frames: Sequence[Frame], method: str, widen_peak: float = 1.0) -> dict:
    """Fit the ``uncertainty`` entries a method needs (``peak``; ``diff``: peak's too) into ``cal``; returns the report.
    ``widen_peak`` (>= 1): a factor on peak's covariance ``scale`` (at most :data:`MAX_SCALE`), for a peak mapping fitted
    on these same few frames, whose errors on them understate its errors on new ones
    (:func:`~place_safe.calibration.points.small_sample_factor`); diff's entry is fitted with peak's so widened."""
    old = cal.sections.get("uncertainty")
    section = dict(old) if isinstance(old, dict) else {}  # (a file's section that is not an object: replaced)
    report = {}
    if method in ("peak", "diff"):
        # the forward model's mount tilt where the file has a valid one (diff's calibration fits it before this; a
        # broken forward section does not stop the peak method)
        forward = bool(cal.sections.get("forward")) and "forward" not in cal.errors
        # where the sweep adopted each zone's own time scale with the mount held level, the mount the free reading saw
        # (peak's zone gains read the sweep the same way: its slopes part from a mounted unit's by as much; diff's too)
        left = mount_left(cal) if forward else None
        unc, report["peak"] = fit_peak_uncertainty(frames, cal.peak(),
                                                   mount_tilt=(left, 0.0) if left is not None else
                                                   cal.forward().mount_tilt if forward else None)
        if widen_peak > 1.0:
            report["peak"]["small_sample"] = {"factor": widen_peak, "scale_in_sample": unc.scale}
            unc = unc.replace(scale=min(unc.scale * widen_peak, MAX_SCALE))
        section["peak"] = unc.to_dict()
        mount_deg = report["peak"].get("tilt_offset_mount_deg", 0.0)
        if method == "peak":  # (a diff calibration prints diff's notes, which say the same of this capture)
            notes = []
            rep = report["peak"]
            if str(rep.get("tilt_term", "")).startswith("stated") and "tilt_term_sized" not in rep:
                notes.append(PEAK_TILT_NOTE)  # level frames: the slopes' scale was not measured
            if mount_deg > 0:  # a forward model this calibration did not fit: say whose mount the covariance carries
                notes.append(PEAK_MOUNT_NOTE.format(deg=mount_deg))
            if notes:
                report["peak"]["note"] = "; ".join(notes)
    if method == "diff":
        from place_safe.calibration.forward_fit import crosstalk_traded

        # the unit's model error as the forward fit measured it at the frames' true planes (sizes diff's tilt term)
        measured = (cal.reports.get("forward") or {}).get("model_error_chi2")
        forward = cal.forward()
        # the crosstalk where the forward fit says a level sweep left it undetermined (LEVEL_SWEEP_TRADED)
        traded = crosstalk_traded(cal.reports.get("forward"))
        unc, report["diff"] = fit_diff_uncertainty(frames, forward, cal.peak(), cal.diff(),
                                                   Uncertainty.from_dict(section["peak"]), cal.diff_options(),
                                                   model_error=measured,
                                                   crosstalk=forward.crosstalk if traded else None,
                                                   other_reading=other_reading(cal), mount_left=left,
                                                   readings_tail=readings_note_tail(cal))
        section["diff"] = unc.to_dict()
    cal.sections["uncertainty"] = section
    return report


def readings_note_tail(cal) -> str:
    """What the readings note (:data:`READINGS_NOTE`) ends with for ``cal``: what its tilted frames without ground truth
    showed where it compared some and they chose neither reading (:data:`READINGS_NEITHER_NOTE`), else how to give some
    (:data:`READINGS_FROM_NOTE`)."""
    seen = _forward_geometry(cal).get("unlabelled")
    return READINGS_NEITHER_NOTE.format(why=seen.get("why", "?")) if isinstance(seen, dict) else READINGS_FROM_NOTE


def other_reading(cal):
    """The forward model of the reading ``calibrate`` did not keep, where ``cal``'s level sweep did not tell its two
    readings of the zones' geometry apart (``reports.forward.geometry``: ``told_apart`` false, ``other_params`` kept):
    a :class:`~place_safe.recovery.forward.ForwardParams`; else None (a report of another shape, or params that do not
    load, too)."""
    geometry = _forward_geometry(cal)
    if geometry.get("told_apart") is not False or not isinstance(geometry.get("other_params"), dict):
        return None
    from place_safe.recovery.forward_params import ForwardParams

    try:
        return ForwardParams.from_dict(geometry["other_params"], "reports.forward.geometry.other_params")
    except CalibrationError:
        return None


__all__ = ["update_calibration", "reading_disagreement", "slope_scale_offset_bias", "DISAGREEMENT_FRAMES",
           "READINGS_NOTE", "READINGS_FROM_NOTE", "NEAR_LAW_FEW_FRAMES", "NEAR_FEW_NOTE", "near_prior", "NEAR_PRIOR_NOTE",
           "READINGS_NEITHER_NOTE", "readings_note_tail",
           "sweep_slopes",
           "mount_left", "other_reading", "ADOPTED_MOUNT_OFFSET_REL",
           "LEVEL_SLOPE", "nees", "fit_floor", "fit_peak_uncertainty", "fit_diff_uncertainty", "select_fallback",
           "chi2_candidates", "near_std_law", "fit_near_law", "near_law_table", "near_law_parameters", "knot_factor",
           "NEAR_KNOT_SHARE", "NEAR_REFERENCE_DEPTH", "CONSISTENCY_LIMIT", "PEAK_TILT_REL",
           "PEAK_MOUNT_OFFSET_REL", "PEAK_MOUNT_NOTE", "peak_tilt_term",
           "DIFF_TILT_REL", "DIFF_TILT_OFFSET_REL", "DIFF_TILT_PIVOT", "DIFF_TILTED_SHARE",
           "DIFF_TILT_FLOOR", "DIFF_TILT_PER_ERROR", "DIFF_TILT_PER_CROSSTALK", "DIFF_TILT_OFFSET_PER_CROSSTALK",
           "DIFF_TILT_OFFSET_FLOOR", "DIFF_TILT_OFFSET_PER_ERROR",
           "diff_tilt_term", "size_tilt_term", "TILT_TERM_MIN_FRAMES", "TILT_TERM_SCALES", "TILT_TERM_NOTE", "CV_FOLDS",
           "PREFER_RATIOS", "FALLBACK_SCORE_SE", "FALLBACK_SCORE_REL", "BLEND"]
