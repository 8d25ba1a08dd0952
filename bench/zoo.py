"""`bagit bench zoo`: bags the paper never tried (issue 35), each run through `bagit run` with the CR5s.

A zoo is `n` bags drawn from documented ranges (`CORE`, a lab's ordinary bags), bag i from a
generator seeded with (zoo seed, i), so that bag i is the same whatever `n` and on any machine.
Each bag is paired with a bundled object (exp01..exp12, drawn) and the run seed i; its scenario is
the object's bundled scenario with the bag's fabric, binding, size, colours, light and depth noise
(`bag.fabric`, `bag.rim`, `bag.*`, `sim.*`; common/bag.py). Its name, `zoo-<set>-<zoo seed>-<i>`,
is all a sweep worker needs to build it again (`zoo_scenario`), so the runs go through the sweep's
engine (bench/closed_loop.py: a local Dask cluster, or `--cluster`) and its records are the
sweep's `RunResult`s (commit, host, worker, parameters), each with the bag it ran (`zoo_bag`).

Each bag belongs to classes by where its values lie: the lowest or highest quarter of a range (in
its own scale: log for the stiffnesses, mass, damping and noise) names a class (soft, stiff,
heavy, small, large, floppy or stiff binding, dim or bright light, noisy depth), as do a binding of
another colour than red and a solid bag. The report gives success, error and simulated time per
class and overall. A perimeter is drawn where the object fits: a draw is drawn again (up to
MAX_FIT_DRAWS times) when `check_scenario_goal` refuses it, the rule `bagit run` and `bagit up` apply
before anything moves: the goal the object and the bag's start rim give cannot be made (no ellipse of
perimeter R holds V under C1-C3), cannot be reached by the arms, or ends where the planner cannot
(g† or g* within the planner's margin of the object: `ends_touch`, the planner's own check). Such a bag
cannot be bagged by the method from its start rim at all, so it is no sample of the range; a bag that
fits and then fails is a failure. A bag's depth is cut to what hangs clear of the table from its start
rim (DEPTH_CLEARANCE_M).

    bagit bench zoo [--bags 100] [--zoo-seed 0] [--quick] [--record] [--workers 1] [--cluster tcp://HOST:PORT]

Records only when asked: `--record` writes bench/results/zoo-core-<zoo seed>.{jsonl,json,md};
`--quick` (QUICK_BAGS bags) writes under bench/results/quick/ and never over a published record.
"""

from __future__ import annotations

import colorsys
import json
import logging
import math
import os
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from bagit.bench.closed_loop import RUN_TIMEOUT_S, sweep
from bagit.bench.common import RESULTS_DIR, machine, write_results
from bagit.bench.isolated import Key
from bagit.common.bag import FABRIC_DAMPING_S, RIM_BENDING_NM2, RIM_COLOR
from bagit.common.errors import BagItError
from bagit.common.names import DEFAULT_CONTROLLER
from bagit.common.scenario import Scenario

log = logging.getLogger("bagit.bench.zoo")

ZOO_PREFIX = "zoo"
OBJECTS = [f"exp{k:02d}" for k in range(1, 13)]  # the paper's twelve experiments' objects (bundled scenarios)
QUICK_BAGS = 4
DEFAULT_BAGS = 100
MAX_FIT_DRAWS = 20  # perimeter draws before a bag's object is taken not to fit any bag of the range
DEPTH_CLEARANCE_M = 0.02  # a bag's bottom hangs at least this far above the table at the start
SOLID_SHARE = 0.25  # the share of solid-colour bags (the others red-edged, with a binding of any hue)
MIN_HUE_GAP_DEG = 40.0  # a segmented colour's hue this far from the object's and (a binding) the fabric's: 2x perception's tolerance
OBJECT_RGB = (0.85, 0.65, 0.25)  # services/sim/objects.py OBJECT_RGBA: the bundled objects' colour
RED_CLASS_DEG = 20.0  # a binding within this of red's hue is a red binding (perception's tolerance)
TAIL = 0.25  # the lowest and highest quarter of a range name its classes


@dataclass(frozen=True)
class Range:
    """One parameter's range: uniform in [lo, hi], or in [log lo, log hi] (`log`); `low`/`high` name the
    classes of its lowest and highest TAIL (None: no class)."""

    lo: float
    hi: float
    log: bool
    doc: str
    low: str | None = None
    high: str | None = None

    def _unit(self, v: float) -> float:
        f = (lambda x: math.log(x)) if self.log else (lambda x: x)
        return (f(v) - f(self.lo)) / (f(self.hi) - f(self.lo))

    def at(self, u: float) -> float:
        """The value a share `u` in [0, 1] of the way through the range (in its own scale)."""
        return float(math.exp(math.log(self.lo) + u * math.log(self.hi / self.lo))) if self.log else self.lo + u * (self.hi - self.lo)

    def draw(self, rng: np.random.Generator) -> float:
        return self.at(float(rng.uniform()))

    def classes(self, v: float) -> list[str]:
        u = self._unit(v)
        return [c for c, inside in ((self.low, u <= TAIL), (self.high, u >= 1 - TAIL)) if c is not None and inside]


# Issue 35's core ranges: a lab's ordinary bags under ordinary lights. Multiples are of the default bag's (common/bag.py).
CORE: dict[str, Range] = {
    "stretch_n_per_m": Range(1000.0, 64000.0, True, "membrane stretch stiffness E*t (N/m)", "soft", "stiff"),
    "mass_kg": Range(0.03, 0.3, True, "the bag's mass (kg)", None, "heavy"),
    "damping_x": Range(0.5, 4.0, True, f"x the membrane damping {FABRIC_DAMPING_S} s"),
    "friction": Range(0.2, 1.0, False, "sliding friction (MuJoCo's IPC contacts are frictionless: no effect there)"),
    "bending_x": Range(0.1, 10.0, True, f"x the binding's bending stiffness {RIM_BENDING_NM2:.3g} N m^2", "floppy binding", "stiff binding"),
    "perimeter_m": Range(0.55, 1.0, False, "rim perimeter R (m), where the object fits", "small", "large"),
    "depth_m": Range(0.2, 0.45, False, "bag depth (m), cut to hang clear of the table"),
    "light_x": Range(0.5, 1.5, False, "x the scene's light intensity", "dim light", "bright light"),
    "light_elevation_deg": Range(20.0, 90.0, False, "the key light's elevation above the table (deg), from any azimuth"),
    "depth_noise_x": Range(0.5, 2.0, True, "x the D455 model's depth noise", None, "noisy depth"),
    "fabric_saturation": Range(0.45, 0.9, False, "the fabric's HSV saturation (any hue)"),
    "fabric_value": Range(0.45, 0.85, False, "the fabric's HSV value"),
    "binding_saturation": Range(0.75, 0.95, False, "the binding's HSV saturation (any hue)"),
    "binding_value": Range(0.65, 0.9, False, "the binding's HSV value"),
}
CALIBRATION_CLASS = "calibration error"
# The camera's calibrated pose wrong by a distance and an angle, each in any direction (sim.camera.calibration_error):
# drawn after everything else, so that adding them left every other draw of a bag as it was. The core's is a
# lab's ordinary hand-eye calibration (a few mm, a fraction of a degree; the issue's classes name it, its
# ranges do not: this choice is ours); the envelope's is the issue's, up to 3 cm and 2 degrees.
CORE_CALIBRATION: dict[str, Range] = {
    "calibration_offset_m": Range(0.0, 0.01, False, "the camera's true position this far from the calibrated one (m, any direction)",
                                  None, CALIBRATION_CLASS),
    "calibration_turn_deg": Range(0.0, 1.0, False, "its true orientation turned this far from the calibrated one (deg, about any axis)",
                                  None, CALIBRATION_CLASS),
}
# Issue 35's envelope: past the core ranges, to find where BagIt stops (the others as the core's).
ENVELOPE: dict[str, Range] = {
    **CORE,
    "stretch_n_per_m": Range(250.0, 256000.0, True, "membrane stretch stiffness E*t (N/m)", "soft", "stiff"),
    "mass_kg": Range(0.03, 0.5, True, "the bag's mass (kg)", None, "heavy"),
    "bending_x": Range(0.003, 300.0, True, f"x the binding's bending stiffness {RIM_BENDING_NM2:.3g} N m^2 (a loose hem to a stiff hoop)",
                       "floppy binding", "stiff binding"),
    "perimeter_m": Range(0.4, 1.3, False, "rim perimeter R (m), from the smallest where the object fits", "small", "large"),
    "light_x": Range(0.25, 2.0, True, "x the scene's light intensity", "dim light", "bright light"),
    "depth_noise_x": Range(0.5, 4.0, True, "x the D455 model's depth noise", None, "noisy depth"),
}
ENVELOPE_CALIBRATION: dict[str, Range] = {
    "calibration_offset_m": replace(CORE_CALIBRATION["calibration_offset_m"], hi=0.03),
    "calibration_turn_deg": replace(CORE_CALIBRATION["calibration_turn_deg"], hi=2.0),
}
RANGE_SETS = {"core": CORE, "envelope": ENVELOPE}
CALIBRATION_SETS = {"core": CORE_CALIBRATION, "envelope": ENVELOPE_CALIBRATION}


def _unit_vector(rng: np.random.Generator) -> np.ndarray:
    """(3,) a direction drawn uniformly on the sphere."""
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _hue_deg(rgb: tuple[float, float, float]) -> float:
    return colorsys.rgb_to_hsv(*rgb)[0] * 360.0


def _hue_gap(a: float, b: float) -> float:
    d = abs(a - b) % 360.0
    return min(d, 360.0 - d)


def _colour(rng: np.random.Generator, sat: float, val: float, away_from: list[float]) -> tuple[float, float, float]:
    """An RGB colour of saturation `sat` and value `val` whose hue is at least MIN_HUE_GAP_DEG from each of `away_from` (deg)."""
    while True:
        h = float(rng.uniform(0.0, 360.0))
        if all(_hue_gap(h, a) >= MIN_HUE_GAP_DEG for a in away_from):
            r, g, b = colorsys.hsv_to_rgb(h / 360.0, sat, val)
            return round(r, 4), round(g, 4), round(b, 4)


def zoo_name(set_name: str, zoo_seed: int, i: int) -> str:
    return f"{ZOO_PREFIX}-{set_name}-{zoo_seed}-{i}"


def is_zoo_name(name: str) -> bool:
    return name.startswith(f"{ZOO_PREFIX}-")


def zoo_bag(name: str) -> dict[str, Any]:
    """The bag named `zoo-<set>-<zoo seed>-<i>`: its drawn values, object, run seed and classes."""
    try:
        _, set_name, zoo_seed, i = name.split("-")
        ranges = RANGE_SETS[set_name]
        seed, index = int(zoo_seed), int(i)
    except (ValueError, KeyError):
        raise BagItError(f"not a zoo bag name: {name!r} (zoo-<{'|'.join(RANGE_SETS)}>-<zoo seed>-<i>)") from None
    if seed < 0 or index < 0:
        raise BagItError(f"not a zoo bag name: {name!r} (negative seed or index)")
    rng = np.random.default_rng([seed, index])
    v = {k: r.draw(rng) for k, r in ranges.items()}
    v["light_azimuth_deg"] = float(rng.uniform(0.0, 360.0))
    solid = bool(rng.uniform() < SOLID_SHARE)
    obj_hue = _hue_deg(OBJECT_RGB)
    fabric = _colour(rng, v["fabric_saturation"], v["fabric_value"], [obj_hue] if solid else [])
    binding = None if solid else _colour(rng, v["binding_saturation"], v["binding_value"], [obj_hue, _hue_deg(fabric)])
    obj = OBJECTS[int(rng.integers(len(OBJECTS)))]
    classes = [c for k, r in ranges.items() for c in r.classes(v[k]) if k != "perimeter_m"]
    if solid:
        classes.append("solid")
    elif binding is not None and _hue_gap(_hue_deg(binding), _hue_deg(RIM_COLOR)) > RED_CLASS_DEG:
        classes.append("colour")
    perimeter_draws = [v["perimeter_m"]] + [ranges["perimeter_m"].draw(rng) for _ in range(MAX_FIT_DRAWS - 1)]
    calibration = {}
    for k, r in CALIBRATION_SETS[set_name].items():
        v[k] = r.draw(rng)
        calibration[k] = np.round(v[k] * _unit_vector(rng), 6).tolist()
        classes += [c for c in r.classes(v[k]) if c not in classes]
    return {"name": name, "set": set_name, "zoo_seed": seed, "index": index, "object": obj, "seed": index,
            "kind": "solid" if solid else "red-edged", "fabric_color": fabric, "binding_color": binding, "values": v,
            "calibration_error": {"offset_m": calibration["calibration_offset_m"], "turn_deg": calibration["calibration_turn_deg"]},
            "classes": classes, "perimeter_draws": perimeter_draws}


def _apply(base: Scenario, bag: dict[str, Any], perimeter: float) -> Scenario:
    """The object's bundled scenario with `bag`'s bag (perimeter `perimeter`), light and depth noise."""
    from bagit.common.geometry import closed_polyline_length

    v = bag["values"]
    doc = json.loads(base.model_dump_json(exclude_none=True))
    b = doc["bag"]
    if base.bag.initial_rim is not None:  # the start rim, scaled about its centre to the new perimeter
        rim = np.asarray(base.bag.initial_rim, dtype=float)
        c = rim.mean(axis=0)
        rim = c + (rim - c) * (perimeter / closed_polyline_length(rim))
        b["initial_rim"] = np.round(rim, 6).tolist()
        hang = float(c[2]) - DEPTH_CLEARANCE_M  # the rim hangs level at its centre's height (services/sim/world.py)
    else:
        hang = v["depth_m"]
    az, el = math.radians(v["light_azimuth_deg"]), math.radians(v["light_elevation_deg"])
    b.update({
        "rim_perimeter": perimeter, "depth": round(min(v["depth_m"], hang), 4), "kind": bag["kind"], "color": list(bag["fabric_color"]),
        "fabric": {"stretch_n_per_m": v["stretch_n_per_m"], "mass_kg": v["mass_kg"], "damping_s": v["damping_x"] * FABRIC_DAMPING_S,
                   "friction": v["friction"]},
        "rim": {"bending_nm2": v["bending_x"] * RIM_BENDING_NM2, **({"color": list(bag["binding_color"])} if bag["binding_color"] else {})},
    })
    doc["name"] = bag["name"]
    doc["description"] = f"bag zoo: {bag['name']} with the object of {bag['object']}"
    doc["sim"] = {"light": {"intensity": v["light_x"], "direction": [-math.cos(el) * math.cos(az), -math.cos(el) * math.sin(az), -math.sin(el)]},
                  "camera": {"depth_noise": v["depth_noise_x"], "calibration_error": bag["calibration_error"]}}
    return Scenario.from_dict(doc, bag["name"])


def zoo_scenario(name: str) -> tuple[Scenario, dict[str, Any]]:
    """The scenario of the zoo bag `name` and the bag (with `perimeter_m`: the first draw where the object
    fits, `check_scenario_goal`; BagItError when none of MAX_FIT_DRAWS does)."""
    from bagit.scenarios import find_scenario
    from bagit.services.planner.plan import check_scenario_goal

    bag = zoo_bag(name)
    base = Scenario.from_file(find_scenario(bag["object"]))
    why = ""
    for k, perimeter in enumerate(bag["perimeter_draws"]):
        sc = _apply(base, bag, perimeter)
        try:
            check_scenario_goal(sc)
        except BagItError as e:
            why = str(e).splitlines()[0]
            continue
        bag = {**bag, "perimeter_m": perimeter, "fit_draws": k + 1}
        bag["classes"] = bag["classes"] + RANGE_SETS[bag["set"]]["perimeter_m"].classes(perimeter)
        return sc, bag
    raise BagItError(f"{name}: the object of {bag['object']} fits none of {MAX_FIT_DRAWS} drawn perimeters (last: {why})")


def summary(records: list[dict[str, Any]], bags: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Success, error (cm, over successes) and simulated time (s, over successes) overall and per class."""
    groups: dict[str, list[dict[str, Any]]] = {"all": records}
    for r in records:
        for c in bags[r["scenario"]]["classes"]:
            groups.setdefault(c, []).append(r)
    out = {}
    for c, rs in groups.items():
        ok = [r for r in rs if r.get("success")]
        out[c] = {"success": len(ok), "of": len(rs), "rate": len(ok) / len(rs) if rs else float("nan"),
                  "error_cm_mean": float(np.mean([r["error_cm"] for r in ok])) if ok else None,
                  "time_s_mean": float(np.mean([r["duration_s"] for r in ok])) if ok else None}
    return out


def _stem(set_name: str, zoo_seed: int, params: dict[str, Any] | None) -> str:
    """The records' name: the set and zoo seed, and the method parameters of an ablation (`-name-value`)."""
    return f"zoo-{set_name}-{zoo_seed}" + "".join(f"-{k}-{v}" for k, v in sorted((params or {}).items()))


def run(n: int | None = None, zoo_seed: int = 0, quick: bool = False, record: bool = False, set_name: str = "core", workers: int = 1,
        cluster: str | None = None, time_limit_s: float = 40.0, timeout_s: float = RUN_TIMEOUT_S, out_dir: Path | None = None,
        params: dict[str, Any] | None = None) -> dict[str, Any]:
    """Draw the zoo, run each bag (resuming a recorded sweep), and report; files only with `record` or `quick`.
    `params`: method parameters for every run (an ablation, e.g. {"jacobian_update": "frozen"}), in the records' name."""
    if set_name not in RANGE_SETS:
        raise BagItError(f"no zoo range set {set_name!r}; choose from {', '.join(RANGE_SETS)}")
    n = n or (QUICK_BAGS if quick else DEFAULT_BAGS)
    names = [zoo_name(set_name, zoo_seed, i) for i in range(n)]
    bags = {}
    for name in names:
        bags[name] = zoo_scenario(name)[1]
    stem = _stem(set_name, zoo_seed, params)
    folder = out_dir or (RESULTS_DIR / "quick" if quick else RESULTS_DIR)
    jsonl = folder / f"{stem}.jsonl" if (record or quick) else None
    if jsonl is not None:
        folder.mkdir(parents=True, exist_ok=True)
        if quick and out_dir is None:
            jsonl.unlink(missing_ok=True)  # a smoke check runs afresh; a recorded zoo resumes where it stopped
    load_before = os.getloadavg()
    keys: list[Key] = [(name, DEFAULT_CONTROLLER, "cbirrt", int(bags[name]["seed"]), "cr5") for name in names]
    records = sweep(keys, jsonl, workers, timeout_s, time_limit_s, params, cluster)
    runs = [{**r, "zoo_bag": bags[r["scenario"]], "cause": cause(r)} for r in records]
    result = {"kind": "zoo", "set": set_name, "zoo_seed": zoo_seed, "bags": n, "machine": machine(), "load_before": load_before,
              "load_after": os.getloadavg(), "params": {"controller": DEFAULT_CONTROLLER, "planner": "cbirrt", "arms": "cr5",
                                                        "time_limit_s": time_limit_s, "workers": workers, "cluster": cluster,
                                                        "method_params": dict(params or {})},
              "ranges": {k: {"lo": r.lo, "hi": r.hi, "log": r.log, "doc": r.doc, "low": r.low, "high": r.high}
                         for k, r in {**RANGE_SETS[set_name], **CALIBRATION_SETS[set_name]}.items()},
              "summary": summary(records, bags), "map": envelope_map(runs, set_name), "runs": runs}
    if jsonl is not None:
        jp, mp = write_results(stem, result, markdown(result), folder)
        result["files"] = {"runs": str(jsonl), "json": str(jp), "markdown": str(mp)}
    return result


def write_bag(name: str, folder: Path) -> dict[str, Any]:
    """The zoo bag `name` as a scenario file `folder/<name>.yaml`, which `bagit run FILE` and `bagit up FILE` run
    (its object, fabric, binding, colours, light, depth noise and calibration error); its run seed is the bag's."""
    sc, bag = zoo_scenario(name)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.yaml"
    path.write_text(sc.to_yaml())
    return {"kind": "zoo-bag", "scenario": str(path), "seed": bag["seed"], "bag": {k: v for k, v in bag.items() if k != "perimeter_draws"}}


def run_from_args(a: Any) -> dict[str, Any]:
    """`bagit bench zoo` from its parsed flags; the sweep's progress on stderr."""
    from bagit.bench.closed_loop import quiet_engine_logs

    if a.write_bag:
        return write_bag(a.write_bag, a.out or Path.cwd())
    if a.perception:
        from bagit.bench import zoo_perception

        return zoo_perception.run(a.bags, a.zoo_seed, a.zoo_set, a.quick, a.record, a.out)
    quiet_engine_logs()
    return run(a.bags, a.zoo_seed, a.quick, a.record, set_name=a.zoo_set, workers=a.workers, cluster=a.cluster,
               time_limit_s=a.time_limit_s, timeout_s=a.timeout_s, out_dir=a.out, params=a.params)


# -- why a run failed, and the envelope's map -----------------------------------------------------------

CAUSES = ("perception", "goal", "plan", "control", "physics", "outcome", "harness")


def cause(r: dict[str, Any]) -> str | None:
    """Which part a failed run's record blames (CAUSES), from its stage and reason; None for a success.
    perception: the rim lost or never seen; goal, plan: their stages failed; physics: the simulator failed
    or crawled; control: servoing ran out of time or the controller failed; outcome: the run ended but the
    rim is not round the object (the truth's verdict); harness: the run gave no record of its own."""
    if r.get("success"):
        return None
    reason, stage = str(r.get("reason") or ""), r.get("stage_reached")
    if reason.startswith(("timed out", "crashed", "error:")):
        return "harness"
    if reason.startswith("simulator:"):
        return "physics"
    if "perception lost the rim" in reason or "no fresh SOI" in reason:
        return "perception"
    if stage == "goal":
        return "goal"
    if stage == "planning":
        return "plan"
    if stage == "done":
        return "outcome"
    return "control"


MAP_BINS = 5
FALLOFF_RATE = 0.9  # a bin below this success rate is where BagIt falls off along that parameter


def envelope_map(runs: list[dict[str, Any]], set_name: str) -> dict[str, list[dict[str, Any]]]:
    """Success against each parameter: its range cut into MAP_BINS equal bins (in its own scale), each with
    its runs, successes and the causes of its failures."""
    ranges = {**RANGE_SETS[set_name], **CALIBRATION_SETS[set_name]}
    out: dict[str, list[dict[str, Any]]] = {}
    for k, r in ranges.items():
        bins: list[dict[str, Any]] = [{"lo": r.at(b / MAP_BINS), "hi": r.at((b + 1) / MAP_BINS), "of": 0, "success": 0, "causes": {}}
                                      for b in range(MAP_BINS)]
        for x in runs:
            bag = x["zoo_bag"]
            val = bag.get(k) if k == "perimeter_m" else bag["values"].get(k)
            if val is None:
                continue
            b = min(MAP_BINS - 1, max(0, int(r._unit(float(val)) * MAP_BINS)))
            bins[b]["of"] += 1
            if x.get("success"):
                bins[b]["success"] += 1
            else:
                c = x.get("cause") or cause(x) or "?"
                bins[b]["causes"][c] = bins[b]["causes"].get(c, 0) + 1
        out[k] = bins
    return out


def markdown(r: dict[str, Any]) -> str:
    """The report: provenance, then one row per class."""
    m = r["machine"]
    lines = [f"# Bag zoo: {r['bags']} bags from the {r['set']} ranges (zoo seed {r['zoo_seed']})", "",
             f"Commit {m.get('commit')}, host {m.get('host')}, {m.get('cpu')} ({m.get('cores')} cores), {m.get('when')}; "
             f"load average before {r['load_before']}, after {r['load_after']}; {r['params']}.", "",
             "| class | success | error cm (mean) | time s (mean) |", "| --- | --- | --- | --- |"]
    for c, s in sorted(r["summary"].items(), key=lambda kv: (kv[0] != "all", kv[0])):
        err = f"{s['error_cm_mean']:.2f}" if s["error_cm_mean"] is not None else "-"
        t = f"{s['time_s_mean']:.1f}" if s["time_s_mean"] is not None else "-"
        lines.append(f"| {c} | {s['success']}/{s['of']} | {err} | {t} |")
    fails = [f"- {x['scenario']} ({x['zoo_bag']['object']}, {', '.join(x['zoo_bag']['classes']) or 'no class'}): "
             f"{x.get('cause')}: {x.get('stage_reached')}: {x.get('reason')}" + (f" (arms slowed {_slowed(x)} periods)" if _slowed(x) else "")
             for x in r["runs"] if not x.get("success")]
    slowed = [f"{x['scenario']} ({_slowed(x)}, {'success' if x.get('success') else 'failed'})" for x in r["runs"] if _slowed(x)]
    return "\n".join(lines + _map_lines(r.get("map") or {}) + ([""] + ["Failures:"] + fails if fails else [])
                     + ([""] + [f"Runs the arm driver slowed (arm_events.slowed > 0; periods): {', '.join(slowed)}."] if slowed else [])) + "\n"


def _slowed(run: dict[str, Any]) -> int:
    """The control periods the CR5 driver slowed in a run (its arm_events; 0 without them): the runs a driver change can alter."""
    return int((run.get("arm_events") or {}).get("slowed") or 0)


def _map_lines(m: dict[str, list[dict[str, Any]]]) -> list[str]:
    """The map as a table: per parameter, successes per bin (low to high), the bins below FALLOFF_RATE and why."""
    if not m:
        return []
    lines = ["", f"Success against each parameter ({MAP_BINS} equal bins of its range, in its own scale; "
             f"falls off: the bins below {FALLOFF_RATE:.0%}, each with the causes of its own failures):", "",
             "| parameter | " + " | ".join(f"bin {b + 1}" for b in range(MAP_BINS)) + " | falls off (causes) |",
             "| --- |" + " --- |" * (MAP_BINS + 1)]
    for k, bins in m.items():
        cells = [f"{b['success']}/{b['of']} ({b['lo']:.3g}-{b['hi']:.3g})" for b in bins]
        low = [b for b in bins if b["of"] and b["success"] / b["of"] < FALLOFF_RATE]
        where = "; ".join(f"{b['lo']:.3g}-{b['hi']:.3g} ({', '.join(f'{c} {n}' for c, n in sorted(b['causes'].items()))})" for b in low)
        lines.append(f"| {k} | " + " | ".join(cells) + f" | {where or '-'} |")
    return lines
