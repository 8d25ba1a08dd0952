"""The arm driver's cycle: what it costs to turn the controller's increments into two ServoP commands.

Offline (no sockets), per servo period for both arms:
  ruckig      one 12-DoF Ruckig update alone (the driver's limits, a target moving every cycle)
  pipeline    targets -> 12-DoF Ruckig step -> safety gate (check_and_clip)
  format      mount pose -> flange in each base -> Dobot pose6 -> `ServoP(...)` text
  reach       the driver's IK check of both targets (bagit.common.cr5.ik, on by default)
  cycle       all of it, as the servo loop runs it (steady 30 Hz stream of increments)
Live, against two simulated CR5 controllers on loopback:
  loop        the driver's measured compute per cycle, and the interval between its ServoPs
  estop       from `estop()` to each controller logging EmergencyStop(1)

    python -m bagit.bench.arm_driver [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bagit.bench.common import stats_ms, timeit
from bagit.common import cr5
from bagit.common.dual_arm import Poses
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.services.arm_driver.client import DobotClient
from bagit.services.arm_driver.frames import ArmFrames
from bagit.services.arm_driver.servo_path import ServoPath
from bagit.services.arm_driver.smoothing import N_DOF, RuckigSmoother
from bagit.services.sim.harness import home_poses

PERIOD = 0.03


def _ruckig(n: int) -> dict:
    """One Ruckig update of the 12 axes, as the streamer calls it: its per-axis limits, time
    synchronisation, and a target that moves each cycle (a streamed command never lets it finish)."""
    from ruckig import InputParameter, OutputParameter, Result, Ruckig, Synchronization

    limits = RuckigSmoother(RigConfig().safety, PERIOD)  # the driver's per-axis limits, nothing else of it
    otg, inp, out = Ruckig(N_DOF, PERIOD), InputParameter(N_DOF), OutputParameter(N_DOF)
    inp.max_velocity = limits.max_velocity.tolist()
    inp.max_acceleration = limits.max_acceleration.tolist()
    inp.max_jerk = limits.max_jerk.tolist()
    inp.synchronization = Synchronization.Time
    inp.current_position = [0.0] * N_DOF
    amplitude = np.tile([0.04, 0.04, 0.02, 0.1, 0.1, 0.1], 2)
    state = {"k": 0}

    def update() -> None:
        k = state["k"]
        inp.target_position = (amplitude * np.sin(k / 40 + np.arange(N_DOF))).tolist()
        if otg.update(inp, out) not in (Result.Working, Result.Finished):
            raise RuntimeError("ruckig refused the benchmark's input")
        out.pass_to_input(inp)
        state["k"] += 1

    return timeit(update, n)


def _offline(n: int) -> dict:
    rig = RigConfig()
    pipe = ServoPath(rig)  # its targets, smoothing and limits (`tick`); reach and wire timed apart below
    pipe.reset(home_poses())
    frames = {a: ArmFrames.from_config(rig.arms[a]) for a in ARMS}
    seeds = {}
    for a in ARMS:
        T_bf = frames[a].flange_in_base(home_poses()[a])
        seeds[a] = cr5.ik_all(T_bf)[0]
    state = {"k": 0, "now": 0.0}

    def u_at(k: int) -> np.ndarray:
        u = np.zeros(12)
        u[0] = u[6] = 0.04 * np.sin(k / 40) / 30  # back and forth along x, 4 cm/s peak
        u[2] = u[8] = 0.02 * np.cos(k / 25) / 30
        u[5] = 0.1 * np.sin(k / 50) / 30
        return u

    def pipeline_step() -> Poses:
        k = int(state["k"])  # (a count: the dict holds the clock's float too)
        pipe.submit(u_at(k), 1 / 30, state["now"])
        tick = pipe.tick(state["now"])
        state["k"] += 1
        state["now"] += PERIOD
        if tick.command is None:
            raise RuntimeError("the motion pipeline gave no poses for a streamed period")
        return tick.command

    last = {"cmd": pipeline_step()}

    def fmt() -> None:
        for a in ARMS:
            T_bf = frames[a].flange_in_base(last["cmd"][a])
            DobotClient.servo_text("ServoP", cr5.matrix_to_pose6(T_bf), PERIOD, 50, 500)

    def reach() -> None:
        for a in ARMS:
            q = cr5.ik(frames[a].flange_in_base(last["cmd"][a]), seeds[a])
            if q is not None:
                seeds[a] = q

    def cycle() -> None:
        last["cmd"] = pipeline_step()
        reach()
        fmt()

    return {
        "ruckig": _ruckig(n),
        "pipeline": timeit(lambda: last.__setitem__("cmd", pipeline_step()), n),
        "format": timeit(fmt, n),
        "reach": timeit(reach, n),
        "cycle": timeit(cycle, n),
    }


def _live(seconds: float, estops: int) -> dict:
    """The running driver against two simulated controllers (imports the simulator only here)."""
    from bagit.common.messages import Command
    from bagit.services.arm_driver.config import DriverConfig
    from bagit.services.arm_driver.driver import ArmDriver
    from bagit.services.sim.harness import start_sims

    sims = start_sims()
    rig, servers = sims.rig, sims.servers
    latency: dict[ArmName, list[float]] = {a: [] for a in ARMS}
    try:
        drv = ArmDriver(rig, DriverConfig(feedback_timeout_s=0.5)).start()
        try:
            drv.cycle_ms.clear()
            drv.send_times.clear()
            t0, k = time.monotonic(), 0
            while time.monotonic() - t0 < seconds:
                u = np.zeros(12)
                u[0] = u[6] = 0.04 * np.sin(k / 40) / 30
                drv.submit(Command(u=u, dt=1 / 30, seq=k))
                k += 1
                time.sleep(max(0.0, t0 + k / 30 - time.monotonic()))
            cycle = stats_ms(list(drv.cycle_ms))
            period = stats_ms(np.diff(np.array(drv.send_times)) * 1000.0)
            for _ in range(estops):
                t_call = time.monotonic()
                drv.estop("bench")
                for a in ARMS:
                    latency[a].append((servers[a].commands("EmergencyStop")[-1][0] - t_call) * 1000.0)
                drv.reset_estop()
                time.sleep(0.05)
        finally:
            drv.close()
    finally:
        sims.close()
    return {"loop_cycle": cycle, "servo_interval": period, **{f"estop_{a}": stats_ms(latency[a]) for a in ARMS}}


def run(quick: bool = False) -> dict:
    offline = _offline(300 if quick else 2000)
    ratios = {f"{k}_over_ruckig": offline[k]["median_ms"] / offline["ruckig"]["median_ms"] for k in ("pipeline", "cycle")}
    return {"offline": offline, "ratios": ratios, "live": _live(2.0 if quick else 6.0, 3 if quick else 10)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    r = run(ap.parse_args().quick)
    for group in ("offline", "live"):
        for name, s in r[group].items():
            print(f"{group}.{name}: min {s['min_ms']:.3f} / median {s['median_ms']:.3f} / p95 {s['p95_ms']:.3f} ms (n={s['n']})")
    for name, v in r["ratios"].items():
        print(f"{name}: {v:.2f}x (medians)")


if __name__ == "__main__":
    main()
