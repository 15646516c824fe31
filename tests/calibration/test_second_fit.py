"""The second forward fit and the choice between the two readings of a capture (:mod:`place_safe.calibration.second_fit`);
the second fit is stood in for by the values it would report (the fits themselves: docs/results.md)."""
import math

import numpy as np

from place_safe.recovery.forward import ForwardParams


def test_a_level_sweep_that_sets_the_geometry_far_from_nominal_gets_a_note():
    """The real sweep's level fit put its mount tilt at 4.2 deg and its fields of view at 0.81 / 0.67: a level table
    cannot tell those from each zone's own time scale, and ``calibrate`` says so. Near-nominal geometry, or tilted
    calibration frames (which do tell), get no note."""
    from types import SimpleNamespace

    from place_safe.calibration.second_fit import geometry_note
    from place_safe.recovery.forward import ForwardParams

    def frames(tilts_deg):
        return [SimpleNamespace(truth=SimpleNamespace(normal=np.array([math.sin(math.radians(t)), 0.0,
                                                                       math.cos(math.radians(t))])))
                for t in tilts_deg]

    level, tilted = frames([0.3, 0.5, 0.4]), frames([0.0, 12.0, 24.0])
    real = ForwardParams(edge_fov_scale=0.81, corner_fov_scale=0.67, mount_tilt=[-0.008, -0.073])
    note = geometry_note(real, level)
    assert note is not None and "0.81 / 0.67" in note and "4.2 deg" in note and "capture" in note
    assert geometry_note(ForwardParams(mount_tilt=[0.0, 0.02]), level) is not None  # 1.1 deg alone
    assert geometry_note(ForwardParams(edge_fov_scale=1.078, corner_fov_scale=1.055), level) is None
    assert geometry_note(ForwardParams(), level) is None
    assert geometry_note(real, tilted) is None
    assert geometry_note(real, []) is None


def test_a_far_geometry_gives_way_to_the_zones_time_scales_only_for_a_better_fit_reading_one_albedo(monkeypatch):
    """The choice of :func:`reconsider_geometry` (the second fit stood in by the values it would report; the fits
    themselves are measured in docs/results.md): tilted frames, a second fit with each zone's own time scale and the
    geometry free together, adopted when clearly better (the albedo's rule where the frames are of one surface); a
    level sweep, one whatever the geometry
    its first fit set (near nominal too: unit 52's zones kept their own time behind it); a converged
    nominal-geometry fit at least NOMINAL_GEOMETRY_GAIN lower in RMS whose frames' albedos spread at most 3 times as
    much (or the absolute allowance more), and read as one surface, from the default start, is adopted, and the report
    says from what; a smaller gain, more spread albedos,
    a fit that did not converge or one that failed leaves the first fit, with the note when its geometry is beyond
    the note's limits (naming the comparison or the failure) and without one when it is not; without a second fit (the
    staged unit model) the note alone."""
    from types import SimpleNamespace

    import place_safe.calibration.forward_fit as ff
    import place_safe.calibration.second_fit as sf
    from place_safe.calibration.uncertainty import mount_left, other_reading

    def sweep(tilt_deg):
        t = math.radians(tilt_deg)
        return [SimpleNamespace(truth=SimpleNamespace(normal=np.array([math.sin(t * k), 0.0, math.cos(t * k)])))
                for k in range(3)]

    level, tilted = sweep(0.2), sweep(12.0)
    far = ForwardParams(edge_fov_scale=0.81, corner_fov_scale=0.67, mount_tilt=[-0.008, -0.073])
    off = ForwardParams(edge_fov_scale=1.078, corner_fov_scale=1.055)  # within the note's limits
    first = {"rms_scaled_residual_after": 2.0, "converged": True, "ref_floor": {"chosen": "published"},
             "one_surface": {"albedo_cv_after": 0.04}}
    calls = []

    def second(rms, converged=True, cv=0.05, undetermined=()):
        def fit(frames, init=None, progress=True, fitted=None, **kw):
            calls.append((fitted, kw, init))
            if rms is None:
                raise ArithmeticError("the residuals at the start are not finite")
            return (ForwardParams(zone_bin_scales=[0.98] * 4 + [1.0] + [0.98] * 4),
                    {"rms_scaled_residual_after": rms, "converged": converged, "solver": {"seconds": 1.0},
                     "one_surface": {"albedo_cv_after": cv},
                     "posterior_std": {"not_determined": ["crosstalk", *undetermined]}})
        return fit

    monkeypatch.setattr(ff, "fit_forward", second(1.7))
    p, r = sf.reconsider_geometry(tilted, far, dict(first), progress=False)
    # tilted frames tell the zones' directions from their time: the second fit has both free, and a clearly better
    # one is adopted (the geometry as it fitted it, not nominal)
    fitted, kw, init = calls.pop()
    assert fitted == sf.SCALES_AND_GEOMETRY_FITTED and {"zone_bin_scales", *sf.NOMINAL_GEOMETRY} <= set(fitted)
    assert init is None and not calls and sf.second_fit_for(tilted) is sf.scales_and_geometry_fit
    assert sf.second_fit_for(level) is sf.nominal_geometry_fit
    g = r["geometry"]
    assert p.zone_bin_scales[0] == 0.98 and g["adopted"] == "time_scales" and "2.000 -> 1.700" in g["why"]
    assert g["told_apart"] and g["other_params"]["edge_fov_scale"] == far.edge_fov_scale and "note" not in g
    assert g["capture"] == "tilted" and g["time_scales"]["not_determined"] == []
    # kept, and said why; the other reading goes with the report where its fit converged (the tilted frames told the
    # two apart: nothing is left for diff's covariance to hold, uncertainty.other_reading)
    for fit, first_cv, says, apart in ((second(2.0 * (1.0 - 0.9 * sf.NOMINAL_GEOMETRY_GAIN)), 0.04, "lower", True),
                                       (second(1.5, converged=False), 0.04, "not converged", False),
                                       (second(1.5, cv=0.04 * sf.NOMINAL_GEOMETRY_ALBEDO_SPREAD + 0.001), 0.04,
                                        "albedos spread", True),
                                       (second(1.5), math.nan, "could not be compared", True),
                                       (second(1.5, cv=math.nan), 0.04, "could not be compared", True),
                                       (second(1.5, undetermined=["mount_tilt"]), 0.04, "do not determine mount_tilt",
                                        True),
                                       (second(None), 0.04, "failed: ArithmeticError", False)):
        monkeypatch.setattr(ff, "fit_forward", fit)
        lines = []
        p, r = sf.reconsider_geometry(tilted, far, dict(first, one_surface={"albedo_cv_after": first_cv}),
                                      progress=False, log=lines.append)
        g = r["geometry"]
        assert p is far and g["adopted"] == "free" and says in g["why"] and says in lines[-1]
        assert g["capture"] == "tilted" and g["told_apart"] is apart and ("other_params" in g) is apart
        assert other_reading(SimpleNamespace(reports={"forward": r})) is None and mount_left(
            SimpleNamespace(reports={"forward": r})) is None  # nothing left open for diff's covariance
    # frames both readings call many surfaces (the independent generator's): the albedos cannot witness, even spread
    # wider; the tilted frames' RMS decides
    monkeypatch.setattr(ff, "fit_forward", second(1.5, cv=2.5))
    p, r = sf.reconsider_geometry(tilted, far, dict(first, one_surface={"albedo_cv_after": 0.5}), progress=False)
    assert r["geometry"]["adopted"] == "time_scales" and "many surfaces" in r["geometry"]["why"]
    # one table that the first fit misread as many albedos (unit 39's capture, 95 % -> 1.1 %): one surface, the guard
    # passes; a second fit that reads many albedos where the first reads one surface is refused
    monkeypatch.setattr(ff, "fit_forward", second(1.5, cv=0.011))
    p, r = sf.reconsider_geometry(tilted, far, dict(first, one_surface={"albedo_cv_after": 0.95}), progress=False)
    assert r["geometry"]["adopted"] == "time_scales" and "many surfaces" not in r["geometry"]["why"]
    monkeypatch.setattr(ff, "fit_forward", second(1.5, cv=0.25))
    p, r = sf.reconsider_geometry(tilted, far, dict(first, one_surface={"albedo_cv_after": 0.1}), progress=False)
    assert r["geometry"]["adopted"] == "free" and "one surface" in r["geometry"]["why"]
    calls.clear()
    monkeypatch.setattr(ff, "fit_forward", second(1.7))
    near = ForwardParams(edge_fov_scale=1.004, corner_fov_scale=1.003, mount_tilt=[-0.003, -0.001])  # unit 52's
    p, r = sf.reconsider_geometry(level, near, dict(first), progress=False)
    assert len(calls) == 1 and r["geometry"]["adopted"] == "nominal_time_scales"  # a level sweep: whatever its geometry

    lines = []
    for params in (far, off):
        p, r = sf.reconsider_geometry(level, params, dict(first), progress=False, log=lines.append)
        fitted, kw, init = calls[-1]
        assert fitted == sf.NOMINAL_GEOMETRY_FITTED and "zone_bin_scales" in fitted and init is None and not kw
        assert not set(sf.NOMINAL_GEOMETRY) & set(fitted)
        assert p.edge_fov_scale == 1.0 and p.mount_tilt == [0.0, 0.0] and p.zone_bin_scales[0] == 0.98
        g = r["geometry"]
        assert g["adopted"] == "nominal_time_scales" and "note" not in g and "2.000 -> 1.700" in g["why"]
        assert g["free"]["edge_fov_scale"] == params.edge_fov_scale and "adopted" in lines[-1]
        assert g["told_apart"] and g["other_params"]["edge_fov_scale"] == params.edge_fov_scale  # the reading set aside
    assert abs(sf.reconsider_geometry(level, far, dict(first), progress=False)[1]["geometry"]["free"]
               ["mount_tilt_deg"][1] + 4.18) < 0.01

    # kept: the second fit's params go with the report where it converged; the sweep told the readings apart only where
    # the second fit is clearly worse (TOLD_APART_GAIN): about as good, or better but set aside, leaves both possible
    lower = f"not a converged fit {sf.NOMINAL_GEOMETRY_GAIN:.1%} lower"
    for fit, says, apart, other in ((second(2.0 * (1.0 - 0.9 * sf.NOMINAL_GEOMETRY_GAIN)), lower, False, True),
                                    (second(2.2), lower, True, True),
                                    (second(1.5, converged=False), "not converged", False, False),
                                    (second(1.5, cv=0.15), "many albedos", False, True),
                                    (second(1.5, cv=0.04 * sf.NOMINAL_GEOMETRY_ALBEDO_SPREAD + 0.001), "many albedos",
                                     False, True),
                                    (second(None), "failed: ArithmeticError", False, False)):
        monkeypatch.setattr(ff, "fit_forward", fit)
        for params in (far, off):
            p, r = sf.reconsider_geometry(level, params, dict(first, ref_floor=None), progress=False,
                                          log=lines.append)
            g = r["geometry"]
            assert p is params and g["adopted"] == "free" and says in g["why"]
            assert g["told_apart"] is apart and ("other_params" in g) is other
            if other:
                assert g["other_params"]["zone_bin_scales"][0] == 0.98 and g["other_params"]["edge_fov_scale"] == 1.0
            assert "kept the fitted geometry" in lines[-1]
            if params is far:
                assert "0.81 / 0.67" in g["note"] and "capture" in g["note"] and says in g["note"]
            else:
                assert "note" not in g

    # the albedos: a first fit reading nearly one albedo does not refuse every second fit; unknown spreads do not adopt
    monkeypatch.setattr(ff, "fit_forward", second(1.7, cv=0.04 * sf.NOMINAL_GEOMETRY_ALBEDO_SPREAD))  # at the bound
    assert sf.reconsider_geometry(level, off, dict(first), progress=False)[1]["geometry"]["adopted"] == \
        "nominal_time_scales"
    monkeypatch.setattr(ff, "fit_forward", second(1.5, cv=0.004))
    p, r = sf.reconsider_geometry(level, off, dict(first, one_surface={"albedo_cv_after": 0.0}), progress=False)
    assert r["geometry"]["adopted"] == "nominal_time_scales"
    # unit 52 (0.58 -> 2.64 %, RMS 18.6 % lower) is adopted: within the absolute allowance, which is CV noise between
    # alike readings; just past the allowance it is not, nor are the real halves' time scales (4.5 -> 21 %)
    for cv_first, cv_second, adopted in ((0.0058, 0.0264, True),
                                         (0.0058, 0.0058 + sf.NOMINAL_GEOMETRY_ALBEDO_CV + 0.001, False),
                                         (0.0446, 0.2109, False)):
        monkeypatch.setattr(ff, "fit_forward", second(0.814 * 2.0, cv=cv_second))
        p, r = sf.reconsider_geometry(level, off, dict(first, one_surface={"albedo_cv_after": cv_first}),
                                      progress=False)
        assert (r["geometry"]["adopted"] == "nominal_time_scales") is adopted
    # unit 60 (time scales of 0.8 %): the RMS 3.7 % lower, the table read as closely: adopted
    monkeypatch.setattr(ff, "fit_forward", second(2.0 * 0.880 / 0.914, cv=0.0137))
    p, r = sf.reconsider_geometry(level, off, dict(first, one_surface={"albedo_cv_after": 0.0167}), progress=False)
    assert r["geometry"]["adopted"] == "nominal_time_scales"
    for a, b in ((math.nan, 0.01), (0.01, math.nan)):
        monkeypatch.setattr(ff, "fit_forward", second(1.5, cv=b))
        p, r = sf.reconsider_geometry(level, off, dict(first, one_surface={"albedo_cv_after": a}), progress=False)
        assert p is off and "could not be compared" in r["geometry"]["why"]
    # frames of many surfaces (the independent generator draws an albedo per frame): the albedos cannot witness, and a
    # better RMS alone does not take the geometry away, even with the spread no wider than the first fit's
    monkeypatch.setattr(ff, "fit_forward", second(1.5, cv=2.50))
    p, r = sf.reconsider_geometry(level, off, dict(first, one_surface={"albedo_cv_after": 2.55}), progress=False)
    assert p is off and "one surface" in r["geometry"]["why"]
    monkeypatch.setattr(ff, "fit_forward", second(1.5, cv=ff.SAME_SURFACE_CV))  # at the bound: one surface
    p, r = sf.reconsider_geometry(level, off, dict(first, one_surface={"albedo_cv_after": 0.19}), progress=False)
    assert r["geometry"]["adopted"] == "nominal_time_scales"

    n = len(calls)
    p, r = sf.reconsider_geometry(level, far, dict(first), second_fit=False)
    assert p is far and len(calls) == n and r["geometry"]["adopted"] == "free" and "0.81 / 0.67" in r["geometry"]["note"]
    assert "geometry" not in sf.reconsider_geometry(level, off, dict(first), second_fit=False)[1]


def test_the_level_sweeps_albedo_alone_chooses_the_time_scales_where_it_reads_one_albedo_much_more_closely(
        monkeypatch):
    """:func:`reconsider_geometry` on the albedo's evidence: a second fit at least ALBEDO_CLUE_GAIN lower in RMS whose
    frames read one albedo at least ALBEDO_CLUE_FACTOR times more closely is adopted (the readings told apart); a fall
    of the CV less than that, a first CV under ALBEDO_CLUE_MIN_CV (noise), a smaller RMS gain, a first fit of many
    surfaces, or a fit that did not converge leaves the first reading."""
    from types import SimpleNamespace

    import place_safe.calibration.forward_fit as ff
    import place_safe.calibration.second_fit as sf

    level = [SimpleNamespace(truth=SimpleNamespace(normal=np.array([math.sin(0.002 * k), 0.0, math.cos(0.002 * k)])))
             for k in range(3)]
    off = ForwardParams(edge_fov_scale=1.136, corner_fov_scale=1.081, mount_tilt=[0.013, 0.015])

    def second(rms, cv, converged=True, excluded=0):
        def fit(frames, init=None, progress=True, fitted=None, **kw):
            return (ForwardParams(zone_bin_scales=[1.01] * 4 + [1.0] + [1.01] * 4),
                    {"rms_scaled_residual_after": rms, "converged": converged, "solver": {"seconds": 1.0},
                     "one_surface": {"albedo_cv_after": cv}, "frames_excluded_as_bad": excluded})
        return fit

    def choose(rms, cv, first_cv, converged=True, left_out=(0, 0), first_rms=1.424):
        monkeypatch.setattr(ff, "fit_forward", second(rms, cv, converged, left_out[1]))
        first = {"rms_scaled_residual_after": first_rms, "converged": True,
                 "one_surface": {"albedo_cv_after": first_cv, "frames_at_albedo_bound": left_out[0]}}
        p, r = sf.reconsider_geometry(level, off, first, progress=False)
        return r["geometry"]

    # between the two RMS bars (ALBEDO_CLUE_GAIN, NOMINAL_GEOMETRY_GAIN) only the albedo's evidence adopts: unit 44's
    # albedos (measured on the simulator before 2026-11-30, with its RMS 4 % lower)
    clue = 1.424 * (1.0 - 0.5 * (sf.ALBEDO_CLUE_GAIN + sf.NOMINAL_GEOMETRY_GAIN))
    g = choose(clue, 0.007, 0.037)
    assert g["adopted"] == "nominal_time_scales" and g["told_apart"] and "5.3 times more closely" in g["why"]
    g = choose(1.424 * (1 - sf.ALBEDO_CLUE_GAIN), 0.037 / sf.ALBEDO_CLUE_FACTOR, 0.037)  # at both bounds
    assert g["adopted"] == "nominal_time_scales"
    for rms, cv, first_cv, converged in ((clue, 0.013, 0.037, True),     # the CV falls less than 3 times
                                         (1.424 * 0.985, 0.007, 0.037, True),  # the RMS 1.5 % lower
                                         (1.430, 0.007, 0.037, True),    # higher RMS (a mount alone)
                                         (clue, 0.002, 0.009, True),     # the first CV within noise
                                         (clue, 0.05, 0.25, True),       # the first reads many surfaces
                                         (clue, 0.007, 0.037, False)):   # not converged
        g = choose(rms, cv, first_cv, converged)
        assert g["adopted"] == "free" and not g["told_apart"], (rms, cv, first_cv, converged)
    # a spread made small by leaving frames out is no evidence; on as many frames left out as the first's, it is
    g = choose(clue, 0.007, 0.037, left_out=(0, 1))
    assert g["adopted"] == "free" and g["nominal_time_scales"]["frames_left_out"] == 1
    assert choose(clue, 0.007, 0.037, left_out=(1, 1))["adopted"] == "nominal_time_scales"
    # the clearly better fit whose albedos spread more, within the guard: unit 34's figures (its zones keep their own
    # time; kept at 1.52 deg with the guard at 1.5 times, 0.13 adopted)
    g = choose(1.372, 0.082, 0.030, first_rms=1.693)
    assert g["adopted"] == "nominal_time_scales" and "clearly better" in g["why"]
    assert choose(1.372, 0.14, 0.030, first_rms=1.693)["adopted"] == "free"  # (the real halves: 4.7 times, kept)
