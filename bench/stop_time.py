"""How soon the arms are still after the last command, on the wall clock, against two simulated CR5s.

Both mounts stream at 4 cm/s along x (30 commands a second, alternately there and back), then:

  hold      the controller ends its stream with a hold command (`ArmDriver` in this process)
  silence   its commands just stop (`ArmDriver` in this process)
  sigkill   a controller process streaming on Zenoh to a `bagit arm-driver` process is SIGKILLed
            (the processes as `bagit up` runs them; the CR5s and a Zenoh peer in this process)

Per trial, from the last command (its submit; for sigkill its arrival at this process's peer) to:
  halt      the first braking ServoP at the controllers (the hold, or the watchdog's stop)
  servo     the last ServoP that moved a mount
  still     the first feedback packet below 1 mm/s of each controller, the later arm (the goal: 250 ms)

    python -m bagit.bench.stop_time [--trials 20] [--cases hold,silence,sigkill] [--record]

prints min / median / p95 / max per case with the machine's load, and with --record appends a record
(commit, host, load, parameters, every sample) to bench/results/stop-time.jsonl. `bagit bench stages
--only stop_time` runs the in-process cases briefly.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bagit.bench.common import RESULTS_DIR
from bagit.common.logs import configure_logging
from bagit.common.messages import Command
from bagit.common.results import provenance
from bagit.common.rig import ARMS, ArmName
from bagit.harness import ENV, stop_process, wait_until
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.sim.harness import FeedbackRecorder, RecordingServer, SimPair, servo_parameter, servo_positions, start_sims

if TYPE_CHECKING:
    from bagit.services.arm_driver.driver import ArmDriver

log = logging.getLogger("bagit.bench.stop_time")

V0 = 0.04  # m/s, both mounts along x (the controller's increments stay below 5 cm/s per axis)
RATE = 30.0  # commands per second
STREAM_S = 0.6  # how long each trial streams before the end
STILL_MM_S = 1.0  # "still": the controller's feedback TCP speed below this
TARGET_S = 0.25  # the goal (issue 25): still within 250 ms of the last command
CASES = ("hold", "silence", "sigkill")
RUN_ID = "stop-time"
CFG = DriverConfig(feedback_timeout_s=0.5)  # a loaded machine can stall the simulated feedback a while
JSONL = RESULTS_DIR / "stop-time.jsonl"


def increment(direction: float) -> np.ndarray:
    """One command's increment: both mounts `direction` (+1 or -1) along x at V0."""
    u = np.zeros(12)
    u[0] = u[6] = direction * V0 / RATE
    return u


def still_after(rec: dict[ArmName, FeedbackRecorder], last: float, horizon: float = 2.0) -> float:
    """Seconds from `last` until both arms' feedback is below STILL_MM_S for good (the later arm)."""
    out = []
    for a in ARMS:
        tf, speed = rec[a].series("TCPSpeedActual", last, last + horizon)
        v = np.linalg.norm(speed[:, :3], axis=1)
        moving = np.flatnonzero(v >= STILL_MM_S)
        if moving.size == len(v):
            raise RuntimeError(f"{a}: still moving {horizon:g} s after the last command")
        out.append(tf[moving[-1] + 1] - last if moving.size else tf[0] - last)
    return float(max(out))


def servo_times(servers: dict[ArmName, RecordingServer], last: float, halt_aheadtime: float) -> tuple[float, float]:
    """(first braking ServoP, last ServoP that moved a mount), seconds after `last`, the later arm.
    A braking ServoP is one sent with the halting aheadtime (`DriverConfig.servo_params`)."""
    halt, moved = [], []
    for srv in servers.values():
        braking = [t for t, text, reply in srv.commands("ServoP")
                   if t > last and reply.startswith("0,") and servo_parameter(text, "aheadtime") == halt_aheadtime]
        halt.append(braking[0] - last if braking else np.nan)
        ts, xyz = servo_positions(srv, last - 0.2, last + 2.0)
        steps = ts[1:][np.linalg.norm(np.diff(xyz, axis=0), axis=1) > 1e-6]
        moved.append(steps[-1] - last if steps.size else 0.0)
    return float(max(halt)), float(max(moved))


def driver_trials(end: str, trials: int, disturbed: list[str] | None = None) -> list[dict[str, float]]:
    """`end` 'hold' or 'silence' against an ArmDriver in this process: per trial, `still_s`, `halt_s`,
    `servo_s` and the servo loop's `stall_s` meanwhile (cycles a loaded machine started late).

    A trial the machine disturbed is redone, with why appended to `disturbed`: a command refused (made
    longer than the watchdog before the driver saw it: this process was starved), a servo loop stalled
    past the watchdog (the driver dropped the trajectory, so there is no braking to time) or a link lost
    (a feedback time-out). Each is the driver's protection doing its job, not the stop being measured;
    RuntimeError if the disturbed attempts outnumber 3 x `trials`."""
    from bagit.services.arm_driver.driver import ArmDriver

    disturbed = [] if disturbed is None else disturbed
    sims = start_sims()
    drv = ArmDriver(sims.rig, CFG)
    rec = {a: FeedbackRecorder(s.feedback_port) for a, s in sims.servers.items()}
    out: list[dict[str, float]] = []
    try:
        drv.start()
        attempt = 0
        while len(out) < trials:
            if len(disturbed) > 3 * trials:
                raise RuntimeError(f"the machine disturbed {len(disturbed)} trials: {disturbed}")
            row, why = _driver_trial(drv, sims, rec, end, attempt)
            attempt += 1
            if why is None:
                out.append(row)
                continue
            disturbed.append(why)
            log.info("trial %d disturbed, redone: %s", attempt, why)
            wait_until(lambda: drv.mode not in ("streaming", "stopping", "restarting", "link_down"), 10.0)
            if drv.status()["fault"] is not None:
                drv.clear_fault()
            if not wait_until(lambda: drv.mode == "holding", 10.0):
                raise RuntimeError(f"the driver did not recover from a disturbed trial ({why}): {drv.status()}")
    finally:
        for r in rec.values():
            r.close()
        drv.close()
        sims.close()
    return out


def _driver_trial(drv: ArmDriver, sims: SimPair, rec: dict[ArmName, FeedbackRecorder], end: str,
                  trial: int) -> tuple[dict[str, float], str | None]:
    """One stream and its end: the row, and why the machine disturbed it (None: it did not)."""
    u = increment(1.0 if trial % 2 == 0 else -1.0)  # there and back: the arms stay near home
    stalls = drv.counters["stalls"]
    t0, k, last = time.monotonic(), 0, 0.0
    while k / RATE < STREAM_S:
        time.sleep(max(0.0, t0 + k / RATE - time.monotonic()))
        last = time.monotonic()
        if not drv.submit(Command(u=u, dt=1 / RATE, seq=1000 * trial + k)):
            return {}, f"a command refused: {drv.last_refusal}"
        k += 1
    if end == "hold":
        time.sleep(max(0.0, t0 + k / RATE - time.monotonic()))
        last = time.monotonic()
        drv.submit(Command(u=np.zeros(12), mode="hold", reason="done", seq=1000 * trial + k))
    if not wait_until(lambda: drv.mode not in ("streaming", "stopping"), 3.0):
        raise RuntimeError(f"the driver did not come to rest: {drv.mode}")
    time.sleep(0.3)
    if drv.mode != "holding":
        return {}, f"the driver is {drv.mode}: {drv.status()['fault']}"
    if drv.counters["stalls"] > stalls:
        return {}, "the servo loop stalled past the watchdog"
    still = still_after(rec, last)
    halt, servo = servo_times(sims.servers, last, CFG.halt_aheadtime)
    return {"still_s": still, "halt_s": halt, "servo_s": servo, "stall_s": loop_stall(drv, last, last + still)}, None


def loop_stall(drv: Any, t0: float, t1: float) -> float:
    """Seconds the servo loop lost to a loaded machine between t0 and t1 (cycles that started late)."""
    starts = np.array([t for t in drv.cycle_starts if t0 - drv.period <= t <= t1 + drv.period])
    gaps = np.diff(starts)
    return float(np.sum(np.clip(gaps - drv.period, 0.0, None)[gaps > 1.2 * drv.period]))


def stand_in_controller(connect: str, rig: str, direction: float) -> None:
    """A controller process's stream, until it is killed: increments for RUN_ID at RATE on controller/cmd."""
    from bagit.common.bus import BusConfig, Keys, Publisher, open_session

    session = open_session(BusConfig(rig=rig, connect=[connect]))
    pub = Publisher(session, Keys(rig).controller_cmd, Command)
    wait_until(lambda: pub.matched, 10.0)
    u, k, t0 = increment(direction), 0, time.monotonic()
    while True:
        time.sleep(max(0.0, t0 + k / RATE - time.monotonic()))
        pub.put(Command(u=u, dt=1 / RATE, seq=k, run_id=RUN_ID))
        k += 1


def sigkill_trials(trials: int, workdir: Path) -> list[dict[str, float]]:
    """A `bagit arm-driver` process and, per trial, a controller process that streams and is SIGKILLed."""
    from bagit.common.bus import BusConfig, Keys, LatestCache, Publisher, Subscriber, locators, open_session
    from bagit.common.messages import ArmState, RunState

    sims = start_sims()
    rig = sims.rig.model_copy(update={"name": "stoptime"})
    keys = Keys(rig.name)
    (workdir / "rig.yaml").write_text(rig.to_yaml())
    (workdir / "arm-driver.yaml").write_text(f"rig_config: rig.yaml\ndriver:\n  feedback_timeout_s: {CFG.feedback_timeout_s}\n")
    hub = open_session(BusConfig(rig=rig.name, adminspace=True))
    connect = locators(hub)[0]
    rec = {a: FeedbackRecorder(s.feedback_port) for a, s in sims.servers.items()}
    cmds: list[float] = []
    Subscriber(hub, keys.controller_cmd, Command, lambda c: cmds.append(time.monotonic()))
    states = LatestCache(hub, keys.arm_state_any, ArmState)
    run_pub = Publisher(hub, keys.run_state, RunState)
    stop = threading.Event()

    def coordinator() -> None:  # the run, servoing, at 2 Hz as `bagit planner` publishes it
        while not stop.wait(0.5):
            run_pub.put(RunState(run_id=RUN_ID, stage="bagging"))

    threading.Thread(target=coordinator, daemon=True).start()
    err = open(workdir / "arm-driver.log", "w")
    driver = subprocess.Popen([sys.executable, "-m", "bagit.cli", "arm-driver", "--config", str(workdir / "arm-driver.yaml"),
                               "-e", connect], stdout=err, stderr=err, env=ENV)
    out = []
    try:
        if not wait_until(lambda: len(states.items()) == 2, 60.0, 0.05):
            raise RuntimeError(f"bagit arm-driver not up: {(workdir / 'arm-driver.log').read_text()[-2000:]}")
        for trial in range(trials):
            n0 = len(cmds)
            ctl = subprocess.Popen([sys.executable, "-m", "bagit.bench.stop_time", "--stand-in", connect, rig.name,
                                    str(1.0 if trial % 2 == 0 else -1.0)], env=ENV)
            try:
                def streaming(n0: int = n0) -> bool:
                    return len(cmds) > n0 and _speed(rec) > 0.5 * V0 * 1000

                moving = wait_until(streaming, 30.0, 0.01)
                if not moving:
                    raise RuntimeError(f"trial {trial}: the stand-in controller's commands do not move the arms")
                time.sleep(STREAM_S - 0.2)
            finally:
                ctl.send_signal(signal.SIGKILL)
                ctl.wait(10)
            time.sleep(0.8)
            last = cmds[-1]
            still = still_after(rec, last)
            halt, servo = servo_times(sims.servers, last, CFG.halt_aheadtime)
            out.append({"still_s": still, "halt_s": halt, "servo_s": servo})
            wait_until(lambda: _speed(rec) < STILL_MM_S, 3.0, 0.02)
    finally:
        stop.set()
        stop_process(driver)
        err.close()
        for r in rec.values():
            r.close()
        hub.close()
        sims.close()
    return out


def _speed(rec: dict[ArmName, FeedbackRecorder]) -> float:
    """Both arms' newest feedback TCP speed (mm/s), the faster."""
    v = 0.0
    for r in rec.values():
        _, speed = r.series("TCPSpeedActual", time.monotonic() - 0.05)
        if len(speed):
            v = max(v, float(np.linalg.norm(speed[-1][:3])))
    return v


def summary(samples_s: list[float]) -> dict[str, float]:
    """n, min, median, p95, max (ms) of samples in seconds."""
    a = np.asarray(samples_s, dtype=float) * 1000.0
    a = a[np.isfinite(a)]
    if not a.size:
        return {"n": 0}
    return {"n": int(a.size), "min_ms": float(a.min()), "median_ms": float(np.median(a)),
            "p95_ms": float(np.percentile(a, 95)), "max_ms": float(a.max())}


def measure(cases: tuple[str, ...], trials: int) -> dict[str, Any]:
    """Every case's trials and their summary, with the machine's load before and after."""
    load_before = os.getloadavg()
    out: dict[str, Any] = {}
    for case in cases:
        t0 = time.monotonic()
        disturbed: list[str] = []
        if case == "sigkill":
            with tempfile.TemporaryDirectory(prefix="bagit-stop-time-") as d:
                rows = sigkill_trials(trials, Path(d))
        else:
            rows = driver_trials(case, trials, disturbed)
        out[case] = {key: summary([r[key + "_s"] for r in rows]) for key in ("still", "halt", "servo")}
        out[case]["samples"] = rows
        out[case]["disturbed"] = disturbed
        out[case]["within_target"] = sum(r["still_s"] <= TARGET_S for r in rows)
        log.info("%s: %d trials in %.0f s", case, len(rows), time.monotonic() - t0)
    return {"cases": out, "load_avg": {"before": list(load_before), "after": list(os.getloadavg())}}


def params() -> dict[str, Any]:
    """What the numbers depend on: the stream, the threshold, the driver's limits and halting settings."""
    from bagit.common.rig import SafetyLimits

    lim = SafetyLimits()
    return {"v0_mps": V0, "rate_hz": RATE, "stream_s": STREAM_S, "still_mm_s": STILL_MM_S, "target_s": TARGET_S,
            "watchdog_s": lim.watchdog_s, "servo_period_s": lim.servo_period_s, "max_tcp_accel_mps2": lim.max_tcp_accel_mps2,
            "max_tcp_jerk_mps3": lim.max_tcp_jerk_mps3, "aheadtime": CFG.aheadtime, "halt_aheadtime": CFG.halt_aheadtime,
            "gain": CFG.gain, "niceness": os.nice(0)}


def record(result: dict[str, Any], path: Path = JSONL) -> Path:
    """Append one record (commit, host, load, parameters, every sample) to `path`."""
    rec = {"kind": "stop_time", "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
           "provenance": provenance(params()).model_dump(), **result}
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", encoding="utf-8") as f:
        f.write(json.dumps(rec) + "\n")
    return path


def report(result: dict[str, Any]) -> str:
    """The numbers, one line per case and measure, with the machine's load."""
    la = result["load_avg"]
    lines = [f"load average {la['before'][0]:.1f} before, {la['after'][0]:.1f} after, on {os.cpu_count()} cores; "
             f"from the last command, ms (goal: still within {TARGET_S * 1000:.0f})"]
    for case, r in result["cases"].items():
        for key in ("still", "halt", "servo"):
            s = r[key]
            if s["n"]:
                lines.append(f"{case:8s} {key:6s} n={s['n']:3d}  min {s['min_ms']:6.1f}  median {s['median_ms']:6.1f}  "
                             f"p95 {s['p95_ms']:6.1f}  max {s['max_ms']:6.1f}")
        lines.append(f"{case:8s} still within {TARGET_S * 1000:.0f} ms: {r['within_target']}/{len(r['samples'])}"
                     f"{'; redone, disturbed by the machine: ' + str(len(r['disturbed'])) if r['disturbed'] else ''}")
    return "\n".join(lines)


def run(quick: bool = False) -> dict[str, Any]:
    """For `bagit bench stages`: the in-process cases, 5 trials each (--quick: 3)."""
    result = measure(("hold", "silence"), 3 if quick else 5)
    return {case: {k: v for k, v in r.items() if k != "samples"} for case, r in result["cases"].items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--trials", type=int, default=20, help="trials per case (default 20)")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated, of {', '.join(CASES)}")
    ap.add_argument("--record", action="store_true", help=f"append the record to {JSONL}")
    ap.add_argument("--stand-in", nargs=3, metavar=("CONNECT", "RIG", "DIRECTION"), help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.stand_in:
        stand_in_controller(args.stand_in[0], args.stand_in[1], float(args.stand_in[2]))
        return
    configure_logging()
    cases = tuple(c for c in args.cases.split(",") if c)
    unknown = sorted(set(cases) - set(CASES))
    if unknown or args.trials < 1:
        ap.error(f"unknown case(s) {unknown}; choose from {', '.join(CASES)}" if unknown else "--trials must be >= 1")
    result = measure(cases, args.trials)
    log.info("%s", report(result))
    if args.record:
        log.info("record appended to %s", record(result))


if __name__ == "__main__":
    main()
