"""CR5 kinematics and the simulated controllers: fk/ik cost, controller step cost, dashboard round
trips and the feedback period over loopback, and the whole rig's real-time factor with the arms
servoing the mounts (with and without the camera at 15 frames per simulated second).

    python -m bagit.bench.cr5 [--quick]
"""

from __future__ import annotations

import argparse
import socket
import time

import numpy as np

from bagit.bench.common import stats_ms, timeit
from bagit.common import cr5, dobot
from bagit.services.sim.cr5_sim import SimulatedCR5
from bagit.services.sim.dobot_server import DobotControllerServer


def _kinematics(n: int) -> dict:
    rng = np.random.default_rng(0)
    qs = rng.uniform(-2.5, 2.5, (n, 6))
    qs[:, 2] = rng.uniform(-2.6, 2.6, n)
    Ts = [cr5.fk(q) for q in qs]
    it = iter(range(10**9))
    return {
        "fk": timeit(lambda: cr5.fk(qs[next(it) % n]), n),
        "ik_nearest": timeit(lambda: cr5.ik(Ts[(k := next(it) % n)], qs[k] + 0.05), n),
        "ik_all": timeit(lambda: cr5.ik_all(Ts[next(it) % n]), n),
        "self_collision": timeit(lambda: cr5.self_collision(qs[next(it) % n]), n),
    }


def _controller_step(n: int) -> dict:
    a = SimulatedCR5()
    a.enable()
    p0 = a.get_pose6()
    k = iter(range(10**9))

    def servo_and_step() -> None:
        i = next(k)
        a.servo_p(p0 + [0, 30 * np.sin(i / 30), 20 * np.sin(i / 45), 0, 0, 0], t=0.03)
        a.step(0.03)

    return {"step_4ms_idle": timeit(lambda: a.step(0.004), n), "servo_p_then_step_30ms": timeit(servo_and_step, n // 4)}


def _loopback(n: int, seconds: float) -> dict:
    srv = DobotControllerServer(SimulatedCR5(), dashboard_port=0, feedback_port=0, step_in_background=True).start()
    try:
        c = socket.create_connection(("127.0.0.1", srv.dashboard_port), timeout=2.0)
        c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

        def ask(text: str) -> None:
            c.sendall(text.encode())
            buf = b""
            while not buf.endswith(b";"):
                buf += c.recv(4096)

        ask("EnableRobot()")
        p = SimulatedCR5().get_pose6()
        servo = dobot.format_command("ServoP", *p, t=0.03)
        out = {"getpose_round_trip": timeit(lambda: ask("GetPose()"), n), "servop_round_trip": timeit(lambda: ask(servo), n)}
        c.close()
        fb = socket.create_connection(("127.0.0.1", srv.feedback_port), timeout=2.0)
        asm = dobot.FeedbackAssembler()
        stamps = []
        t0 = time.monotonic()
        while time.monotonic() - t0 < seconds:
            for _ in asm.feed(fb.recv(65536)):
                stamps.append(time.monotonic())
        fb.close()
        gaps = np.diff(stamps) * 1e3
        out["feedback_period"] = {**stats_ms(gaps), "max_ms": float(gaps.max()), "packets_per_s": len(stamps) / seconds}
        return out
    finally:
        srv.stop()


def _rig(seconds: float, camera: bool) -> dict:
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.sim.rig_sim import SimRig

    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    with SimRig(s, seed=0, camera=camera) as rig:
        for arm in rig.arms.values():
            arm.enable()
        start = {name: arm.get_pose6() for name, arm in rig.arms.items()}
        dt, fps, frames = 1 / 30, 15.0, 0
        n = int(seconds / dt)
        t0 = time.perf_counter()
        for k in range(n):
            f = min(1.0, (k + 1) / (0.8 * n))
            for name, arm in rig.arms.items():  # lift both mounts 8 cm and draw them 2 cm together
                arm.servo_p(start[name] + [20 * f, 0, 80 * f, 0, 0, 0], t=dt)
            rig.step(dt)
            if camera and (k * dt * fps) % 1 < dt * fps:
                rig.render_rgbd(frames)
                frames += 1
        wall = time.perf_counter() - t0
        alarms = {name: arm.alarms() for name, arm in rig.arms.items()}
    return {"sim_s": n * dt, "wall_s": wall, "realtime_factor": n * dt / wall, "frames": frames, "alarms": str(alarms)}


def run(quick: bool = False) -> dict:
    n = 200 if quick else 1000
    return {
        "kinematics": _kinematics(n),
        "controller": _controller_step(n),
        "loopback": _loopback(n // 2, 1.0 if quick else 3.0),
        "rig_physics_only": _rig(2.0 if quick else 6.0, camera=False),
        "rig_with_camera_15hz": _rig(2.0 if quick else 6.0, camera=True),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    r = run(ap.parse_args().quick)
    for group in ("kinematics", "controller", "loopback"):
        for name, s in r[group].items():
            extra = f", max {s['max_ms']:.2f}, {s['packets_per_s']:.1f} packets/s" if "max_ms" in s else ""
            print(f"{group}.{name}: min {s['min_ms']:.3f} / median {s['median_ms']:.3f} / p95 {s['p95_ms']:.3f} ms{extra}")
    for name in ("rig_physics_only", "rig_with_camera_15hz"):
        v = r[name]
        print(f"{name}: {v['realtime_factor']:.2f}x real time ({v['sim_s']:.0f} s simulated in {v['wall_s']:.1f} s, {v['frames']} frames), "
              f"alarms {v['alarms']}")


if __name__ == "__main__":
    main()
