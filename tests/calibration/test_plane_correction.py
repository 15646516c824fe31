"""Diff's plane correction (:mod:`place_safe.calibration.plane_correction`): the series' degree and variable chosen by
cross-validation, and the albedo's range law."""
import numpy as np


def test_correction_series_chosen_by_cross_validation_in_range_or_inverse_range():
    """An error that grows as 1 / z0 (a zone's depth disagreement of fixed size seen as a slope) is taken as a
    low-degree series in 1 / z0; one linear in z0 as a line in z0; pure noise as degree 0 at most."""
    from place_safe.calibration.plane_correction import _best_series, _series_degree

    rng = np.random.default_rng(3)
    z = np.sort(rng.uniform(0.05, 0.40, 24))
    domain = [float(z.min()), float(z.max())]
    noise = 1e-4 * rng.standard_normal(z.size)
    assert _series_degree(24) == 4 and _series_degree(8) == 1 and _series_degree(150) == 4
    _, inverse, deg = _best_series(z, 3e-4 / z + noise, domain, 4)
    assert inverse and deg == 1
    _, inverse, deg = _best_series(z, 0.01 * z + noise, domain, 4)
    assert not inverse and deg == 1
    loo, _, deg = _best_series(z, noise, domain, 4)
    assert deg <= 1 and loo < 2e-4


def test_the_albedo_series_follows_one_surfaces_trend_over_distance_and_not_scatter():
    """One surface whose albedo reads low up close (the real sweep: 14 at 5 cm, 25 beyond 10 cm) gets a log-albedo
    series that brings every frame to the sweep's mean (held-out frames too); albedos that scatter without a trend
    (several surfaces) get none, and neither do fewer than 8 frames with an albedo."""
    from place_safe.calibration.plane_correction import _albedo_series, _series_design

    rng = np.random.default_rng(5)
    z = np.sort(rng.uniform(0.05, 0.40, 26))
    domain = [float(z.min()), float(z.max())]
    trend = lambda zz: np.log(28.0) - 0.035 / zz  # noqa: E731 - 13.5 at 5 cm, 25 at 30 cm
    log_a = trend(z) + 0.01 * rng.standard_normal(z.size)
    log_a[3] = np.nan  # a frame without an albedo takes no part
    report = {}
    coef = _albedo_series(z, log_a, domain, 4, report)
    assert report["albedo_frames"] == 25
    assert report["albedo_mean_abs_leave_one_out"] < 0.1 * report["albedo_mean_abs_before"]
    z_new = np.linspace(domain[0], domain[1], 9)  # frames between the calibration's
    corrected = trend(z_new) + _series_design(z_new, domain, len(coef) - 1, False, True) @ coef
    assert np.ptp(corrected) < 0.03 and abs(corrected.mean() - np.nanmean(log_a)) < 0.03
    report = {}
    assert _albedo_series(z, np.log(20.0) + 0.3 * rng.standard_normal(z.size), domain, 4, report) is None
    assert "no clear" in report["albedo_why_not"]
    assert _albedo_series(z[:7], trend(z[:7]), domain, 4, {}) is None
