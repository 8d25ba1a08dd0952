"""`bagit bench zoo --perception`: perception's SOI against the simulator's true rim on the zoo's bags (issue 35).

For each bag of the zoo (its fabric and binding colours, its light, its depth noise; `zoo_scenario`), the
world is built, the bag hangs still for SETTLE_S, and FRAMES frames are rendered a control tick apart;
each goes through perception's own path as `bagit run` uses it (`RimTracker` with the bag's kind and
colour and the binding's colour, as the lab's perception config names it), and the SOI is compared with
the true rim: the distance of each SOI point to the true rim's polyline, mean and largest (mm). The
camera's calibration error is left out (zeroed): it displaces what perception sees by the error itself
(tests/sim/test_sim_calibration_error.py), which would hide what colour and light do. No run, no arms:
what is measured is perception alone, on the bag as it hangs at the start.

The report gives the error per class (the zoo's: dim light, colour, solid, ...), per light-intensity bin
and per hue bin of the segmented colour (the binding's, or a solid bag's fabric).

    bagit bench zoo --perception [--bags 100] [--zoo-seed 0] [--zoo-set core] [--record | --quick]
"""

from __future__ import annotations

import colorsys
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from bagit.bench.common import RESULTS_DIR, machine, write_results
from bagit.bench.zoo import DEFAULT_BAGS, QUICK_BAGS, zoo_name, zoo_scenario
from bagit.common.bag import CalibrationError
from bagit.common.errors import BagItError
from bagit.common.geometry import points_to_polyline_distance

log = logging.getLogger("bagit.bench.zoo_perception")

SETTLE_S = 1.0  # the bag hangs still this long before the first frame (as a run's perceiving stage)
FRAMES = 3  # frames per bag, a control tick apart
FRAME_DT_S = 1.0 / 30
HUE_BINS_DEG = 60.0
LIGHT_BINS = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0)


def measure(name: str) -> dict[str, Any]:
    """One bag: the SOI's distance to the true rim (mm) on FRAMES frames, or why perception gave none."""
    from bagit.services.perception.tracker import RimTracker
    from bagit.services.sim.world import SimWorld

    sc, bag = zoo_scenario(name)
    camera = sc.sim.camera.model_copy(update={"calibration_error": CalibrationError()})
    sc = sc.model_copy(update={"sim": sc.sim.model_copy(update={"camera": camera})})
    out: dict[str, Any] = {"scenario": name, "kind": bag["kind"], "classes": bag["classes"], "light_x": bag["values"]["light_x"],
                           "light_elevation_deg": bag["values"]["light_elevation_deg"],
                           "segmented_rgb": bag["binding_color"] or bag["fabric_color"], "frames": [], "failures": []}
    r, g, b = out["segmented_rgb"]
    out["segmented_hue_deg"] = colorsys.rgb_to_hsv(r, g, b)[0] * 360.0
    t0 = time.perf_counter()
    with SimWorld(sc, seed=int(bag["seed"])) as w:
        tracker = RimTracker(sc.bag.n_x, sc.bag.kind, sc.bag.color, rim_color=sc.bag.rim.color)
        w.step(SETTLE_S)
        for k in range(FRAMES):
            frame = w.render_rgbd(k)
            truth = w.true_rim()
            try:
                soi, cloud = tracker.update(frame, hint=truth[0])
            except BagItError as e:
                out["failures"].append(str(e).splitlines()[0])
            else:
                d = points_to_polyline_distance(soi, truth)
                out["frames"].append({"mean_mm": round(float(d.mean()) * 1000, 3), "max_mm": round(float(d.max()) * 1000, 3),
                                      "cloud_points": len(cloud)})
            w.step(FRAME_DT_S)
    out["wall_s"] = round(time.perf_counter() - t0, 2)
    return out


def _group(rows: list[dict[str, Any]]) -> dict[str, Any]:
    frames = [f for r in rows for f in r["frames"]]
    return {"bags": len(rows), "frames": len(frames), "failed_frames": sum(len(r["failures"]) for r in rows),
            "mean_mm": round(float(np.mean([f["mean_mm"] for f in frames])), 2) if frames else None,
            "max_mm": round(float(np.max([f["max_mm"] for f in frames])), 2) if frames else None}


def summary(rows: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """The error overall, per class, per light bin and per hue bin of the segmented colour."""
    groups: dict[str, list[dict[str, Any]]] = {"all": rows}
    for r in rows:
        for c in r["classes"]:
            groups.setdefault(f"class: {c}", []).append(r)
        k = int(np.searchsorted(LIGHT_BINS, r["light_x"], side="right")) - 1
        lo, hi = LIGHT_BINS[max(k, 0)], LIGHT_BINS[min(k + 1, len(LIGHT_BINS) - 1)]
        groups.setdefault(f"light x{lo:g}-{hi:g}", []).append(r)
        h = int(r["segmented_hue_deg"] // HUE_BINS_DEG) * HUE_BINS_DEG
        groups.setdefault(f"hue {h:g}-{h + HUE_BINS_DEG:g} deg ({r['kind']})", []).append(r)
    return {k: _group(v) for k, v in sorted(groups.items(), key=lambda kv: (kv[0] != "all", kv[0]))}


def run(n: int | None = None, zoo_seed: int = 0, set_name: str = "core", quick: bool = False, record: bool = False,
        out_dir: Path | None = None) -> dict[str, Any]:
    """Measure the zoo's bags one after the other (one core); files only with `record` or `quick`."""
    n = n or (QUICK_BAGS if quick else DEFAULT_BAGS)
    load_before = os.getloadavg()
    rows = []
    for i in range(n):
        rows.append(measure(zoo_name(set_name, zoo_seed, i)))
        log.info("[%d/%d] %s: %s", i + 1, n, rows[-1]["scenario"], rows[-1]["frames"] or rows[-1]["failures"])
    result = {"kind": "zoo-perception", "set": set_name, "zoo_seed": zoo_seed, "bags": n, "machine": machine(), "load_before": load_before,
              "load_after": os.getloadavg(), "params": {"settle_s": SETTLE_S, "frames": FRAMES, "frame_dt_s": FRAME_DT_S,
                                                        "calibration_error": "zeroed"},
              "summary": summary(rows), "bags_measured": rows}
    if record or quick:
        folder = out_dir or (RESULTS_DIR / "quick" if quick else RESULTS_DIR)
        jp, mp = write_results(f"zoo-perception-{set_name}-{zoo_seed}", result, markdown(result), folder)
        result["files"] = {"json": str(jp), "markdown": str(mp)}
    return result


def markdown(r: dict[str, Any]) -> str:
    """The report: provenance, then one row per group."""
    m = r["machine"]
    lines = [f"# Perception on the bag zoo: {r['bags']} bags from the {r['set']} ranges (zoo seed {r['zoo_seed']})", "",
             "The SOI's distance to the simulator's true rim (each SOI point to the true rim's polyline; mm) on "
             f"{r['params']['frames']} frames per bag after {r['params']['settle_s']:g} s of settling, the camera's calibration error zeroed.", "",
             f"Commit {m.get('commit')}, host {m.get('host')}, {m.get('cpu')} ({m.get('cores')} cores), {m.get('when')}; "
             f"load average before {r['load_before']}, after {r['load_after']}.", "",
             "| group | bags | frames | frames without SOI | mean mm | largest mm |", "| --- | --- | --- | --- | --- | --- |"]
    for k, s in r["summary"].items():
        lines.append(f"| {k} | {s['bags']} | {s['frames']} | {s['failed_frames']} | {s['mean_mm'] if s['mean_mm'] is not None else '-'} | "
                     f"{s['max_mm'] if s['max_mm'] is not None else '-'} |")
    fails = [f"- {b['scenario']} ({b['kind']}, {', '.join(b['classes']) or 'no class'}): {b['failures'][0]}"
             for b in r["bags_measured"] if b["failures"]]
    return "\n".join(lines + ([""] + ["Frames without an SOI:"] + fails if fails else [])) + "\n"
