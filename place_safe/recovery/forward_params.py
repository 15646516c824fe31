"""The forward imaging model's parameters (:class:`ForwardParams`): what a unit's calibration states in its ``forward``
section, with their units, bounds and defaults (the values published with the paper), and the constants their shapes
need. No torch here: a calibration file is read and checked, and the peak method runs, without loading the renderer
(:mod:`place_safe.recovery.forward`, which renders with these parameters and re-exports them).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from pydantic import Field, model_validator

from place_safe.config import ParamModel, vector
from place_safe.exceptions import CalibrationError
from place_safe.sensor.frame import N_BINS, N_ZONES, ZONE_KIND, ZONE_RECTS
from place_safe.sensor.histogram import COUNT_MAX

#: Lags (bins) of the learned impulse response (:class:`ForwardParams` ``response_kernel``). The real sweep's
#: histograms hold a second bump 13-19 bins after the peak, which no exponential tail of the model reaches.
RESPONSE_LAGS = 24
#: m: the range at which :class:`ForwardParams` ``echo_gain`` is the echo's size relative to the direct return.
ECHO_REFERENCE_RANGE = 0.1


#: Spacing (bins) of the knots of ``ForwardParams.time_warp`` and their number (bins 0, 8, ..., 128).
WARP_SPACING = 8
WARP_KNOTS = N_BINS // WARP_SPACING + 1


def _grid_positions() -> np.ndarray:
    """Each zone's (column, row) in the 3x3 grid (9, 2), each in {-1, 0, 1}: the signs of its rectangle's centre."""
    centre = np.stack([ZONE_RECTS[:, :2].mean(axis=1), ZONE_RECTS[:, 2:].mean(axis=1)], axis=1)
    return np.sign(np.round(centre, 9)).astype(int)


#: The 8 neighbour displacements (dx, dy) of the 3x3 grid, in the order of ``ForwardParams.crosstalk_grid``:
#: row by row (dy = -1, 0, 1), within a row dx = -1, 0, 1, the zone itself (0, 0) left out.
GRID_DISPLACEMENTS = tuple((dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if (dx, dy) != (0, 0))


def _grid_selectors() -> np.ndarray:
    """(8, 9, 9): ``S[k, to, from]`` is 1 where zone ``from`` sits at ``GRID_DISPLACEMENTS[k]`` from zone ``to``."""
    pos = _grid_positions()
    sel = np.zeros((len(GRID_DISPLACEMENTS), N_ZONES, N_ZONES))
    for k, (dx, dy) in enumerate(GRID_DISPLACEMENTS):
        for to in range(N_ZONES):
            for frm in range(N_ZONES):
                if pos[frm, 0] - pos[to, 0] == dx and pos[frm, 1] - pos[to, 1] == dy:
                    sel[k, to, frm] = 1.0
    return sel


_GRID_SELECTORS = _grid_selectors()


class ForwardParams(ParamModel):
    """Camera parameters of the forward model. Defaults are the values published with the paper.

    ``tail_weight`` and ``tail_decay`` (bins) extend the paper's model: the zone histograms of a real
    TMF8820 decay more slowly after the peak than the rescaled reference pulse, so the pulse is
    convolved with ``delta + tail_weight * exp(-k / tail_decay)`` (k >= 1 bins); and the zones'
    fields of view may be narrower than the nominal rectangles (the paper's calibrated peak method
    found edge and corner directions at 0.94 and 0.89 of their nominal angles), so ``edge_fov_scale``
    and ``corner_fov_scale`` scale those zones' rectangles on ``z = 1`` towards the axis. The
    defaults (``tail_weight = 0``, scales 1) are the paper's model exactly. Each zone may add its own tail
    (``zone_tail_weights``, ``zone_tail_decays``, (9,) each): zone ``z``'s histogram, after the pulse, is
    convolved with ``delta + zone_tail_weights[z] * exp(-k / zone_tail_decays[z])`` (k >= 1 bins, up to
    :data:`~place_safe.recovery.forward.ZONE_TAIL_BINS`), before crosstalk and pile-up; zero weights (the default) add nothing. ``pileup`` (1/counts)
    adds the timing distortion of SPAD pile-up (Coates): a detector that records at most one photon
    per laser cycle sees bin ``b`` with probability ``(1 - exp(-k h_b)) exp(-k sum_{j<b} h_j)``, so
    at high flux the histogram shifts and skews earlier, which the paper's amplitude-only saturation
    cannot express. ``pileup = 0`` turns it off.

    ``mount_tilt`` (rad, rotation vector ``(rx, ry, 0)``) is the rotation from the sensor's optical
    frame, in which the model renders, to the frame planes are reported in (the nominal sensor frame
    of the mount, in which ground truth is given): a sensor soldered a degree off its nominal
    orientation is calibrated, not mistaken for a tilted table. See :func:`~place_safe.recovery.forward.mount_rotation`.

    ``model_error`` is the relative error (a fraction of the counts in a bin) the estimator allows
    the model when weighting residuals (:func:`~place_safe.recovery.forward.residual_weights`): 0.5 % by default, which is what
    calibration chooses for data the model describes exactly; ``calibrate --method diff`` chooses it
    for each sensor (1-2 % on the real sweep).

    Structural choices (the paper and its published code differ; real code uses either): the zone
    pulse is ``(1 - pulse_soft_bin)`` times the reference rescaled by linear interpolation plus
    ``pulse_soft_bin`` times the reference rescaled by the paper's Gaussian soft binning (sigma
    ``soft_bin_sigma``, each normalised to peak 1); saturation acts on ``shade^saturate_shading``
    and the remaining ``shade^(1 - saturate_shading)`` multiplies afterwards
    (``p = s (1 - exp(-g rho shade^w / (s r^2))) shade^(1-w)``: 1 is the paper's equation, 0 the
    published code); crosstalk adds ``crosstalk * (total - (1 - crosstalk_self) h)``; the zone gain
    ``g`` enters the saturation as ``g^saturate_gain`` and multiplies the saturated counts by
    ``g^(1 - saturate_gain)`` (1: a zone's gain is optical, in front of the SPADs, and saturates with
    the flux; 0: it is the zone's share of SPAD pixels, each saturating on its own, so the gain scales
    saturated counts and zone brightness ratios do not change with range). The defaults (0, 1, 0, 1)
    are the model as it was.

    Emitter-receiver baseline: the receiver is at the origin, the emitter at ``(bx, by, 0)`` =
    ``baseline`` (m). A ray's return then travels ``r_e + r`` (``r_e`` = |P - E|, the bin position uses
    half of it), its irradiance falls with ``r_e^2`` instead of ``r^2``, the Lambert cosine is the light's
    ``(d - n . E) / r_e`` and the emitter's profile ``(P_z / r_e)^beam_power`` weights it. Close up
    this tilts the illumination of the zones' footprints; far away it is the co-located model times a
    per-direction beam weight. ``baseline = (0, 0)``, ``beam_power = 0`` is the paper's model exactly.

    The unit's own terms (version 3; every default adds nothing, so files without them read as the model as it
    was). Each has a meaning, a unit, a range (its ``Field``) and a prior
    (:data:`place_safe.calibration.forward_fit.PRIORS`, mean / std):

    * ``crosstalk_grid`` (8, fraction, [0, 0.5], prior 0 / 0.02): light of a zone's neighbour that reaches the
      zone's SPADs (lens blur, stray light between neighbouring apertures), by the neighbour's displacement in the
      3x3 grid (:data:`GRID_DISPLACEMENTS`); added with the scalar ``crosstalk`` (which leaks into every zone).
    * ``glass_gains`` (9, counts per unit-area transient, [0, 1e5], prior 0 / 100) and ``glass_delay`` (bins,
      [-8, 16], prior 0 / 4): the return of the cover glass and package at zero range, the same in every frame,
      shaped by the pulse; ``glass_delay`` is its position after ``bin_offset`` (zero range).
    * ``echo_gain`` (fraction, [0, 1], prior 0 / 0.1): the multipath echo, light the surface returns to the
      sensor's face and the face sends back to the surface, at twice the range, ``echo_gain (0.1 m / r)^echo_power`` of the
      direct return (:meth:`ForwardModel.add_echo_and_glass`).
    * ``centre_fov_scale`` (fraction, (0, 3], prior 1 / 0.2 in log): the centre zone's rectangle scaled about the
      axis, as ``edge_fov_scale`` and ``corner_fov_scale`` scale the others (the spread of ranges in its footprint).
    * ``echo_power`` ((0 .. 4), default 2, prior 2 / 1): the echo's size relative to the direct return is
      ``echo_gain (0.1 m / r)^echo_power``. 2 is the face-to-surface round trip spreading over the range squared; the
      real sweep's second return is about 5e-4 of the peak at every range from 5 to 31 cm (a power near 0: light
      that the package sends back along the same cone, whose share of the return does not change with range).
    * ``pileup_shadow`` (blend, [0, 1], default 1, prior 1 / 0.5): the pile-up is
      ``(1 - exp(-k h_b)) / k exp(-k pileup_shadow sum_{j<b} h_j)``. 1 is Coates' single-photon detector (counts early
      in the cycle shadow later bins); 0 keeps only each bin's own compression, as in a zone of many SPADs with a
      dead time about the pulse's width, where the peak is compressed and the tail after it is not (the real
      sweep's tail grows relative to the peak as the surface comes closer).
    * ``zone_pulse_widths`` (9, bins^2, [-0.25, 0.25], prior 0 / 0.1) and ``zone_pulse_skews`` (9, bins^3, [-0.25,
      0.25], prior 0 / 0.1): each zone's pulse differs from the reference's rescaled shape (its SPADs' jitter, the
      spread of its footprint's path lengths inside the package): after the pulse convolution zone ``z``'s
      histogram is convolved with a short kernel of zero area and mean (:func:`~place_safe.recovery.forward.pulse_shape_matrix`) that adds
      ``2 w_z`` bins^2 to the pulse's variance and ``6 s_z`` bins^3 to its third central moment. Beside a sharp pulse
      the correction can dip below zero; the expected counts are clamped at 0 (after the crosstalk, before pile-up).
    * ``bin_gains`` (128, relative width, [0.5, 1.5], default 1, prior 1 / 0.03; version 5): the time-to-digital
      converter's differential non-linearity. Bin ``b`` of every zone is ``bin_gains[b]`` times as wide as nominal, so
      it collects that much more (or less) of the light arriving in it: the expected counts of bin ``b`` are multiplied
      by it after the crosstalk and before the pile-up. One vector shared by the zones. Only the bin-to-bin pattern
      acts: each gain is divided by the mean of its neighbours within 4 bins (:func:`~place_safe.recovery.forward.bin_widths`), because a slow
      trend is the brightness's fall with range to a level sweep. The measured floor (ambient)
      is not multiplied: a few % of a 100-150 count ambient is below its Poisson noise (the real sweep's ambient bins
      90-127 show no pattern above it). A level sweep moves each zone's return across the bins, so a gain fixed in
      bin index is separable from the pulse's shape (fixed relative to the return).
    * ``time_warp`` (17, bins, [-4, 4], default 0, prior 0 / 0.3; version 5): the time-to-digital converter's
      integral non-linearity, where a return appears minus where ``bin_offset + range / bin_size`` (plus the zone's
      offset) puts it, at bins 0, 8, ..., 128 and linear between, less its straight line over the knots (which is
      ``bin_offset`` and ``bin_size``'s, :func:`~place_safe.recovery.forward.warp_positions`); it moves the direct return, the echo and the glass
      alike. A level sweep with known ranges determines it where returns fall, with ``bin_offset`` and ``bin_size``
      held (fitted together, the reached knots trade with ``bin_size``).
    * ``zone_bin_scales`` (9, bins per nominal bin, [0.9, 1.1], default 1, prior 1 / 0.02 in log; version 6): each
      zone's histogram has its own time scale (its own TDC channel's bin width, or the return-weighted obliquity of its
      footprint differing from the nominal rectangle's): a return at one-way range ``r`` sits at
      ``r / bin_size * zone_bin_scales[z] + bin_offset + zone_offsets[z]`` (the echo at twice that range likewise; the
      glass at zero range does not move). ``zone_offsets`` is each zone's constant delay, this its delay growing with
      range. The centre zone's is the gauge (1: ``bin_size`` is the common scale). A level sweep determines it with the
      fields of view and the beam held (on level planes they move a zone's return with range alike): the real sweep's
      rising edges, fitted without it, drift by -0.11 .. +0.08 bins per 10 cm from zone to zone (docs/results.md, the
      unit model, step 5).
    * ``soft_bin_integrated`` (blend, [0, 1], default 0; version 7): how a ray's arrival becomes counts in bins. 0 is
      the paper's Gaussian of ``soft_bin_sigma`` sampled at the bin centres, whose sum over the bins and centroid
      vary with the ray's sub-bin position (sigma 0.5: +-1.4 %, +-0.023 bins); 1 is that Gaussian integrated over each
      bin, ``Phi((n + 1/2 - u) / sigma) - Phi((n - 1/2 - u) / sigma)``, which sums to 1 and keeps the centroid at any
      position, as a time-to-digital converter that counts every arrival within a bin does (:func:`~place_safe.recovery.forward.bin_kernel`). A
      structural choice held at its value (not among the fitted parameters).
    * ``soft_bin_spline`` (0 or 1, default 0; version 8): 1 spreads each ray's arrival by the quadratic B-spline (the
      bin's box convolved with itself twice, variance 1/4 bin^2) convolved with the Gaussian of ``soft_bin_sigma``
      (:func:`~place_safe.recovery.forward.bin_kernel`). A B-spline of degree 2 reproduces polynomials up to degree 2, so the kernel's sum over
      the bins, its centroid and its width stay the same wherever the ray falls within a bin, for any sigma. The
      sampled Gaussian's do not below sigma ~0.65: the fitted sigma (0.48-0.55 on real and simulated units) then
      makes the model's shape, and so diff's timing, follow the return's sub-bin position by a one-bin periodic error
      that the sensor does not have (docs/results.md, the unit model, step 10). Its total width is
      ``sqrt(1/4 + sigma^2)`` bins. Exclusive with ``soft_bin_integrated``; held, not fitted.
    * The per-zone timing offsets and gains (``zone_offsets``, ``zone_gains``), pile-up (``pileup``), the zones'
      own tails and the learned response kernel are described above.
    * ``ambient_slope`` (version 9, [-0.9, 0.9], default 0): a unit whose ambient floor changes by this share of its
      middle value from the first bin to the last, the same in every frame. Not part of the rendering: the floor
      subtracted from a frame's counts before they are compared with the model follows it
      (:func:`~place_safe.sensor.histogram.floor_profile`); calibration measures it from the first bins of a level
      sweep and keeps it only where it is one number over distance
      (:func:`~place_safe.calibration.forward_fit.measure_ambient_slope`).

    The ranges (each field's ``Field``) are wide (a TMF8820 fitted on the shared sweep sits well inside) but
    exclude what breaks the model: a zero or negative albedo, gain or specular exponent (undefined Phong term), a
    pulse stretched so far that its kernel would not fit in memory, a mount tilt beyond any soldering error.

    Units: ``bin_offset``, ``soft_bin_sigma``, ``tail_decay``, ``zone_tail_decays`` and ``zone_offsets`` in bins; ``bin_size`` in metres
    of one-way range per bin; ``ref_floor`` and ``floor`` in counts; the rest dimensionless.
    """

    what: ClassVar[str] = "forward parameters"
    error: ClassVar[type[Exception]] = CalibrationError

    albedo: float = Field(3.4410, gt=0.0, le=1e4, description="(dimensionless reflectance scale)")
    edge_gain: float = Field(0.5996, gt=0.0, le=10.0, description="(relative to the centre zone)")
    corner_gain: float = Field(0.4070, gt=0.0, le=10.0, description="(relative to the centre zone)")
    bin_offset: float = Field(9.5235, ge=-64.0, le=128.0, description="bins")
    bin_size: float = Field(0.014131, ge=0.001, le=0.1, description="m of one-way range per bin")
    crosstalk: float = Field(0.0097662, ge=0.0, le=0.5, description="(fraction of every other zone)")
    specular_weight: float = Field(0.14681, ge=0.0, le=100.0, description="(relative to the diffuse term)")
    specular_exponent: float = Field(1.8378, gt=0.0, le=1000.0, description="(Phong exponent)")
    soft_bin_sigma: float = Field(0.5, ge=0.01, le=32.0, description="bins")
    ref_time_scale: float = Field(0.27887, ge=0.01, le=4.0, description="zone bins per reference bin")
    ref_floor: float = Field(135.14, ge=0.0, le=COUNT_MAX, description="counts")
    # (at most 1e9 counts, beyond which the model has no saturation to speak of: 1e308 overflowed diff's solve)
    saturation: float = Field(315.85, gt=0.0, le=1e9, description="counts (very large: no saturation)")
    rays_per_zone: int = Field(2304, ge=1, le=1 << 16, description="rays")
    floor: float = Field(0.0, ge=-COUNT_MAX, le=COUNT_MAX, description="counts")
    tail_weight: float = Field(0.0, ge=0.0, le=10.0, description="(relative to the pulse)")
    tail_decay: float = Field(2.0, gt=0.0, le=64.0, description="bins")
    zone_tail_weights: vector(N_ZONES, ge=0.0, le=10.0) = Field(default_factory=lambda: [0.0] * N_ZONES,
                                                                description="(relative to the zone's histogram)")
    zone_tail_decays: vector(N_ZONES, gt=0.0, le=8.0) = Field(default_factory=lambda: [2.0] * N_ZONES,
                                                              description="bins")
    edge_fov_scale: float = Field(1.0, gt=0.0, le=3.0, description="(of the nominal zone rectangle)")
    corner_fov_scale: float = Field(1.0, gt=0.0, le=3.0, description="(of the nominal zone rectangle)")
    pileup: float = Field(0.0, ge=0.0, le=1.0, description="1/counts")
    mount_tilt: vector(2, ge=-0.5, le=0.5) = Field(default_factory=lambda: [0.0, 0.0],
                                                   description="rad (x, y of a rotation vector)")
    model_error: float = Field(0.005, ge=0.0, le=1.0, description="(fraction of the counts in a bin)")
    zone_offsets: vector(N_ZONES, ge=-32.0, le=32.0) = Field(default_factory=lambda: [0.0] * N_ZONES,
                                                             description="bins")
    zone_gains: vector(N_ZONES, gt=0.0, le=100.0) = Field(default_factory=lambda: [1.0] * N_ZONES,
                                                          description="(relative, centre zone 1)")
    # Structural choices of implementations of the paper's model, as continuous blends so calibration can
    # choose them by the data (see the class doc). All dimensionless, physical range [0, 1].
    # 0: reference rescaled by linear interpolation; 1: Gaussian soft binning
    pulse_soft_bin: float = Field(0.0, ge=0.0, le=1.0,
                                  description="(blend: 0 linear interpolation, 1 Gaussian soft binning)")
    # 1: SPAD saturation of the shaded intensity; 0: of the unshaded term
    saturate_shading: float = Field(1.0, ge=0.0, le=1.0,
                                    description="(blend: 1 saturate the shaded intensity, 0 the unshaded term)")
    # 0: a zone leaks into the others; 1: into all zones, itself included
    crosstalk_self: float = Field(0.0, ge=0.0, le=1.0, description="(blend: 1 crosstalk includes the zone itself)")
    # 1: zone gains inside the SPAD saturation; 0: outside (per-pixel saturation)
    saturate_gain: float = Field(
        1.0, ge=0.0, le=1.0, description="(blend: 1 the zone gains saturate with the flux, 0 they multiply afterwards)")
    # The emitter beside the receiver (what dominates close up): its position (m) in the optical frame and its
    # angular profile. Defaults (co-located, uniform) are the paper's model.
    baseline: vector(2, ge=-0.02, le=0.02) = Field(default_factory=lambda: [0.0, 0.0],
                                                   description="m (emitter x, y in the optical frame)")
    beam_power: float = Field(0.0, ge=0.0, le=20.0, description="(emitter profile cos^beam_power)")
    # The unit's impulse response beyond the reference pulse (version 2 of the model; absent from older files,
    # whose default adds nothing): the zone histograms after the pulse are convolved with
    # ``delta + sum_k response_kernel[k-1] delta(k)``, k = 1..RESPONSE_LAGS bins, every weight >= 0.
    response_kernel: vector(RESPONSE_LAGS, ge=0.0, le=1.0) = Field(
        default_factory=lambda: [0.0] * RESPONSE_LAGS, description="(of the histogram, at lags 1..RESPONSE_LAGS bins)")
    # Version 3 of the model (absent from older files; every default adds nothing, the model as it was):
    # crosstalk between neighbouring zones by their displacement in the 3x3 grid (GRID_DISPLACEMENTS), the return
    # of the cover glass / package at zero range (per zone, counts) ``glass_delay`` bins after zero range, and the
    # multipath echo (sensor face -> surface -> sensor face -> surface) at twice the range.
    crosstalk_grid: vector(8, ge=0.0, le=0.5) = Field(
        default_factory=lambda: [0.0] * 8, description="(of a neighbouring zone's histogram, by grid displacement)")
    glass_gains: vector(N_ZONES, ge=0.0, le=1e5) = Field(
        default_factory=lambda: [0.0] * N_ZONES, description="counts (per unit-area transient: about the counts at the pulse's peak)")
    glass_delay: float = Field(0.0, ge=-8.0, le=16.0, description="bins (after zero range)")
    echo_gain: float = Field(0.0, ge=0.0, le=1.0, description="(of the direct return, at ECHO_REFERENCE_RANGE)")
    centre_fov_scale: float = Field(1.0, gt=0.0, le=3.0, description="(of the nominal zone rectangle)")
    # Version 4 (absent from older files; the defaults are the model as it was): the echo's falloff with range, the
    # pile-up's shadowing of later bins as a blend, and each zone's pulse width and skew (see the class doc).
    echo_power: float = Field(2.0, ge=0.0, le=4.0, description="(the echo falls as (ECHO_REFERENCE_RANGE / range)^echo_power of the direct return)")
    pileup_shadow: float = Field(1.0, ge=0.0, le=1.0, description="(blend: 1 Coates pile-up, earlier counts shadow later bins; 0 per-bin only)")
    zone_pulse_widths: vector(N_ZONES, ge=-0.25, le=0.25) = Field(
        default_factory=lambda: [0.0] * N_ZONES, description="bins^2 (half the variance added to each zone's pulse)")
    zone_pulse_skews: vector(N_ZONES, ge=-0.25, le=0.25) = Field(
        default_factory=lambda: [0.0] * N_ZONES, description="bins^3 (a sixth of the third moment added to each zone's pulse)")
    # Version 5 (absent from older files; the default is the model as it was): the TDC's differential non-linearity.
    bin_gains: vector(N_BINS, ge=0.5, le=1.5) = Field(
        default_factory=lambda: [1.0] * N_BINS,
        description="(width of each time bin relative to the nominal; multiplies the expected counts of that bin)")
    time_warp: vector(WARP_KNOTS, ge=-4.0, le=4.0) = Field(
        default_factory=lambda: [0.0] * WARP_KNOTS,
        description="bins (where a return appears minus where the linear range law puts it, at bins 0, 8, ..., 128)")
    # Version 6 (absent from older files; the default is the model as it was): each zone's own TDC time scale.
    zone_bin_scales: vector(N_ZONES, ge=0.9, le=1.1) = Field(
        default_factory=lambda: [1.0] * N_ZONES,
        description="(bins of each zone's histogram per nominal bin: multiplies range / bin_size)")
    # Version 7 (absent from older files; the default is the model as it was): the soft binning integrated over each
    # bin (a TDC counts every arrival inside a bin) instead of sampled at its centre. Held, not fitted.
    soft_bin_integrated: float = Field(
        0.0, ge=0.0, le=1.0,
        description="(blend: 0 the Gaussian sampled at bin centres, 1 the Gaussian integrated over each bin)")
    # Version 8 (absent from older files; the default is the model as it was): the quadratic B-spline convolved with
    # the Gaussian as the soft binning's kernel (its sum, centroid and width do not follow the sub-bin position).
    soft_bin_spline: float = Field(
        0.0, ge=0.0, le=1.0,
        description="(0 the Gaussian as soft_bin_integrated says, 1 the quadratic B-spline convolved with it)")
    # Version 9 (absent from older files; the default is the model as it was): the ambient's shape across the bins.
    # Not rendered: the floor subtracted from a frame before it is compared with the model
    # (:func:`~place_safe.sensor.histogram.floor_profile`); measured by calibration, not fitted.
    ambient_slope: float = Field(
        0.0, ge=-0.9, le=0.9,
        description="(the ambient's relative change from the first bin to the last; 0 a flat floor)")

    @model_validator(mode="after")
    def _one_soft_binning(self) -> "ForwardParams":
        if self.soft_bin_spline not in (0.0, 1.0):
            raise ValueError(f"soft_bin_spline must be 0 or 1 (a structural choice), got {self.soft_bin_spline}")
        if self.soft_bin_spline and self.soft_bin_integrated:
            raise ValueError("soft_bin_spline and soft_bin_integrated exclude each other (one soft binning)")
        return self

    def kind_gains(self) -> np.ndarray:
        """Gain of each zone (9,): centre 1, edge/corner gains, times the per-zone gains."""
        base = np.array([1.0, self.edge_gain, self.corner_gain])[ZONE_KIND]
        return base * np.asarray(self.zone_gains, dtype=float)
