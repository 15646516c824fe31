"""Scenario regression runs: random scenes, judging each run by simulation truth, summary figures.

Concept: a *run* is one :class:`~place_safe.sim.scenario.Scenario` through
:func:`place_safe.sim.placement_run.run_placement` (the same :class:`~place_safe.placement.loop.PlacementLoop`
a task script uses). :func:`judge` turns its result into one flat row (the per-run fields of issue 12)
and says whether the run met the scenario's expectation and whether it was an *unsafe release* or a
*false refusal*. :func:`random_scenario` draws scenes like a tester would (tilt, start height,
material, table edge or clutter near or under the cup, sensor faults, both simulated sensors) and
labels each with what a correct placement must do from the scene's geometry. :func:`run_many`
runs rows serially, in local processes (``jobs``) or on a Ray cluster (``ray_address``).

Definitions (SI units in rows; degrees / millimetres only in :func:`format_table`):

* **unsafe release**: released and any of: true tilt above the limit (``max_tilt``), cup bottom more
  than ``max_release_height`` (10 mm) above the surface it would land on when the gripper opened (the
  table, or clutter under its footprint where higher: a board, a tray), the cup ended tipped (> 10 deg)
  or standing neither on the table nor on that clutter (bottom > 5 mm off), liquid spilled, or the scene
  was labelled *unsupported* (edge or clutter under the cup's footprint).
* **clearly safe** scene: true tilt <= limit - 1 deg, nothing within the footprint plus 30 mm, no
  injected fault, start height >= 8 cm; a refusal there is a **false refusal**.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from place_safe.sim.scenario import (Expectation, ON_TABLE_TOL, REFERENCE_HEIGHT, Scenario, TIPPED_TILT,
                                     home_cup_position, load_scenario)
from place_safe.exceptions import PlaceSafeError
from place_safe.placement.config import PlacementConfig
from place_safe.sim.scene import SceneConfig
from place_safe.sim.placement_run import run_placement
from place_safe.placement.loop import within_robot_limits
from place_safe.sim.robot import sim_limits
from place_safe.sim.tof import ToFConfig

#: N: a contact at least this hard counts as a collision in the summary (half the robot's 60 N protective stop;
#: arrival on the surface stays under about 15 N).
HARD_CONTACT = 30.0
#: m beyond the cup's footprint that must be clear for a scene to count as clearly safe.
CLEAR_MARGIN = 0.03
#: rad below the tilt limit for a scene to count as clearly safe.
TILT_MARGIN = math.radians(1.0)


# ---------------------------------------------------------------------------------------------
# random scenes
# ---------------------------------------------------------------------------------------------
def _random_material(rng: np.random.Generator) -> tuple[dict[str, Any], str]:
    """A table material as a tester draws it (albedo, and uniform, glossy or checker) and its kind."""
    mat: dict[str, Any] = {"albedo": float(rng.choice([0.15, 0.4, 1.0, 1.0, 1.6]))}
    kind = str(rng.choice(["uniform", "uniform", "glossy", "checker"]))
    if kind == "glossy":
        mat.update(specular_weight=float(rng.uniform(0.5, 1.5)), specular_exponent=float(rng.uniform(10, 40)))
    elif kind == "checker":
        mat.update(pattern="checker", square=float(rng.uniform(0.02, 0.06)), albedo2=float(rng.uniform(0.1, 0.5)))
    return mat, kind


def _random_sensor(rng: np.random.Generator) -> dict[str, Any]:
    """Either simulated sensor with its own noise seed; a mismatched one on for a while (calibrated warm, at 45 degC),
    still warming a little."""
    sensor: dict[str, Any] = {"model": str(rng.choice(["nominal", "mismatch"])), "seed": int(rng.integers(1 << 30))}
    if sensor["model"] == "mismatch":
        sensor["mismatch"] = {"temp_start": float(rng.uniform(40.0, 45.0))}
    return sensor


def random_scenario(rng: np.random.Generator, index: int = 0, calibration: str = "sim") -> Scenario:
    """One random scene (see module docstring); ``expect`` and ``labels`` come from its geometry."""
    pc = PlacementConfig()
    base = SceneConfig()
    cup = home_cup_position(base)
    radius = pc.cup_radius
    tilt = math.radians(rng.uniform(0.0, 15.0))
    direction = rng.uniform(-math.pi, math.pi)
    start = 0.40 if rng.random() < 0.3 else rng.uniform(0.10, 0.40)  # enough starts at 40 cm for the time figure
    mat, kind = _random_material(rng)
    table: dict[str, Any] = {"tilt": tilt, "tilt_direction": direction, "material": mat,
                             "center": [float(base.table.center[0]), float(base.table.center[1])]}
    scene: dict[str, Any] = {"table": table, "start_height": start}
    support = "full"
    clearance_to_hazard = math.inf  # m from the footprint's rim to the nearest edge/clutter
    hazard = rng.choice(["none", "none", "edge", "clutter"])
    if hazard == "edge":
        e = float(rng.uniform(-0.06, 0.12))  # cup centre this far inside the edge (negative: beyond it)
        side = int(rng.integers(4))
        half = (base.table.size[0] / 2, base.table.size[1] / 2)
        c = list(table["center"])
        if side == 0:  # the edge between the cup and the robot: a table half as deep, so it stays clear of the arm
            table["size"] = [base.table.size[0] / 2, base.table.size[1], base.table.size[2]]
            c[0] = float(cup[0] - e + half[0] / 2)
        elif side == 1:
            c[0] = float(cup[0] + e - half[0])
        elif side == 2:
            c[1] = float(cup[1] - e + half[1])
        else:
            c[1] = float(cup[1] + e - half[1])
        table["center"] = c
        clearance_to_hazard = e - radius
        support = "edge" if e < radius else "full"
    elif hazard == "clutter":
        table["tilt"] = 0.0
        tilt = 0.0
        hz = float(rng.uniform(0.005, 0.02))  # half height
        hx, hy = float(rng.uniform(0.015, 0.04)), float(rng.uniform(0.015, 0.04))
        r = float(rng.uniform(0.0, 0.12))
        a = float(rng.uniform(-math.pi, math.pi))
        px, py = float(cup[0] + r * math.cos(a)), float(cup[1] + r * math.sin(a))
        top = float(cup[2] - start)
        scene["clutter"] = [{"shape": "box", "pos": [px, py, top + hz], "size": [hx, hy, hz],
                             "material": {"albedo": float(rng.uniform(0.3, 1.2))}}]
        dx, dy = max(abs(px - cup[0]) - hx, 0.0), max(abs(py - cup[1]) - hy, 0.0)
        clearance_to_hazard = math.hypot(dx, dy) - radius
        support = "clutter" if clearance_to_hazard < 0 else "full"
    sensor = _random_sensor(rng)
    if rng.random() < 0.3:
        sensor.update(drop_prob=float(rng.uniform(0, 0.15)), corrupt_prob=float(rng.uniform(0, 0.05)))
    if rng.random() < 0.2:
        sensor["spike_prob"] = float(rng.uniform(0, 0.05))
    if rng.random() < 0.2:
        sensor["ambient_range"] = [400.0, 1500.0]  # strong ambient light
    unsafe = tilt > pc.max_tilt or support != "full"
    clearly_safe = (tilt <= pc.max_tilt - TILT_MARGIN and clearance_to_hazard >= CLEAR_MARGIN and start >= 0.08)
    outcome = "refused" if unsafe else ("released" if clearly_safe else "any")
    desc = (f"random #{index}: tilt {math.degrees(tilt):.1f} deg towards {math.degrees(direction):.0f} deg, "
            f"start {start * 100:.0f} cm, {kind} albedo {mat['albedo']}, hazard {hazard}"
            + (f" ({clearance_to_hazard * 1e3:.0f} mm from the footprint)" if hazard != "none" else "")
            + f", sensor {sensor['model']}")
    return Scenario(name=f"random_{index:04d}", description=desc, scene=scene, sensor=sensor,
                    calibration=calibration, expect=Expectation(outcome=outcome),
                    labels={"support": support, "clearly_safe": bool(clearly_safe), "hazard": str(hazard),
                            "hazard_clearance": None if math.isinf(clearance_to_hazard) else clearance_to_hazard})


def _level_table(rng: np.random.Generator) -> tuple[np.ndarray, float, dict[str, Any], str, dict[str, Any]]:
    """The start of a scene on a level table of any material: (the cup's home position, its start height 10-40 cm
    above the table, the material, its kind, the scene's ``table`` section). Draws the start, then the material."""
    base = SceneConfig()
    start = float(rng.uniform(0.10, 0.40))
    mat, kind = _random_material(rng)
    table: dict[str, Any] = {"tilt": 0.0, "tilt_direction": 0.0, "material": mat,
                             "center": [float(base.table.center[0]), float(base.table.center[1])]}
    return home_cup_position(base), start, mat, kind, table


def _random_box(rng: np.random.Generator, half_height: tuple[float, float], reach: tuple[float, float]
                ) -> tuple[dict[str, Any], dict[str, Any]]:
    """A level table with one axis-aligned box (``half_height`` m drawn from the range, 30-80 mm across) whose near
    face (or corner, along a diagonal) lies about ``reach`` m (drawn from the range) from the cup's centre, the cup
    10-40 cm up, either simulated sensor: (the scene, its geometry: ``start``, ``kind`` (the table's material),
    ``height``, ``size`` (x, y), ``direction`` (rad), ``reach_in`` (m from the cup's centre to the box's nearest
    point), ``clearance`` (``reach_in`` less the cup's radius: negative under the footprint), ``support``
    (``clutter`` under the footprint, else ``full``), ``tilt`` (rad: the cup released on the box pivots on its edge
    until its far rim meets the table, ``atan(h / (r + reach_in))``; 0 outside the footprint), ``sensor``)."""
    pc = PlacementConfig()
    cup, start, mat, kind, table = _level_table(rng)
    hz = float(rng.uniform(*half_height))
    hx, hy = float(rng.uniform(0.015, 0.04)), float(rng.uniform(0.015, 0.04))
    a = float(rng.uniform(-math.pi, math.pi))
    near = float(rng.uniform(*reach))  # m from the cup's centre to the box's near side, along a
    ux, uy = math.cos(a), math.sin(a)
    px = cup[0] + ux * near + (math.copysign(hx, ux) if abs(ux) > 0.38 else 0.0)
    py = cup[1] + uy * near + (math.copysign(hy, uy) if abs(uy) > 0.38 else 0.0)
    top = float(cup[2] - start)
    scene: dict[str, Any] = {"table": table, "start_height": start,
                             "clutter": [{"shape": "box", "pos": [float(px), float(py), top + hz], "size": [hx, hy, hz],
                                          "material": {"albedo": float(rng.uniform(0.3, 1.2))}}]}
    dx, dy = max(abs(px - cup[0]) - hx, 0.0), max(abs(py - cup[1]) - hy, 0.0)
    reach_in = math.hypot(dx, dy)
    under = reach_in < pc.cup_radius
    geometry = {"start": start, "kind": kind, "albedo": mat["albedo"], "height": 2.0 * hz, "size": (2 * hx, 2 * hy),
                "direction": a, "reach_in": reach_in, "clearance": reach_in - pc.cup_radius,
                "support": "clutter" if under else "full",
                "tilt": math.atan(2.0 * hz / (pc.cup_radius + reach_in)) if under else 0.0,
                "sensor": _random_sensor(rng)}
    return scene, geometry


def _box_description(label: str, index: int, g: dict[str, Any]) -> str:
    return (f"random {label} #{index}: {g['height'] * 1e3:.1f} mm tall, {g['size'][0] * 1e3:.0f} x "
            f"{g['size'][1] * 1e3:.0f} mm, {g['clearance'] * 1e3:.0f} mm from the footprint towards "
            f"{math.degrees(g['direction']):.0f} deg, start {g['start'] * 100:.0f} cm, {g['kind']} albedo "
            f"{g['albedo']}, sensor {g['sensor']['model']}")


def random_low_box_scenario(rng: np.random.Generator, index: int = 0, calibration: str = "sim") -> Scenario:
    """One random scene of a low box (4-12 mm tall, 30-80 mm across) at or under the cup's footprint on a level
    table, the cup 10-40 cm up: what no footprint view tells from the table (a box this low under part of a zone moves
    its point by a fraction of its height), so only the touch can. The box's nearest point lies from 15 mm off the
    cup's centre (or over it, at a diagonal) to 10 mm past its rim. ``labels``: ``support`` is ``clutter`` when the box
    reaches under the footprint (any release there is judged unsafe), ``box_height`` its height (m), and
    ``tilt_if_released`` the tilt (rad) the cup is left at, pivoting on the box's edge ``e`` from its centre until its
    far rim meets the table: ``atan(h / (r + e))`` (0 outside the footprint; over the centre, the worst case
    ``atan(h / r)``). Scenes whose cup would be left beyond ``max_tilt`` must be refused."""
    pc = PlacementConfig()
    scene, g = _random_box(rng, (0.002, 0.006), (0.015, pc.cup_radius + 0.01))
    outcome = "refused" if g["tilt"] > pc.max_tilt else "any"
    return Scenario(name=f"low_box_{index:04d}", description=_box_description("low box", index, g), scene=scene,
                    sensor=g["sensor"], calibration=calibration, expect=Expectation(outcome=outcome),
                    labels={"support": g["support"], "clearly_safe": False, "hazard": "low box",
                            "hazard_clearance": g["clearance"], "box_height": g["height"],
                            "tilt_if_released": g["tilt"]})


def random_rim_box_scenario(rng: np.random.Generator, index: int = 0, calibration: str = "sim") -> Scenario:
    """One random scene of a box 7-30 mm tall (30-80 mm across) near the cup's rim on a level table, the cup 10-40 cm
    up: its nearest point from 10 mm inside the rim to 40 mm past it. What the footprint rule decides: a box under
    the rim leaves the cup tilted beyond ``max_tilt`` (``atan(h / (r + e))`` >= 5.7 deg) and must be refused; one at
    least ``CLEAR_MARGIN`` (30 mm) past the rim is clearly safe and must be released; between the two, either answer.
    The zones over the footprint's rim reach 3-5 cm past it from the survey heights, so a box there raises them as a
    box at the rim does. ``labels`` as :func:`random_low_box_scenario`'s."""
    pc = PlacementConfig()
    scene, g = _random_box(rng, (0.0035, 0.015), (pc.cup_radius - 0.01, pc.cup_radius + 0.04))
    clearly_safe = g["support"] == "full" and g["clearance"] >= CLEAR_MARGIN and g["start"] >= 0.08
    outcome = "refused" if g["tilt"] > pc.max_tilt else ("released" if clearly_safe else "any")
    return Scenario(name=f"rim_box_{index:04d}", description=_box_description("rim box", index, g), scene=scene,
                    sensor=g["sensor"], calibration=calibration, expect=Expectation(outcome=outcome),
                    labels={"support": g["support"], "clearly_safe": bool(clearly_safe), "hazard": "clutter",
                            "hazard_clearance": g["clearance"], "box_height": g["height"],
                            "tilt_if_released": g["tilt"]})


def random_board_scenario(rng: np.random.Generator, index: int = 0, calibration: str = "sim") -> Scenario:
    """One random scene of the cup put down on a board (a cutting board, a tray, a book: 5-25 mm thick, 200-300 mm
    square, turned to face any direction) on a level table of any material, the cup 10-40 cm up, either simulated
    sensor. The cup's centre lies 20-150 mm inside the board's edge, the rest of its surroundings on the board. Wholly
    on the board with ``CLEAR_MARGIN`` (30 mm) to spare past its rim it is clearly safe and must be released (onto the
    board: the judge measures the fall to it); over the edge (the footprint past it) it must be refused, as a table's
    edge under the cup; between, either. The sensor, 70 mm beside the cup, often looks at the edge: a step that a
    3 x 3 grid's plane through two rows of zones reads as a slope. ``labels``: ``support`` (``full`` or ``edge``),
    ``hazard_clearance`` (m from the footprint's rim to the edge), ``board_height`` (m)."""
    pc = PlacementConfig()
    cup, start, mat, kind, table = _level_table(rng)
    h = float(rng.uniform(0.005, 0.025))
    half = float(rng.uniform(0.10, 0.15))
    a = float(rng.uniform(-math.pi, math.pi))  # the board's edge faces this way from the cup
    e = float(rng.uniform(0.02, 0.15))  # m from the cup's centre to that edge
    top = float(cup[2] - start)
    centre = [float(cup[0] + math.cos(a) * (e - half)), float(cup[1] + math.sin(a) * (e - half)), top + h / 2]
    board = {"shape": "box", "pos": centre, "size": [half, half, h / 2], "euler": [0.0, 0.0, a],
             "material": {"albedo": float(rng.uniform(0.3, 1.2))}}
    sensor = _random_sensor(rng)
    clearance = e - pc.cup_radius
    support = "edge" if clearance < 0 else "full"
    clearly_safe = clearance >= CLEAR_MARGIN and start >= 0.08
    outcome = "refused" if support != "full" else ("released" if clearly_safe else "any")
    desc = (f"random board #{index}: {h * 1e3:.1f} mm thick, {2 * half * 1e3:.0f} mm square, its edge {e * 1e3:.0f} mm "
            f"from the cup's centre ({clearance * 1e3:.0f} mm past the rim) towards {math.degrees(a):.0f} deg, start "
            f"{start * 100:.0f} cm, {kind} table albedo {mat['albedo']}, sensor {sensor['model']}")
    return Scenario(name=f"board_{index:04d}", description=desc,
                    scene={"table": table, "start_height": start, "clutter": [board]}, sensor=sensor,
                    calibration=calibration, expect=Expectation(outcome=outcome),
                    labels={"support": support, "clearly_safe": bool(clearly_safe), "hazard": "board edge",
                            "hazard_clearance": clearance, "board_height": h})


#: The kinds of random scenes ``place-safe scenarios --random N --kind K`` draws.
RANDOM_KINDS = {"tables": random_scenario, "low-boxes": random_low_box_scenario, "rim-boxes": random_rim_box_scenario,
                "boards": random_board_scenario}


# ---------------------------------------------------------------------------------------------
# judging
# ---------------------------------------------------------------------------------------------
def judge(sc: Scenario, res: Any, max_tilt: float | None = None) -> dict:
    """One flat row for a run: the issue's per-run fields, safety verdicts and whether it met ``sc.expect``."""
    if max_tilt is None:
        max_tilt = sc.placement_config().max_tilt
    exp = sc.expect or Expectation(outcome="any")
    labels = sc.labels or {}
    released = res.outcome == "released"
    upright = bool(res.cup_tilt <= TIPPED_TILT)
    # standing on the table, or on clutter under it (a board, a tray): the support is what it would land on
    support = getattr(res, "support_height", math.nan)
    on_table = bool(abs(res.cup_height) <= ON_TABLE_TOL or abs(support) <= ON_TABLE_TOL)
    rh = res.release_height
    problems = []
    if released:
        if res.true_tilt > max_tilt:
            problems.append(f"surface tilted {math.degrees(res.true_tilt):.1f} deg")
        if not (rh <= exp.max_release_height):
            problems.append(f"released {rh * 1e3:.1f} mm above the surface")
        if not upright:
            problems.append(f"cup tipped ({math.degrees(res.cup_tilt):.0f} deg)")
        if not on_table:
            problems.append(f"cup not on the table ({res.cup_height * 1e3:.0f} mm off)" if not math.isfinite(support)
                            or support >= res.cup_height else
                            f"cup not on the table nor on the clutter under it ({support * 1e3:.0f} mm off)")
        if res.liquid_spilled > exp.max_spilled:
            problems.append(f"{res.liquid_spilled} liquid spheres spilled")
        if labels.get("support", "full") != "full":
            problems.append(f"released over {labels['support']}")
    unsafe = bool(released and problems)
    misses = list(problems)
    if exp.outcome != "any" and res.outcome != exp.outcome:
        misses.insert(0, f"expected {exp.outcome}, got {res.outcome}")
    if exp.outcome == "refused" and res.outcome == "refused" and exp.reason:
        if not any(w.lower() in res.reason.lower() for w in exp.reason):
            misses.append(f"reason does not mention {' / '.join(exp.reason)}")
    if exp.max_decision_time is not None and not (res.decision_time is not None
                                                  and res.decision_time <= exp.max_decision_time):
        misses.append(f"decision time {res.decision_time} s > {exp.max_decision_time} s")
    force = float(res.contact_force_peak or 0.0)
    if exp.max_contact_force is not None and not force < exp.max_contact_force:
        misses.append(f"contact {force:.1f} N >= {exp.max_contact_force:.0f} N")
    clearly_safe = bool(labels.get("clearly_safe", exp.outcome == "released"))
    return {
        "name": res.scenario, "description": sc.description, "sensor": res.sensor, "method": res.method,
        "calibration": res.calibration, "true_tilt_deg": math.degrees(res.true_tilt),
        "surface_height": res.surface_height, "start_height": res.start_height, "decision": res.outcome,
        "release_height": None if math.isnan(rh) else rh, "cup_upright": upright, "on_table": on_table,
        "liquid_spilled": int(res.liquid_spilled), "decision_time": res.decision_time,
        "time_from": REFERENCE_HEIGHT if res.start_height >= REFERENCE_HEIGHT - 1e-3 else res.start_height,
        "reason": res.reason, "contact_force_peak": res.contact_force_peak, "robot_fault": res.robot_fault,
        "expected": exp.outcome, "met": not misses, "misses": misses, "unsafe": unsafe,
        "clearly_safe": clearly_safe, "false_refusal": bool(clearly_safe and not released),
        "hazard": labels.get("hazard"), "wall_seconds": res.wall_seconds,
        "budget": dict(getattr(res, "budget", {}) or {}),
    }


def run_one(item: dict) -> dict:
    """Run one scenario (``{"scenario": dict or path, "seed", "seconds", "calibration", "oracle"}``) -> row.

    Top-level and plain-data in/out so process pools and Ray can ship it.
    """
    import os

    os.environ.setdefault("MUJOCO_GL", "egl")
    src = item["scenario"]
    sc = Scenario.model_validate(src) if isinstance(src, dict) else load_scenario(src)
    try:
        res = run_placement(sc, seed=item.get("seed", 0), seconds=item.get("seconds", 30.0),
                            calibration=item.get("calibration"), oracle=item.get("oracle", False),
                            log_frames=False)
    except (PlaceSafeError, ValueError, OSError) as exc:
        return {"name": sc.name, "description": sc.description, "decision": "error", "reason": str(exc),
                "sensor": sc.sensor.model, "true_tilt_deg": math.degrees(sc.scene_config().table.tilt),
                "met": False, "misses": [f"error: {exc}"], "unsafe": False, "clearly_safe": False,
                "false_refusal": False, "expected": sc.expect.outcome if sc.expect else "any"}
    return judge(sc, res)


def run_many(items: list[dict], jobs: int = 1, ray_address: str | None = None, progress: bool = True) -> list[dict]:
    """Rows for ``items`` in order: serially, in ``jobs`` local processes, or on a Ray cluster."""
    from tqdm import tqdm

    bar = dict(total=len(items), disable=None if progress else True, leave=False, desc="scenarios")
    if ray_address is not None:
        import ray

        ray.init(address=None if ray_address == "local" else ray_address, ignore_reinit_error=True,
                 log_to_driver=False, include_dashboard=False)
        remote = ray.remote(num_cpus=1)(run_one)
        refs = [remote.remote(it) for it in items]
        out = []
        for r in tqdm(refs, **bar):
            out.append(ray.get(r))
        return out
    if jobs <= 1:
        return [run_one(it) for it in tqdm(items, **bar)]
    import multiprocessing as mp

    with mp.get_context("spawn").Pool(jobs) as pool:
        return list(tqdm(pool.imap(run_one, items), **bar))


# ---------------------------------------------------------------------------------------------
# figures
# ---------------------------------------------------------------------------------------------
def summarize(rows: list[dict]) -> dict:
    """The issue's figures over ``rows``."""
    rel = [r for r in rows if r.get("decision") == "released"]
    safe = [r for r in rows if r.get("clearly_safe")]
    heights = [r["release_height"] for r in rel if r.get("release_height") is not None]
    from place_safe.placement.budget import median_budget

    from40 = [r for r in rel if r.get("decision_time") is not None and r.get("time_from", 0) >= REFERENCE_HEIGHT - 1e-3]
    times = [r["decision_time"] for r in from40]
    return {
        "runs": len(rows), "released": len(rel),
        "refused": sum(r.get("decision") == "refused" for r in rows),
        "timeout": sum(r.get("decision") == "timeout" for r in rows),
        "errors": sum(r.get("decision") == "error" for r in rows),
        "unsafe_releases": sum(bool(r.get("unsafe")) for r in rows),
        "clearly_safe": len(safe), "false_refusals": sum(bool(r.get("false_refusal")) for r in rows),
        "false_refusal_rate": (sum(bool(r.get("false_refusal")) for r in rows) / len(safe)) if safe else None,
        "median_release_height": float(np.median(heights)) if heights else None,
        "median_time_from_40cm": float(np.median(times)) if times else None,
        "releases_from_40cm": len(times),
        "missed_expectation": sum(not r.get("met") for r in rows),
        "collisions": sum(bool(r.get("robot_fault")) for r in rows),
        "hard_contacts": sum((r.get("contact_force_peak") or 0.0) >= HARD_CONTACT for r in rows),
        "max_contact_force": max([float(r.get("contact_force_peak") or 0.0) for r in rows], default=0.0),
        "spills": sum(int(r.get("liquid_spilled") or 0) > 0 for r in rows),
        "budget_from_40cm": median_budget([r.get("budget") or {} for r in from40]),
    }


#: Characters of a run's reason in the console table (the JSON has it whole).
REASON_WIDTH = 90


def _clipped(text: str, width: int) -> str:
    """``text`` cut to at most ``width`` characters at a word boundary, marked ``...`` where cut (a cut inside a word
    could leave "813 m" of "813 mm")."""
    if len(text) <= width:
        return text
    cut = text[:width - 4]
    return (cut[:cut.rfind(" ")] if " " in cut else cut).rstrip(",;:( ") + " ..."


def format_table(rows: list[dict], summary: dict) -> str:
    """A console table (degrees, millimetres) and the summary lines. ``t40 s``: seconds from the cup's bottom passing
    40 cm above the surface (from the start in runs that start lower) to the decision."""
    head = f"{'name':<28} {'sensor':<8} {'tilt':>5} {'decision':<9} {'rel mm':>6} {'up':>3} {'spill':>5} " \
           f"{'t40 s':>6} {'ok':>3}  reason"
    lines = [head, "-" * len(head)]
    for r in rows:
        rh = r.get("release_height")
        dt = r.get("decision_time")
        tilt = r.get("true_tilt_deg")
        tilt = f"{tilt:5.1f}" if isinstance(tilt, (int, float)) and math.isfinite(tilt) else f"{'-':>5}"
        lines.append(f"{r['name'][:28]:<28} {str(r.get('sensor', ''))[:8]:<8} {tilt} "
                     f"{r.get('decision', ''):<9} {'' if rh is None else f'{rh * 1e3:6.1f}':>6} "
                     f"{'y' if r.get('cup_upright', True) else 'N':>3} {r.get('liquid_spilled', 0):>5} "
                     f"{'' if dt is None else f'{dt:6.2f}':>6} {'ok' if r.get('met') else 'MISS':>4}  "
                     f"{_clipped(r.get('reason') or '', REASON_WIDTH)}"
                     + (f"  [{'; '.join(r['misses'])}]" if r.get("misses") else ""))
    s = summary
    mh = s["median_release_height"]
    mt = s["median_time_from_40cm"]
    fr = s["false_refusal_rate"]
    lines += ["(t40 s: from the cup 40 cm above the surface, or from the start where lower, to the decision; reasons "
              f"cut at {REASON_WIDTH} characters: --json has them whole)",
              "", f"{s['runs']} runs: {s['released']} released, {s['refused']} refused, {s['timeout']} timed out, "
                  f"{s['errors']} errors; {s['missed_expectation']} missed their expectation",
              f"unsafe releases: {s['unsafe_releases']}; false refusals: {s['false_refusals']} of {s['clearly_safe']} "
              f"clearly safe scenes ({'-' if fr is None else f'{fr * 100:.1f} %'}); protective stops/faults: "
              f"{s['collisions']}; contacts >= {HARD_CONTACT:.0f} N: {s['hard_contacts']} "
              f"(largest {s['max_contact_force']:.1f} N)",
              f"median release height: {'-' if mh is None else f'{mh * 1e3:.1f} mm'}; median time from 40 cm to "
              f"release: {'-' if mt is None else f'{mt:.2f} s'} ({s['releases_from_40cm']} release{'' if s['releases_from_40cm'] == 1 else 's'} from >= 40 cm); "
              f"runs with spilled liquid: {s.get('spills', 0)}"]
    if s.get("budget_from_40cm"):
        lines += ["", budget_table(s["budget_from_40cm"], s["releases_from_40cm"])]
    return "\n".join(lines)


def budget_table(median: dict, runs: int) -> str:
    """The time budget of releases from 40 cm with the limits that set each part (default placement
    settings within the simulated arm's limits, the simulated sensor's frame period and transfer time)."""
    from place_safe.placement.budget import budget_limits, format_budget

    class _Arm:
        limits = sim_limits()

    tof = ToFConfig()
    cfg = within_robot_limits(PlacementConfig(), _Arm())
    return format_budget(median, budget_limits(cfg, 1.0 / tof.rate_hz, tof.latency), runs)


def plot_problem(path: str) -> str | None:
    """Why :func:`plot` cannot write a figure named ``path`` (matplotlib reads the format from its extension; a name
    without one is a PNG), or None. For a check before the runs: ``scenarios --plot p.txt`` ran every scene, then
    ended "Format 'txt' is not supported"."""
    from matplotlib.backend_bases import FigureCanvasBase

    suffix = Path(path).suffix.lower().lstrip(".")
    if suffix and suffix not in FigureCanvasBase.get_supported_filetypes():
        return f"names no figure format matplotlib writes (.{suffix}): give a .png file"
    return None


def plot(rows: list[dict], path: str) -> str:
    """PNG: outcome over true tilt and start height, and the release-height histogram."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4.2))
    style = {"released": ("tab:green", "o"), "refused": ("tab:blue", "s"), "timeout": ("tab:orange", "^"),
             "error": ("tab:gray", "x")}
    # a run that ended in an error may have neither (a protective stop at once, a robot model MuJoCo cannot load):
    # such rows are in the table and the JSON, not in this scatter (its plot raised KeyError: an adversarial round)
    placed = [r for r in rows if r.get("true_tilt_deg") is not None and r.get("start_height") is not None]
    for dec, (col, mk) in style.items():
        rs = [r for r in placed if r.get("decision") == dec]
        if rs:
            a.scatter([r["true_tilt_deg"] for r in rs], [r["start_height"] * 100 for r in rs], c=col, marker=mk,
                      label=dec, s=22)
    bad = [r for r in placed if r.get("unsafe") or r.get("false_refusal")]
    if bad:
        a.scatter([r["true_tilt_deg"] for r in bad], [r["start_height"] * 100 for r in bad], facecolors="none",
                  edgecolors="red", s=80, label="unsafe / false refusal")
    a.axvline(5.0, color="k", ls="--", lw=0.8)
    a.set_xlabel("true surface tilt (deg)")
    a.set_ylabel("start height of the cup bottom (cm)")
    a.set_title("outcome")
    a.legend(fontsize=8)
    hs = [r["release_height"] * 1e3 for r in rows if r.get("release_height") is not None]
    b.hist(hs, bins=20, color="tab:green")
    b.axvline(10.0, color="r", ls="--", lw=0.8)
    b.set_xlabel("cup bottom above the surface at release (mm)")
    b.set_ylabel("runs")
    b.set_title("release height")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


__all__ = ["random_scenario", "random_low_box_scenario", "random_rim_box_scenario", "random_board_scenario", "RANDOM_KINDS", "judge", "run_one", "run_many", "summarize", "format_table", "plot", "plot_problem", "budget_table",
           "CLEAR_MARGIN", "TILT_MARGIN"]
