"""What every estimate must be, whatever went in: no plane with a reason, or a finite plane in front of the
sensor (unit normal, ``n_z > 0``, ``offset > 0``) with a finite albedo or none."""
from __future__ import annotations

import math

import numpy as np


def assert_safe(est) -> None:
    """No plane with a reason, or a finite plane in front of the sensor; a finite albedo or none."""
    if est.plane is None:
        assert isinstance(est.reason, str) and est.reason
        return
    n, d = np.asarray(est.plane.normal), est.plane.offset
    assert np.all(np.isfinite(n)) and math.isfinite(d)
    assert d > 0 and n[2] > 0 and abs(np.linalg.norm(n) - 1) < 1e-9
    assert est.albedo is None or math.isfinite(est.albedo)
