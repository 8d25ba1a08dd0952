"""The whole rig on the wall clock: `bagit up SCENARIO --clock wall` measured from its hub.

    python -m bagit.bench.up_wall [--quick] [--scenario exp02] [--seed 0] [--no-dashboard] [--json]

Starts the rig as `bagit up exp02 --clock wall --exit-when-done` does (`bagit.up.Up`: the
simulator, perception, planner, controller, arm driver and dashboard as child processes, camera
at its default rate), starts the run and follows it from the hub session:

- real-time factor: simulated seconds (the simulator's `sim/truth` clock) per wall second while
  the arms servo (pre-bagging and bagging), and over the whole run;
- watchdog stops and the other arm events of the run (the arm driver's counts on `arm/*/state`);
- frame -> command latency through the real `bagit perception` and `bagit controller` processes:
  each command carries its frame's stamp (`Command.source_stamp`), so its latency is its arrival
  here minus the arrival here of that frame on `camera/rgbd` (frame published -> command, as
  `bagit.bench.latency` measures it), and minus the stamp itself (image taken -> command: the
  render included); the first command of each frame only, keep-alives (a frame already acted on)
  are not timed;
- CPU seconds (user + system, from /proc) of each service while the arms servo, per simulated
  second, and over the whole life of the process.

Every record says the commit, host, CPU, load average before and after, and the effective
parameters (camera mode and rate, control rate, watchdog, services). Goal on 2 cores: real-time
factor >= 1.0, no watchdog stop, frame -> command p99 <= 30 ms.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import threading
import time
from typing import Any, Literal

import numpy as np

from bagit.common.logs import configure_logging
from bagit.common.names import FINAL_STAGES, SERVO_STAGES

log = logging.getLogger("bagit.bench.up_wall")

GOAL_P99_MS = 30.0
GOAL_REALTIME = 1.0


class _Timings:
    """Arrival times on the hub: frames by stamp, the first command per frame stamp."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.frames: dict[float, float] = {}
        self.cmds: dict[float, float] = {}
        self.modes: dict[str, int] = {}

    def on_frame(self, f: Any) -> None:
        now = time.time()
        with self.lock:
            self.frames.setdefault(float(f.stamp), now)

    def on_cmd(self, c: Any) -> None:
        now = time.time()
        with self.lock:
            self.modes[c.mode] = self.modes.get(c.mode, 0) + 1
            if c.source_stamp > 0 and c.run_id is not None:
                self.cmds.setdefault(float(c.source_stamp), now)

    def latency(self, since: float) -> dict[str, Any]:
        """ms from the frame's arrival (published) and from its stamp (taken) to its first command."""
        with self.lock:
            pairs = [(s, t, self.frames.get(s)) for s, t in self.cmds.items() if s >= since]
            n_frames = sum(1 for s in self.frames if s >= since)
        pub = [(t - f) * 1e3 for _, t, f in pairs if f is not None]
        taken = [(t - s) * 1e3 for s, t, _ in pairs]
        return {"frames": n_frames, "commands": len(pairs), "from_published": _pct(pub), "from_taken": _pct(taken)}


def _pct(x: list[float]) -> dict[str, Any]:
    if not x:
        return {"n": 0}
    a = np.asarray(x)
    return {"n": int(a.size), "p50_ms": float(np.percentile(a, 50)), "p90_ms": float(np.percentile(a, 90)),
            "p99_ms": float(np.percentile(a, 99)), "max_ms": float(a.max())}


def measure(scenario: str = "exp02", seed: int = 0, dashboard: bool = True, timeout_s: float = 600.0,
            clock: Literal["wall", "lockstep"] = "wall", fps: float | None = None) -> dict[str, Any]:
    """One `bagit up SCENARIO --clock wall` run, measured (see the module doc); `clock="lockstep"` measures a
    lockstep run the same way (its CPU per simulated second beside the wall clock's, at the same `fps`)."""
    from bagit.bench.common import machine
    from bagit.common.bus import Subscriber
    from bagit.common.messages import Command, RgbdFrame
    from bagit.common.params import MethodParams
    from bagit.common.rig import RigConfig
    from bagit.services.sim.rig_sim import camera_fps
    from bagit.up import SERVICES, Up, UpOptions

    services = tuple(s for s in SERVICES if dashboard or s != "dashboard")
    opts = UpOptions(scenario=scenario, seed=seed, clock=clock, services=services, fps=fps)
    rig = RigConfig()
    rate = MethodParams().controller.control_rate_hz  # the bundled scenarios' (no params: block)
    load_before = os.getloadavg()
    out: dict[str, Any] = {"machine": machine(), "load_before": [round(x, 2) for x in load_before]}
    out["params"] = {
        "scenario": scenario, "seed": seed, "clock": clock, "services": list(services),
        "camera": f"{rig.camera.width}x{rig.camera.height}", "control_rate_hz": rate,
        "camera_fps": camera_fps(opts.fps, clock == "lockstep", rate), "watchdog_s": rig.safety.watchdog_s,
        "servo_period_s": rig.safety.servo_period_s, "speed": opts.speed,
    }
    timings = _Timings()
    stop = threading.Event()
    sink = open(os.devnull, "w", encoding="utf-8")  # noqa: SIM115 - closed in the finally below
    up = Up(opts, log=sink, on_line=lambda who, text: log.debug("[%s] %s", who, text))  # the bench prints its numbers
    subs: list[Any] = []
    t_start = time.monotonic()
    try:
        up.start()
        subs = [Subscriber(up.session, up.keys.camera_rgbd, RgbdFrame, timings.on_frame),
                Subscriber(up.session, up.keys.controller_cmd, Command, timings.on_cmd)]
        missing = up.wait_ready()
        if missing:
            raise RuntimeError(f"services not up: {missing}")
        rep = up.start_run(scenario)
        if not rep.accepted:
            raise RuntimeError(f"run refused: {rep.reason}")
        run_id = rep.run_id
        marks: dict[str, Any] = {}
        deadline = time.monotonic() + timeout_s
        state = None
        while time.monotonic() < deadline:
            assert up.run_state is not None and up.truth is not None
            s = up.run_state.get()
            t = up.truth.get()
            if s is not None and s.run_id == run_id:
                if "run_start" not in marks and t is not None and t.run_id == run_id:
                    marks["run_start"] = (time.monotonic(), t.sim_time)
                if s.stage in SERVO_STAGES and "servo_start" not in marks and t is not None and t.run_id == run_id:
                    marks["servo_start"] = (time.monotonic(), t.sim_time, up.cpu_s(), time.time())
                if s.stage in FINAL_STAGES:
                    state = s
                    break
            time.sleep(0.05)
        t = up.truth.get() if up.truth is not None else None
        marks["end"] = (time.monotonic(), t.sim_time if t is not None else float("nan"), up.cpu_s())
        cpu_total = up.cpu_s()
        arm = up.arm_states.latest() if up.arm_states is not None else None
        events = dict(arm.events) if arm is not None else {}
    finally:
        for s in subs:
            s.close()
        up.stop()
        stop.set()
        sink.close()
    out["load_after"] = [round(x, 2) for x in os.getloadavg()]
    out["wall_s"] = round(time.monotonic() - t_start, 2)
    out["run"] = {"stage": state.stage if state else "timeout", "reason": state.reason if state else None,
                  "error_to_goal_m": (state.result or {}).get("error_to_goal_m") if state else None}
    out["arm_events"] = events
    out["watchdog_stops"] = int(events.get("watchdog_stops", 0))
    if "servo_start" in marks:
        w0, s0, c0, epoch0 = marks["servo_start"]
        w1, s1, c1 = marks["end"]
        sim_s, wall_s = s1 - s0, w1 - w0
        out["servo"] = {"sim_s": round(sim_s, 3), "wall_s": round(wall_s, 3), "realtime_factor": round(sim_s / wall_s, 3) if wall_s > 0 else None}
        out["cpu_s_per_sim_s"] = {n: round((c1.get(n, 0.0) - c0.get(n, 0.0)) / sim_s, 3) for n in c1} if sim_s > 0 else {}
        out["cpu_s_per_sim_s"]["total"] = round(sum(out["cpu_s_per_sim_s"].values()), 3)
        out["latency"] = timings.latency(epoch0)
    if "run_start" in marks:
        w0, s0 = marks["run_start"]
        w1, s1, _ = marks["end"]
        out["run"]["realtime_factor"] = round((s1 - s0) / (w1 - w0), 3) if w1 > w0 else None
    out["cpu_s_whole_life"] = cpu_total
    out["command_modes"] = dict(timings.modes)
    lat = out.get("latency", {}).get("from_published", {})
    out["goal"] = {
        "realtime_factor": (out.get("servo", {}).get("realtime_factor") or 0) >= GOAL_REALTIME,
        "no_watchdog_stop": out["watchdog_stops"] == 0,
        "p99_ms": lat.get("n", 0) > 0 and lat["p99_ms"] <= GOAL_P99_MS,
    }
    return out


def run(quick: bool = False) -> dict[str, Any]:
    """`bagit bench stages --only up_wall`: one run of exp02 (quick or not: a real run is the measurement)."""
    return measure("exp02", 0)


def markdown(r: dict[str, Any]) -> str:
    """A table from a record of `measure`."""
    from bagit.bench.common import metric_table

    lat = r.get("latency", {})
    rows = [
        ("run", f"{r['run']['stage']}" + (f" ({r['run']['reason']})" if r["run"].get("reason") else "")),
        ("real-time factor while servoing", r.get("servo", {}).get("realtime_factor")),
        ("real-time factor over the run", r["run"].get("realtime_factor")),
        ("watchdog stops", r["watchdog_stops"]),
        ("arm events", ", ".join(f"{k} {v}" for k, v in r["arm_events"].items())),
    ]
    for what in ("from_published", "from_taken"):
        x = lat.get(what, {})
        if x.get("n"):
            rows.append((f"frame {what.replace('_', ' ')} -> command p50 / p90 / p99 / max (ms, n)",
                         f"{x['p50_ms']:.1f} / {x['p90_ms']:.1f} / {x['p99_ms']:.1f} / {x['max_ms']:.1f} ({x['n']})"))
    cpu = r.get("cpu_s_per_sim_s", {})
    rows.append(("CPU s per simulated s while servoing", ", ".join(f"{k} {v:.3f}" for k, v in cpu.items())))
    rows.append(("CPU s over each process's life", ", ".join(f"{k} {v:.1f}" for k, v in r["cpu_s_whole_life"].items())))
    rows.append(("goals met", ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in r["goal"].items())))
    return metric_table(f"`bagit up --clock {r['params'].get('clock', 'wall')}`", r, rows)


def main(argv: list[str] | None = None) -> int:
    from bagit.bench.common import write_results

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="exp02")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-dashboard", action="store_true")
    ap.add_argument("--json", action="store_true", help="print the record as JSON")
    ap.add_argument("--record", action="store_true", help="write bench/results/up-wall-<time>.json and .md")
    a = ap.parse_args(argv)
    configure_logging()
    r = measure(a.scenario, a.seed, dashboard=not a.no_dashboard)
    md = markdown(r)
    if a.record:
        jp, mp = write_results(f"up-wall-{time.strftime('%Y%m%d-%H%M%S')}", r, md)
        log.info("written: %s, %s", jp, mp)
    print(json.dumps(r, indent=2) if a.json else md)
    return 0 if all(r["goal"].values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
