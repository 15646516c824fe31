"""Calibration files: one JSON file with a section per method family.

Layout::

    {"format": "place_safe.calibration/1",
     "peak":        {...PeakParams...},          # calibrated histogram-peak method
     "proprietary": {...PeakParams...},          # calibrated on-sensor distances
     "forward":     {...ForwardParams...},       # forward model for differentiable rendering
     "diff":        {"range_correction": {...},  # what diff's solver leaves over (optional)
                     "window_after_peak": 60},   # the solver's window it was calibrated with (bins)
     "uncertainty": {"peak": {...}, "diff": {...}},  # model-error floors and diff's chi-square limit
     "reference":   {"diff": {"tilt_std": ...}, ...},  # how far each method's frames' truth was off (optional)
     "reports":     {"peak": {...}, ...}}        # fit-quality summaries (informational)

``place-safe calibrate --method M -o FILE`` fits one family and writes its section; if FILE already
is a calibration file, its other sections are kept, so one file can carry all methods.
Fitting lives in :mod:`place_safe.calibration.points` (peak and on-sensor distances),
:mod:`place_safe.calibration.forward_fit` (forward model), :mod:`place_safe.calibration.second_fit` (its second reading
of the geometry), :mod:`place_safe.calibration.model_error` and :mod:`place_safe.calibration.plane_correction` (diff's
residual weighting and plane correction).
"""

from __future__ import annotations

import copy
from dataclasses import InitVar, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from place_safe.config import read_json, write_json
from place_safe.exceptions import ArgumentTypeError, CalibrationError
from place_safe.recovery.estimator import Reference, Uncertainty

if TYPE_CHECKING:  # imported when a section is read: the forward model and diff load torch, the peak
    # mapping scipy, and a command's parser and --help need neither
    from place_safe.recovery.forward_params import ForwardParams
    from place_safe.recovery.points import PeakParams

FORMAT = "place_safe.calibration/1"
SECTIONS = ("peak", "proprietary", "forward", "diff", "uncertainty", "reference")


#: Keys a calibration file may have besides its sections.
OTHER_KEYS = ("format", "reports")


@dataclass
class Calibration:
    """Sections of a calibration file as plain dicts; typed views via :meth:`peak` etc.

    Each section is validated on its own when the file is read (:meth:`from_dict`): a bad section is
    remembered in ``errors`` and raises a one-line :class:`CalibrationError` (naming the file, the
    section and the field) only when a method that needs it asks for it, so a broken ``diff``
    section does not stop the ``peak`` method. The file itself must carry the format tag and no
    unknown top-level keys.

    Built directly (``Calibration({"peak": {...}})``, a task script's way), every section is checked at
    once: ``sections`` must be a dict of known section names to parameter dicts, and an invalid section
    raises :class:`CalibrationError` (``Calibration({"peak": "garbage"})`` is refused). Only
    :meth:`from_dict` / :meth:`load` keep a bad section in ``errors`` (``lenient``) for the reason above.
    """

    sections: dict[str, dict] = field(default_factory=dict)
    reports: dict[str, Any] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)
    source: str = "calibration"
    lenient: InitVar[bool] = False

    def __post_init__(self, lenient: bool) -> None:
        if not isinstance(self.sections, dict):
            raise ArgumentTypeError(f"Calibration: sections must be a dict of section name -> parameter dict "
                                    f"(some of {', '.join(SECTIONS)}), got {type(self.sections).__name__}; "
                                    "read a file with Calibration.load(path)")
        unknown = sorted(str(k) for k in self.sections if k not in SECTIONS)
        if unknown:
            raise CalibrationError(f"Calibration: unknown sections {unknown}; expected some of {list(SECTIONS)}")
        if not isinstance(self.reports, dict) or not isinstance(self.errors, dict) or not isinstance(self.source, str):
            raise ArgumentTypeError("Calibration: reports and errors must be dicts and source a str")
        # validate every section once, on its own, so a bad one fails clearly and only for its methods
        for name in list(self.sections):
            if name in self.errors:
                continue
            if not isinstance(self.sections[name], dict):  # null or a list would read as "no section": built-in constants
                self.errors[name] = f"must be an object of parameters, got {type(self.sections[name]).__name__}"
                continue
            try:
                getattr(self, name)()
            except CalibrationError as exc:
                self.errors[name] = str(exc)
        if self.errors and not lenient:
            self.check()

    def check(self) -> "Calibration":
        """Raise :class:`CalibrationError` (one line, the first invalid section) unless every section is valid.

        Commands that drive a robot (``place``, ``scenarios``, ``calibrate-mount``) call it: a
        file with a broken section (a NaN, a wrong type) is refused before anything moves."""
        for name in sorted(self.errors):
            raise CalibrationError(f"{self.source}: section '{name}': {self.errors[name]}")
        return self

    def _section(self, name: str):
        if name in self.errors:
            raise CalibrationError(f"{self.source}: section '{name}': {self.errors[name]}")
        return self.sections.get(name)

    def peak(self) -> PeakParams:
        from place_safe.recovery.points import PeakParams

        d = self._section("peak")
        return PeakParams.from_dict(d) if d is not None else PeakParams.default_peak()

    def proprietary(self) -> PeakParams:
        from place_safe.recovery.points import PeakParams

        d = self._section("proprietary")
        return PeakParams.from_dict(d) if d is not None else PeakParams.default_proprietary()

    def diff(self):
        """The ``diff`` section's range correction (none when the section is absent)."""
        from place_safe.recovery.diff_settings import RangeCorrection

        d = self._section("diff")
        if d is None:
            return RangeCorrection()
        if not isinstance(d, dict) or set(d) - {"range_correction", "window_after_peak", "ambient", "crosstalk_std"}:
            raise CalibrationError("diff section must be an object with only 'range_correction', "
                                   "'window_after_peak', 'ambient' and 'crosstalk_std'")
        self.diff_options()  # validated with the section
        return RangeCorrection.from_dict(d.get("range_correction", {}))

    def diff_options(self):
        """The diff solver's options this calibration was made with: its window after the peak (bins), the
        one its chi-square limit and covariance scale hold for. A file without it predates the key and
        was calibrated with :data:`~place_safe.recovery.diff_settings.LEGACY_WINDOW_AFTER_PEAK`; without a
        ``diff`` section the solver's default is used. ``ambient`` (true or false, absent: false): the forward
        model was fitted with the ambient as it arrives through the pile-up (``calibrate --unit-model staged``),
        and the solver compares it with the data so (:attr:`~place_safe.recovery.differentiable.SolverOptions.ambient`).
        ``crosstalk_std`` (a fraction, 0 or 1e-6..0.5, absent: 0): each frame's crosstalk is solved under a prior of that
        standard deviation about the forward model's (a level sweep left it undetermined); 0 holds it."""
        from place_safe.recovery.diff_settings import LEGACY_WINDOW_AFTER_PEAK, SolverOptions, crosstalk_std_problem

        d = self._section("diff")
        if d is None:
            return SolverOptions()
        w = d.get("window_after_peak", LEGACY_WINDOW_AFTER_PEAK) if isinstance(d, dict) else None
        if isinstance(w, bool) or not isinstance(w, int) or not 1 <= w <= 128:
            raise CalibrationError(f"diff section: window_after_peak must be a whole number of bins in 1..128, "
                                   f"got {w!r}")
        ambient = d.get("ambient", False)
        if not isinstance(ambient, bool):
            raise CalibrationError(f"diff section: ambient must be true or false, got {ambient!r}")
        xt = d.get("crosstalk_std", 0.0)
        if (why := crosstalk_std_problem(xt)) is not None:
            raise CalibrationError(f"diff section: {why}")
        return SolverOptions(window_after_peak=w, ambient=ambient, crosstalk_std=float(xt))

    def uncertainty(self, method: str | None = None):
        """The :class:`~place_safe.recovery.estimator.Uncertainty` of ``method`` (defaults when absent);
        without a method, all entries of the section as a dict. An entry that states no model-error floor at all
        (:meth:`~place_safe.recovery.estimator.Uncertainty.states_no_floor`: a calibration always fits some) is refused,
        as is a ``scale`` below :data:`~place_safe.recovery.estimator.MIN_SCALE`: either makes every plane of the method
        more certain than its calibration frames showed, and placement's rules trust these covariances."""
        sec = self._section("uncertainty") or {}
        if (bad := next((k for k in sec if k not in REQUIRED_SECTIONS), None)) is not None:
            raise CalibrationError(f"uncertainty section: {str(bad)[:40]!r} is not a method family; expected some of "
                                   f"{', '.join(REQUIRED_SECTIONS)}")
        try:
            if method is None:
                return {k: _entry(v, k) for k, v in sec.items()}
            return _entry(sec[method], method) if method in sec else Uncertainty()
        except (TypeError, ValueError, AttributeError, OverflowError) as exc:
            raise CalibrationError(str(exc)) from None

    def reference(self, method: str | None = None):
        """How far the ground truth ``method``'s sections were fitted to was off
        (:class:`~place_safe.recovery.estimator.Reference`; exact when the section or its entry is absent). ``diff``
        starts from and blends with peak's plane: its reference is the larger of its own and peak's. Without a
        method, every entry of the section as a dict."""
        sec = self._section("reference") or {}
        if (bad := next((k for k in sec if k not in REQUIRED_SECTIONS), None)) is not None:
            raise CalibrationError(f"reference section: {str(bad)[:40]!r} is not a method family; expected some of "
                                   f"{', '.join(REQUIRED_SECTIONS)}")
        entries = {k: Reference.from_dict(v, f"reference.{k}") for k, v in sec.items()}
        if method is None:
            return entries
        own = entries.get(method, Reference())
        if method == "diff" and entries.get("peak", own).tilt_std > own.tilt_std:
            return entries["peak"]
        return own

    def without_fallback(self) -> "Calibration":
        """A copy whose ``diff`` uncertainty never falls back to peak's plane
        (:meth:`~place_safe.recovery.estimator.Uncertainty.without_fallback`): diff's own plane on every frame it
        solves, the way docs/results.md measures it; every other section and the reports as they are."""
        d = copy.deepcopy(self.to_dict())
        unc = d.setdefault("uncertainty", {})
        if "diff" in unc:  # (without an entry diff has its defaults, which never fall back)
            unc["diff"] = self.uncertainty("diff").without_fallback().to_dict()
        return Calibration.from_dict(d, f"{self.source} without diff's fallback")

    def forward(self) -> ForwardParams:
        from place_safe.recovery.forward_params import ForwardParams

        d = self._section("forward")
        return ForwardParams.from_dict(d) if d is not None else ForwardParams()

    def to_dict(self) -> dict:
        out: dict[str, Any] = {"format": FORMAT}
        out.update(self.sections)
        if self.reports:
            out["reports"] = self.reports
        return out

    @classmethod
    def from_dict(cls, d: Any, source: str = "calibration") -> "Calibration":
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise CalibrationError(f"{source}: not a place_safe calibration (expected \"format\": \"{FORMAT}\")")
        unknown = sorted(set(d) - set(SECTIONS) - set(OTHER_KEYS))
        if unknown:
            raise CalibrationError(f"{source}: unknown keys {unknown}; expected some of "
                                   f"{sorted(SECTIONS + OTHER_KEYS)}")
        reports = d.get("reports", {})
        return cls({k: d[k] for k in SECTIONS if k in d}, dict(reports) if isinstance(reports, dict) else {},
                   source=source, lenient=True)  # sections validated one by one (see the class docstring)

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        return cls.from_dict(read_json(path, "calibration", CalibrationError), f"calibration {path}")

    def save(self, path: str | Path) -> None:
        write_json(path, self.to_dict())


def _entry(d: Any, method: Any) -> Uncertainty:
    """The ``uncertainty`` section's entry ``d`` for ``method``, refused when it states no floor (see
    :meth:`Calibration.uncertainty`)."""
    unc = Uncertainty.from_dict(d, f"uncertainty.{method}")
    if unc.states_no_floor():
        how = (f"calibrate {method} again (place-safe calibrate FRAMES --method {method} -o CAL) or remove the entry"
               if method in REQUIRED_SECTIONS else "remove the entry")
        raise CalibrationError(f"uncertainty.{method}: states no model error ({', '.join(Uncertainty.FLOOR_TERMS)} "
                               f"all 0), which no calibration fits; {how}")
    return unc


#: Sections a method needs before it may drive a placement (naive methods are uncalibrated by definition).
REQUIRED_SECTIONS = {"diff": ("forward", "peak"), "peak": ("peak",), "proprietary": ("proprietary",)}
# (diff starts from the calibrated peak method and falls back to its plane: with a forward section but no peak one it
# returned peak's planes from built-in constants, 14-16 deg off on a simulated unit, unmarked)

#: The ``uncertainty`` entries a method's estimates read: diff's own, and peak's for the plane it starts from and falls
#: back to. Without them an estimate carries the built-in :class:`~place_safe.recovery.estimator.Uncertainty`: no
#: model-error floor (its covariance the fit's alone) and, for diff, no fallback to peak.
REQUIRED_UNCERTAINTY = {"diff": ("diff", "peak"), "peak": ("peak",)}

#: The diff method's forward-model fits (``calibrate --unit-model``): ``default`` is
#: :func:`~place_safe.calibration.forward_fit.fit_forward` with its default terms, ``staged`` is
#: :func:`~place_safe.calibration.forward_fit.fit_forward_staged` (the learned unit model in three fits).
UNIT_MODELS = ("default", "staged")


UNCALIBRATED_MARK = "[uncalibrated]"
"""The marker every output row of an uncalibrated run carries (JSON records carry ``"calibrated": false``)."""


def mark(text: str, calibrated: bool) -> str:
    """An output row ``text`` as printed: with :data:`UNCALIBRATED_MARK` after two spaces unless ``calibrated``."""
    return text if calibrated else f"{text}  {UNCALIBRATED_MARK}"


def uncalibrated_reason(method: str, calibration: "Calibration | None") -> str | None:
    """Why ``method`` with ``calibration`` is not a calibrated sensor (and how to calibrate), or None.

    Placement refuses at once on a reason: built-in constants read a level table as tilted by degrees. A naive method
    (``peak-naive``, ``proprietary-naive``) takes no calibration: its reason is always given, and names the method to
    calibrate instead.
    """
    need = REQUIRED_SECTIONS.get(method)
    fit = method if method in REQUIRED_SECTIONS else method.removesuffix("-naive")
    how = (f"calibrate it first: place-safe calibrate FRAMES.json --method {fit} -o cal.json (frames of a level "
           "table with ground truth), then pass the calibration file")
    if need is None:  # no calibration is ever its: advising one (then "pass the calibration file") sent users in circles
        return (f"sensor not calibrated: method {method} is a baseline on built-in constants that takes no calibration, "
                f"so a placement refuses it by design; use {fit} ({how.replace('then pass', 'and pass')})")
    if (missing := missing_section(method, calibration)) is not None:
        return f"sensor not calibrated for {method} (no '{missing}' section); {how}"
    return None


def placement_reason(method: str, calibration: "Calibration | None") -> str | None:
    """Why a placement refuses ``method`` with ``calibration`` before anything moves, or None: :func:`uncalibrated_reason`,
    or a calibration whose ``uncertainty`` section lacks an entry the method reads (:data:`REQUIRED_UNCERTAINTY`): its
    planes are calibrated, but their covariances would be the fits' alone, with no model-error floor, and diff would
    never fall back to peak, so the release rule would trust each plane beyond what the sensor measures (every file
    ``calibrate`` writes has the entries: one without them was cut or written by hand)."""
    if (why := uncalibrated_reason(method, calibration)) is not None:
        return why
    if not (missing := missing_uncertainty(method, calibration)):
        return None
    return (f"sensor's uncertainty not calibrated for {method} (no {' or '.join(repr(m) for m in missing)} entry): its "
            f"planes would state the fit's covariance alone{' and never fall back to peak' if method == 'diff' else ''}; "
            f"calibrate it again: place-safe calibrate FRAMES.json --method {method} -o cal.json")


def missing_uncertainty(method: str, calibration: "Calibration | None") -> list[str]:
    """The entries of the ``uncertainty`` section that ``method`` reads (:data:`REQUIRED_UNCERTAINTY`) and
    ``calibration`` lacks, as ``"uncertainty.diff"`` etc. (all of them without a calibration)."""
    have = calibration.sections.get("uncertainty") if calibration is not None else None
    have = have if isinstance(have, dict) else {}
    return [f"uncertainty.{m}" for m in REQUIRED_UNCERTAINTY.get(method, ()) if not isinstance(have.get(m), dict)]


def missing_section(method: str, calibration: "Calibration | None") -> str | None:
    """The first section of :data:`REQUIRED_SECTIONS` for ``method`` that ``calibration`` lacks, or None (all there,
    or a method that takes no calibration)."""
    have = calibration.sections if calibration is not None else {}
    return next((s for s in REQUIRED_SECTIONS.get(method, ()) if not isinstance(have.get(s), dict)), None)
