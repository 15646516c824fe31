"""How well the released placements of scenario runs read their table's tilt.

    python docs/figures/release_tilt.py r17_old.json r17_new.json ...

For each ``place-safe scenarios --json`` file: the released runs whose reason states the tilt the machine released
on ("level (X deg +- S deg, ..."; older runs "level (X deg, ..."), and the mean, 95th percentile and largest ``|X - true_tilt_deg|`` over them (deg).
docs/results.md, "Zones beside an edge or a box do not tilt the plane".
"""
from __future__ import annotations

import argparse
import json
import re

import numpy as np

_READ = re.compile(r"level \(([-\d.]+) deg")


def tilt_errors(path: str) -> np.ndarray:
    """|read - true| tilt (deg) of the released runs of one scenarios JSON file."""
    data = json.load(open(path))
    rows = data["rows"] if isinstance(data, dict) else data
    out = []
    for row in rows:
        m = _READ.search(row.get("reason") or "")
        if row.get("decision") == "released" and m and row.get("true_tilt_deg") is not None:
            out.append(abs(float(m.group(1)) - float(row["true_tilt_deg"])))
    return np.asarray(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", help="place-safe scenarios --json files")
    for path in ap.parse_args().files:
        e = tilt_errors(path)
        if e.size == 0:
            print(f"{path}: no released run states its tilt")
            continue
        print(f"{path}: {e.size} released, |read - true| mean {e.mean():.3f} p95 {np.quantile(e, 0.95):.3f} "
              f"max {e.max():.3f} deg")


if __name__ == "__main__":
    main()
