"""Calibration files: one JSON file with a section per method family.

Layout::

    {"format": "place_safe.calibration/1",
     "peak":        {...PeakParams...},          # calibrated histogram-peak method
     "proprietary": {...PeakParams...},          # calibrated on-sensor distances
     "forward":     {...ForwardParams...},       # forward model for differentiable rendering
     "diff":        {"range_correction": {...}}, # what diff's solver leaves over (optional)
     "reports":     {"peak": {...}, ...}}        # fit-quality summaries (informational)

``place-safe calibrate --method M -o FILE`` fits one family and writes its section; if FILE already
is a calibration file, its other sections are kept, so one file can carry all methods.
Fitting lives in :mod:`place_safe.calibration.points` (peak and on-sensor distances) and
:mod:`place_safe.calibration.forward_fit` (forward model).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from place_safe.exceptions import CalibrationError
from place_safe.recovery.forward import ForwardParams

FORMAT = "place_safe.calibration/1"
SECTIONS = ("peak", "proprietary", "forward", "diff")


@dataclass
class Calibration:
    """Sections of a calibration file as plain dicts; typed views via :meth:`peak` etc."""

    sections: dict[str, dict] = field(default_factory=dict)
    reports: dict[str, Any] = field(default_factory=dict)

    def peak(self):
        from place_safe.recovery.points import PeakParams
        return PeakParams.from_dict(self.sections["peak"]) if "peak" in self.sections else PeakParams.default_peak()

    def proprietary(self):
        from place_safe.recovery.points import PeakParams
        return (PeakParams.from_dict(self.sections["proprietary"]) if "proprietary" in self.sections
                else PeakParams.default_proprietary())

    def diff(self):
        """The ``diff`` section's range correction (none when the section is absent)."""
        from place_safe.recovery.differentiable import RangeCorrection

        d = self.sections.get("diff", {})
        return RangeCorrection.from_dict(d.get("range_correction", {}))

    def forward(self) -> ForwardParams:
        return ForwardParams.from_dict(self.sections["forward"]) if "forward" in self.sections else ForwardParams()

    def to_dict(self) -> dict:
        out: dict[str, Any] = {"format": FORMAT}
        out.update(self.sections)
        if self.reports:
            out["reports"] = self.reports
        return out

    @classmethod
    def from_dict(cls, d: Any) -> "Calibration":
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            raise CalibrationError(f"not a place_safe calibration (expected \"format\": \"{FORMAT}\")")
        cal = cls({k: d[k] for k in SECTIONS if k in d}, dict(d.get("reports", {})))
        # build every typed view once so a bad file fails here, not mid-run
        for name in cal.sections:
            getattr(cal, name)()
        return cal

    @classmethod
    def load(cls, path: str | Path) -> "Calibration":
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise CalibrationError(f"cannot read calibration {path}: {exc.strerror}") from None
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"calibration {path} is not JSON: {exc.msg} at line {exc.lineno}") from None
        try:
            return cls.from_dict(d)
        except (KeyError, TypeError, ValueError) as exc:
            raise CalibrationError(f"calibration {path} is malformed: {exc}") from None

    def save(self, path: str | Path) -> None:
        Path(path).write_text(json.dumps(self.to_dict(), indent=2) + "\n")


#: Sections a method needs before it may drive a placement (naive methods are uncalibrated by definition).
REQUIRED_SECTIONS = {"diff": ("forward",), "peak": ("peak",), "proprietary": ("proprietary",)}


def uncalibrated_reason(method: str, calibration: "Calibration | None") -> str | None:
    """Why ``method`` with ``calibration`` is not a calibrated sensor (and how to calibrate), or None.

    Placement refuses at once on a reason: built-in constants read a level table as tilted by degrees.
    """
    need = REQUIRED_SECTIONS.get(method)
    fit = method if method in REQUIRED_SECTIONS else method.removesuffix("-naive")
    how = (f"calibrate it first: place-safe calibrate FRAMES.json --method {fit} -o cal.json (frames of a level "
           "table with ground truth), then pass the calibration file")
    if need is None:
        return f"sensor not calibrated: method {method} uses built-in constants; {how}"
    have = calibration.sections if calibration is not None else {}
    missing = [s for s in need if s not in have]
    if missing:
        return f"sensor not calibrated for {method} (no '{missing[0]}' section); {how}"
    return None
