"""Where the time goes from the last command to the arms at rest: the watchdog's stop on a virtual clock.

No sockets, threads or wall clock: `bagit run`'s arm side (`app/sim_arms.Cr5Arms`: the arm driver's
`ServoPath` and watchdog, its ServoPs handed to two simulated CR5s in process), commands every 1/30 s,
servo cycles every 30 ms from a chosen phase, the controllers stepped every 2 ms. The stream rests
(zero increments, the controller's keep-alives), then `moving` commands ask both mounts for `speed`
along a direction, then nothing comes: the watchdog stops the arms. In ms after the last command:

  watchdog  the cycle that starts the stop (its ServoPs are the first braking ones)
  rest      the trajectory at rest: the last ServoP that moved a mount, plus its t (the controllers'
            reference gets there then)
  still     both arms' feedback below STILL_MM_S for good (the goal: TARGET_S, 250 ms; issue 36)

and the fastest either arm went after the last command, the most a joint accelerated (the simulated
CR5 never goes past `cr5.JOINT_ACCEL_LIMIT`: at it, the arm could not follow the stop), and the step of
each braking ServoP (a stop never speeds the arms up after its first ServoP). Each case is run at
several phases of the servo cycle against the commands; the worst is reported.

    python -m bagit.bench.stop_timeline [--compare] [--record]

prints one line per case, and with --record appends them (commit, host, load, parameters) to
bench/results/stop-timeline.jsonl. `--compare` also runs every case with a stop at the path's limits
(the stop before it had its own). Deterministic: the machine's load changes nothing.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from typing import Any

import numpy as np

from bagit.bench.common import RESULTS_DIR
from bagit.bench.stop_time import RATE, STILL_MM_S, TARGET_S
from bagit.common.logs import configure_logging
from bagit.common.messages import Command
from bagit.common.results import provenance
from bagit.common.rig import ARMS, RigConfig
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.sim.cr5_sim import SUBSTEP_S

log = logging.getLogger("bagit.bench.stop_timeline")

REST = 10  # zero increments before the motion
HORIZON_S = 1.0  # how long after the last command the controllers are watched
PHASES_S = (0.0, 0.006, 0.012, 0.018, 0.024)  # the first servo cycle's offset against the first command
X, DIAGONAL = (1.0, 0.0, 0.0), (1.0, 1.0, 1.0)
# name -> (speed asked, m/s; direction; commands that ask it): the last command starts the motion from rest
# asking more than the path gives (its limits decide), the same a command later, and stops from a steady speed
CASES: dict[str, tuple[float, tuple[float, float, float], int]] = {
    "from rest, x": (1.0, X, 1),
    "from rest, diagonal": (1.0, DIAGONAL, 1),
    "second command, diagonal": (1.0, DIAGONAL, 2),
    "4 cm/s, x": (0.04, X, 20),
    "0.1 m/s, diagonal": (0.1, DIAGONAL, 20),
    "0.25 m/s, diagonal": (1.0, DIAGONAL, 30),
}
JSONL = RESULTS_DIR / "stop-timeline.jsonl"


def virtual_stop(speed: float, direction: tuple[float, float, float], moving: int, phase_s: float = 0.0,
                 rig: RigConfig | None = None, cfg: DriverConfig | None = None) -> dict[str, Any]:
    """One stream that stops (see the module docstring): the timeline in ms after the last command
    (`watchdog_ms`, `rest_ms`, `still_ms`), `peak_mm_s`, `joint_accel_rps2`, and `steps_mm`: the mounts'
    step (the larger arm's) of the last tracking ServoP, then of each braking one."""
    from bagit.services.sim.harness import home_poses, home_robot
    from bagit.sim_arms import Cr5Arms

    rig = rig or RigConfig()
    robots = {a: home_robot(rig, a, p) for a, p in home_poses().items()}

    def step(dt: float) -> None:
        for r in robots.values():
            r.step(dt)

    arms = Cr5Arms(rig, robots, step, cfg)
    arms.start()
    path, period = arms.path, arms.period
    d = np.asarray(direction, dtype=float) / np.linalg.norm(direction)
    u = np.zeros(12)
    u[:3] = u[6:9] = d * speed / RATE
    cmds = [np.zeros(12)] * REST + [u] * moving
    h, n_cmd, n_cycle, k = SUBSTEP_S, 0, 0, 0
    last = watchdog = None
    sent: list[tuple[float, float, bool, bool]] = []  # per cycle that sent: (time, the larger step (m), moved, braking)
    speeds: list[tuple[float, float]] = []
    qd_prev = {a: np.radians(robots[a].fill_feedback()["QDActual"]) for a in ARMS}
    joint_acc = 0.0
    while last is None or k * h < last + HORIZON_S:
        t = k * h
        while n_cmd < len(cmds) and n_cmd / RATE <= t + 1e-9:
            arms.submit(Command(u=cmds[n_cmd], dt=1 / RATE, seq=n_cmd), t)
            n_cmd += 1
            last = t if n_cmd == len(cmds) else None
        if phase_s + n_cycle * period <= t + 1e-9:
            stops, before = path.counters["watchdog_stops"], path.last_sent
            arms.servo(t)
            n_cycle += 1
            if path.counters["watchdog_stops"] > stops:
                watchdog = t
            now_sent = path.last_sent
            if before is not None and now_sent is not None and now_sent is not before:  # this cycle's ServoPs went out
                dist = max(float(np.linalg.norm(now_sent[a][:3, 3] - before[a][:3, 3])) for a in ARMS)
                moved = any(not np.allclose(now_sent[a], before[a], rtol=0.0, atol=1e-12) for a in ARMS)
                sent.append((t, dist, moved, watchdog is not None))
        arms.step(h)
        k += 1
        recs = {a: robots[a].fill_feedback() for a in ARMS}
        speeds.append((k * h, max(float(np.linalg.norm(r["TCPSpeedActual"][:3])) for r in recs.values())))
        qd = {a: np.radians(recs[a]["QDActual"]) for a in ARMS}
        if last is not None:
            joint_acc = max(joint_acc, *(float(np.abs(qd[a] - qd_prev[a]).max()) / h for a in ARMS))
        qd_prev = qd
    if arms.fault is not None:
        raise RuntimeError(f"the arms faulted: {arms.fault}")
    assert last is not None
    ts, v = np.array(speeds).T
    since = ts >= last
    moving_at = np.flatnonzero(since & (v >= STILL_MM_S))
    if moving_at.size and moving_at[-1] + 1 >= len(ts):
        raise RuntimeError(f"still moving {HORIZON_S:g} s after the last command")
    still = ts[moving_at[-1] + 1] if moving_at.size else last
    ms = lambda x: None if x is None else round(1000.0 * (x - last), 1)  # noqa: E731
    moves = [t for t, _, moved, _ in sent if moved]
    tracking = [step for _, step, _, braking in sent if not braking]
    braking = [step for _, step, moved, braking in sent if braking and moved]
    return {"watchdog_ms": ms(watchdog), "rest_ms": ms(moves[-1] + path.servo_t if moves else None), "still_ms": ms(still),
            "peak_mm_s": round(float(v[since].max()), 1), "joint_accel_rps2": round(joint_acc, 2),
            "steps_mm": [round(1000.0 * x, 3) for x in tracking[-1:] + braking]}


def worst_phase(speed: float, direction: tuple[float, float, float], moving: int, rig: RigConfig | None = None,
                cfg: DriverConfig | None = None) -> dict[str, Any]:
    """`virtual_stop` at every phase of PHASES_S; the one whose arms were still last, with every phase's `still_ms`."""
    runs = [virtual_stop(speed, direction, moving, p, rig, cfg) for p in PHASES_S]
    worst = max(runs, key=lambda r: r["still_ms"])
    return {**worst, "phase_ms": round(1000.0 * PHASES_S[runs.index(worst)], 1), "still_ms_by_phase": [r["still_ms"] for r in runs]}


def stopping_at_the_path_limits(rig: RigConfig) -> RigConfig:
    """`rig` with its stop's acceleration and jerk the path's: how the arms stopped before the stop had its own."""
    lim = rig.safety
    same = {"stop_tcp_accel_mps2": lim.max_tcp_accel_mps2, "stop_tcp_jerk_mps3": lim.max_tcp_jerk_mps3,
            "stop_angular_accel_rps2": lim.max_angular_accel_rps2, "stop_angular_jerk_rps3": lim.max_angular_jerk_rps3}
    return rig.model_copy(update={"safety": lim.model_copy(update=same)})


def params(rig: RigConfig, cfg: DriverConfig) -> dict[str, Any]:
    """What the numbers depend on: the stream, the threshold, the limits and the halting servo settings."""
    lim = rig.safety
    return {"rate_hz": RATE, "rest_commands": REST, "phases_s": list(PHASES_S), "still_mm_s": STILL_MM_S, "target_s": TARGET_S,
            "watchdog_s": lim.watchdog_s, "servo_period_s": lim.servo_period_s, "path_limits": lim.path_limits().tolist(),
            "stop_limits": lim.stop_limits().tolist(), "aheadtime": cfg.aheadtime, "halt_aheadtime": cfg.halt_aheadtime,
            "gain": cfg.gain, "substep_s": SUBSTEP_S, "cases": {k: list(v) for k, v in CASES.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--compare", action="store_true", help="also with a stop at the path's limits")
    ap.add_argument("--record", action="store_true", help=f"append the record to {JSONL}")
    args = ap.parse_args()
    configure_logging()
    rig, cfg = RigConfig(), DriverConfig()
    stops = {"stop limits": rig} | ({"path limits": stopping_at_the_path_limits(rig)} if args.compare else {})
    out = {label: {name: worst_phase(*case, rig=r, cfg=cfg) for name, case in CASES.items()} for label, r in stops.items()}
    log.info("ms after the last command (worst of %d phases; goal: still within %.0f ms)", len(PHASES_S), TARGET_S * 1000)
    for label, cases in out.items():
        for name, r in cases.items():
            log.info("%-11s %-26s watchdog %4.0f  rest %4.0f  still %4.0f | peak %5.1f mm/s, joints %4.1f rad/s^2, braking steps %s mm",
                     label, name, r["watchdog_ms"], r["rest_ms"], r["still_ms"], r["peak_mm_s"], r["joint_accel_rps2"], r["steps_mm"])
    if args.record:
        rec = {"kind": "stop_timeline", "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
               "provenance": provenance(params(rig, cfg)).model_dump(), "results": out}
        with JSONL.open("a", encoding="utf-8") as f:
            f.write(json.dumps(rec) + "\n")
        log.info("record appended to %s", JSONL)


if __name__ == "__main__":
    main()
