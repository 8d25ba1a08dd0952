"""SOI accuracy at the simulated D455's colour+depth modes: is a smaller mode than 640x480 good enough?

    python -m bagit.bench.camera_modes [--quick] [--record]

For a few bundled scenarios and seeds, the simulated world is rendered at 640x480 and at the
smaller D455 modes (the same horizontal field of view: fx, fy scaled with the width, so the 16:9
modes see less vertically), the rim is extracted by perception's `RimTracker` (as the service
does, warm-started frame to frame from the left mount as the hint) and compared with the true rim
(`SimWorld.true_rim`, never seen by perception): RMS and max distance of the SOI's points to the
true rim polyline, in mm, with the bag hanging after the settle and after the mounts have moved
(lifted and brought together, as pre-bagging does). Also the CPU time of one frame (render with the
depth noise, and perception's SOI) per mode. Failures to find a rim are counted.
"""

from __future__ import annotations

import argparse
import logging
import os
import time
from typing import Any

import numpy as np

from bagit.common.logs import configure_logging
from bagit.common.rig import ArmName

log = logging.getLogger("bagit.bench.camera_modes")

MODES = ((640, 480), (640, 360), (480, 270), (424, 240))  # D455 colour+depth modes
SCENARIOS = ("exp01", "exp02", "exp05", "exp10")


def _camera(width: int, height: int) -> Any:
    from bagit.common.rig import CameraConfig

    base = CameraConfig()
    s = width / base.width
    return base.model_copy(update={"width": width, "height": height, "fx": base.fx * s, "fy": base.fy * s})


def _moved(homes: dict[ArmName, np.ndarray], f: float) -> dict[ArmName, np.ndarray]:
    """The mounts lifted 8 cm and brought 4 cm together, a share `f` of the way."""
    out: dict[ArmName, np.ndarray] = {}
    for name, T in homes.items():
        T2 = T.copy()
        T2[:3, 3] += f * np.array([0.0, 0.04 if name == "left" else -0.04, 0.08])
        out[name] = T2
    return out


def measure_one(name: str, seed: int, modes: tuple[tuple[int, int], ...] = MODES) -> dict[str, Any]:
    from bagit.common.geometry import points_to_polyline_distance
    from bagit.common.rig import RigConfig
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.perception.tracker import RimTracker
    from bagit.services.sim.world import SimWorld

    sc = Scenario.from_file(find_scenario(name))
    worlds = {m: SimWorld(sc, RigConfig(camera=_camera(*m)), seed) for m in modes}
    r, g, b = sc.bag.color
    trackers = {m: RimTracker(sc.bag.n_x, sc.bag.kind, (r, g, b)) for m in modes}
    out: dict[str, Any] = {m_key(m): {"errors_mm": [], "max_mm": [], "failed": 0, "render_ms": [], "soi_ms": []} for m in modes}
    try:
        for w in worlds.values():
            w.step(1.0)
        homes = next(iter(worlds.values())).mount_home_poses()
        seq = 0
        for phase in range(6):  # hanging, then moving in five steps of 0.4 s
            if phase:
                for w in worlds.values():
                    w.set_mount_targets(_moved(homes, phase / 5))
                    w.step(0.4)
            for m, w in worlds.items():
                rec = out[m_key(m)]
                t0 = time.process_time()
                frame = w.render_rgbd(seq)
                t1 = time.process_time()
                try:
                    rim, _ = trackers[m].update(frame, hint=w.mount_poses()["left"][:3, 3])
                except Exception as e:  # noqa: BLE001 - no rim found: counted
                    rec["failed"] += 1
                    log.debug("%s %s seed %d: %s", name, m, seed, e)
                    continue
                t2 = time.process_time()
                d = points_to_polyline_distance(rim, np.vstack([w.true_rim(), w.true_rim()[:1]]))
                rec["errors_mm"].append(float(np.sqrt(np.mean(d**2)) * 1e3))
                rec["max_mm"].append(float(d.max() * 1e3))
                rec["render_ms"].append((t1 - t0) * 1e3)
                rec["soi_ms"].append((t2 - t1) * 1e3)
            seq += 1
    finally:
        for w in worlds.values():
            w.close()
    return out


def m_key(m: tuple[int, int]) -> str:
    return f"{m[0]}x{m[1]}"


def run(quick: bool = False) -> dict[str, Any]:
    from bagit.bench.common import machine

    scenarios = SCENARIOS[:2] if quick else SCENARIOS
    seeds = (0,) if quick else (0, 1)
    per: dict[str, Any] = {}
    for name in scenarios:
        for seed in seeds:
            per[f"{name} s{seed}"] = measure_one(name, seed)
            rms = {k: round(float(np.mean(v["errors_mm"])), 2) if v["errors_mm"] else None for k, v in per[f"{name} s{seed}"].items()}
            log.info("%s seed %d: SOI RMS (mm) %s", name, seed, rms)
    summary = {}
    for m in MODES:
        k = m_key(m)
        e = [x for r in per.values() for x in r[k]["errors_mm"]]
        mx = [x for r in per.values() for x in r[k]["max_mm"]]
        summary[k] = {"rms_mm_mean": float(np.mean(e)), "rms_mm_p95": float(np.percentile(e, 95)), "max_mm": float(np.max(mx)),
                      "frames": len(e), "failed": sum(r[k]["failed"] for r in per.values()),
                      "render_ms_median": float(np.median([x for r in per.values() for x in r[k]["render_ms"]])),
                      "soi_ms_median": float(np.median([x for r in per.values() for x in r[k]["soi_ms"]]))}
    return {"machine": machine(), "load": [round(x, 2) for x in os.getloadavg()], "scenarios": list(scenarios), "seeds": list(seeds),
            "summary": summary, "per_run": {r: {k: {"rms_mm": v["errors_mm"], "failed": v["failed"]} for k, v in x.items()} for r, x in per.items()}}


def markdown(r: dict[str, Any]) -> str:
    m = r["machine"]
    lines = ["# SOI accuracy by camera mode (simulated D455)", "",
             f"commit {m['commit']}, host {m['host']}, {m['cpu']}, {m['cores']} cores, load {r['load']}; "
             f"scenarios {', '.join(r['scenarios'])}, seeds {r['seeds']}", "",
             "| mode | SOI RMS to the true rim, mean (mm) | p95 (mm) | worst point (mm) | frames | no rim found | render + noise (ms CPU) | SOI (ms CPU) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for k, s in r["summary"].items():
        lines.append(f"| {k} | {s['rms_mm_mean']:.2f} | {s['rms_mm_p95']:.2f} | {s['max_mm']:.1f} | {s['frames']} | {s['failed']} | "
                     f"{s['render_ms_median']:.1f} | {s['soi_ms_median']:.1f} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from bagit.bench.common import write_results

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--record", action="store_true", help="write bench/results/camera-modes.json and .md")
    a = ap.parse_args(argv)
    configure_logging()
    r = run(a.quick)
    md = markdown(r)
    if a.record:
        write_results("camera-modes", r, md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
