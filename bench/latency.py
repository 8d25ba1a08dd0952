"""End-to-end latency on loopback: camera frame published -> command on controller/cmd.

    python -m bagit.bench.latency [--quick] [--json] [--stages]

Default (`--nodes`): the real services as on the rig. This process publishes simulated RGB-D
frames (640x480, rendered once from the MuJoCo world of exp02 and re-stamped at each put) on
camera/rgbd at 10 and 30 Hz, a RunState (exp02, pre-bagging, mpc), the goal and the real planned
path for exp02 (the planner's compute_plan from the first frame's SOI), and both arms' states at
50 Hz at the scenario's mount home poses; it starts `python -m bagit.cli perception` and
`python -m bagit.cli controller` as child processes (Zenoh peers on loopback, multicast off,
connected to this process) and listens on controller/cmd. A command carries the camera stamp of
the SOI it was computed from (`Command.source_stamp`, = the frame's stamp), so latency is
`receive time of the command - stamp of its frame` (one clock: exact on one machine); commands
without one (holds for a stale SOI, ...) are counted but not timed. The controller ticks at the
run's control rate (30 Hz) and takes the newest SOI, so up to one tick of waiting is included.

`--stages`: the older in-bench stages (the services' algorithms wired with the same bus code,
without the nodes' configuration, control-rate tick, display cloud and marker detection).

Both also measure the RGB-D transport alone across processes at 30 frames/s (bagit.bench.zenoh),
goal: 30 frames/s without drops, p99 <= 30 ms on 2 cores.
"""

from __future__ import annotations

import argparse
import itertools
import json
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from bagit.common.dual_arm import Poses

RIG = "benchlat"
_SEQ = itertools.count(1)  # frame seqs stay new across measurements


def _latest_worker(fn: Callable[[Any], None]) -> Callable[[Any], None]:
    """A callback that hands its message to one worker thread, dropping any not yet taken (latest wins)."""
    cond = threading.Condition()
    box: list[Any] = []

    def loop() -> None:
        while True:
            with cond:
                while not box:
                    cond.wait()
                msg = box.pop()
            fn(msg)

    threading.Thread(target=loop, daemon=True).start()

    def put(msg: Any) -> None:
        with cond:
            box.clear()
            box.append(msg)
            cond.notify()

    return put


def _stage(role: str, connect: str, data: Path) -> int:
    """A child process: the perception or the controller stage."""
    from bagit.common.bus import BusConfig, Keys, Publisher, Subscriber, declare_alive, open_session
    from bagit.common.messages import Command, RgbdFrame, SoiState

    d = np.load(data, allow_pickle=False)
    keys = Keys(RIG)
    s = open_session(BusConfig(rig=RIG, connect=[connect]))
    keep: Subscriber[Any]
    if role == "perception":
        from bagit.services.perception import extract_soi, red_rim_mask, rim_cloud

        soi_pub = Publisher(s, keys.perception_soi, SoiState)
        prev: dict[str, np.ndarray] = {}

        def perceive(f: RgbdFrame) -> None:
            t0 = time.perf_counter()
            try:
                rim = extract_soi(rim_cloud(f, red_rim_mask), int(d["n_x"]), init=prev.get("x"), start_hint=d["hint"])
            except Exception:  # noqa: BLE001 - a frame without a rim is skipped, as the service would
                return
            prev["x"] = rim
            soi_pub.put(SoiState(seq=f.seq, source_stamp=f.stamp, rim=rim, solve_ms=(time.perf_counter() - t0) * 1e3))

        keep = Subscriber(s, keys.camera_rgbd, RgbdFrame, _latest_worker(perceive))
    else:
        from bagit.common.dual_arm import apply_increment
        from bagit.common.params import MethodParams
        from bagit.services.controller import ShapeServo

        servo = ShapeServo("mpc", MethodParams(), d["path"], int(d["dagger_index"]), float(d["R"]))
        grippers: Poses = {"left": d["left"], "right": d["right"]}
        cmd_pub = Publisher(s, keys.controller_cmd, Command)

        def control(soi: SoiState) -> None:
            now = time.time()
            out = servo.step(soi.rim, now, grippers, source_stamp=soi.source_stamp)
            grippers.update(apply_increment(grippers, out.u))
            cmd_pub.put(Command(seq=soi.seq, u=out.u, mode="hold" if out.mode == "hold" else "servo", reason=getattr(out, "reason", None),
                            source_stamp=soi.source_stamp))

        keep = Subscriber(s, keys.perception_soi, SoiState, _latest_worker(control))
    token = declare_alive(s, keys, f"bench-{role}")
    sys.stdin.read()  # until the parent closes our stdin (or dies)
    _ = keep, token
    s.close()
    return 0


RUN_ID = "bench-latency"


def _prepare(tmp: Path, n_frames: int) -> tuple[list[Any], Path, dict[str, Any]]:
    """Frames of the settled exp02 world, the planned path and the grippers, saved for the stages;
    and for the nodes: the scenario, the mount home poses and the planner's Goal and Path messages."""
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.perception import extract_soi, red_rim_mask, rim_cloud
    from bagit.services.planner.coordinator import PlanJob, compute_plan
    from bagit.services.sim.world import SimWorld

    sc = Scenario.from_file(find_scenario("exp02"))
    with SimWorld(sc) as w:
        w.step(1.0)
        frames = [w.render_rgbd(i) for i in range(n_frames)]
        homes = w.mount_home_poses()
    hint = homes["left"][:3, 3]
    g0 = extract_soi(rim_cloud(frames[0], red_rim_mask), sc.bag.n_x, start_hint=hint)
    out = compute_plan(PlanJob(RUN_ID, sc, g0, "cbirrt", 0, 10.0))
    if out.path is None:
        raise RuntimeError(f"no path to servo along: {out.reason}")
    R = sc.bag.rim_perimeter or float(np.sum(np.linalg.norm(np.roll(g0, -1, 0) - g0, axis=1)))
    data = tmp / "stage.npz"
    np.savez(data, path=out.path.nodes, dagger_index=out.path.dagger_index, R=R, n_x=sc.bag.n_x, hint=hint,
             left=homes["left"], right=homes["right"])
    return frames, data, {"scenario": sc, "homes": homes, "goal": out.goal, "path": out.path}


def _chain(frames: list[Any], pub: Any, got: dict[float, float], rate_hz: float, seconds: float) -> dict[str, Any]:
    """Frames at `rate_hz` for `seconds`; `got` maps a command's source_stamp to when it arrived."""
    from bagit.bench.zenoh import _stats

    sent: list[float] = []
    got.clear()
    period = 1.0 / rate_hz
    n = int(seconds * rate_hz)
    t_next = time.monotonic()
    for i in range(n):
        f = frames[i % len(frames)]
        f.seq = next(_SEQ)
        f.stamp = time.time()
        sent.append(f.stamp)
        pub.put(f)
        t_next += period
        time.sleep(max(0.0, t_next - time.monotonic()))
    time.sleep(1.0)
    lat = [(got[s] - s) * 1e3 for s in sent if s in got]
    return {"rate_hz": rate_hz, "frames": n, "commands": len(lat), "commands_per_frame": len(lat) / max(n, 1), "latency": _stats(lat)}


class _Commands:
    """controller/cmd as received: first arrival per source stamp, and counts by mode (untimed: no stamp)."""

    def __init__(self) -> None:
        self.got: dict[float, float] = {}
        self.modes: dict[str, int] = {}
        self.reasons: dict[str, int] = {}

    def __call__(self, c: Any) -> None:
        now = time.time()
        if c.source_stamp > 0:
            self.got.setdefault(c.source_stamp, now)
        key = c.mode if c.source_stamp > 0 else f"{c.mode} (untimed)"
        self.modes[key] = self.modes.get(key, 0) + 1
        if c.mode == "hold" and c.reason:
            self.reasons[c.reason[:80]] = self.reasons.get(c.reason[:80], 0) + 1

    def measure(self, frames: list[Any], pub: Any, rate_hz: float, seconds: float) -> dict[str, Any]:
        self.modes.clear()
        self.reasons.clear()
        r = _chain(frames, pub, self.got, rate_hz, seconds)
        return r | {"modes": dict(self.modes), "hold_reasons": dict(self.reasons)}


def _stage_children(ep: str, data: Path, td: Path) -> list[tuple[str, list[str]]]:
    return [(f"bench-{role}", [sys.executable, "-m", "bagit.bench.latency", "--role", role, "--connect", ep, "--data", str(data)])
            for role in ("perception", "controller")]


def _node_children(ep: str, data: Path, td: Path) -> list[tuple[str, list[str]]]:
    """The real services, configured as `bagit up` configures them (a peer on loopback connected to us)."""
    from bagit.up import zenoh_config

    z = td / "zenoh.json5"
    z.write_text(json.dumps(zenoh_config(ep), indent=2), encoding="utf-8")
    bus = ["--rig", RIG, "--zenoh-config", str(z)]
    return [(svc, [sys.executable, "-m", "bagit.cli", svc, *bus]) for svc in ("perception", "controller")]


class _RigFeed:
    """What the rest of the rig would publish around perception and the controller: the run state
    (5 Hz), the goal and path (1 Hz, as a late joiner would still get them) and both arms' states
    at the mount home poses (50 Hz, as the arm driver does)."""

    def __init__(self, session: Any, keys: Any, prep: dict[str, Any]) -> None:
        from bagit.common.bus import Publisher
        from bagit.common.geometry import matrix_to_rpy
        from bagit.common.messages import ArmState, Goal, RunState
        from bagit.common.messages import Path as PathMsg

        sc = prep["scenario"]
        self.state = RunState(run_id=RUN_ID, scenario=sc.name, stage="pre-bagging", controller="mpc", planner="cbirrt",
                              scenario_doc=sc.model_dump(mode="json", exclude_none=True))
        self.arms = {a: ArmState(arm=a, q=np.zeros(6), qd=np.zeros(6), enabled=True,
                                 tool_pose=np.r_[T[:3, 3], matrix_to_rpy(T[:3, :3])]) for a, T in prep["homes"].items()}
        self.goal, self.path = prep["goal"], prep["path"]
        self.pubs: dict[str, Publisher[Any]] = {"run": Publisher(session, keys.run_state, RunState), "goal": Publisher(session, keys.planner_goal, Goal),
                     "path": Publisher(session, keys.planner_path, PathMsg),
                     **{a: Publisher(session, keys.arm_state(a), ArmState) for a in ("left", "right")}}
        self._stop = threading.Event()
        self._t = threading.Thread(target=self._loop, name="rig-feed", daemon=True)
        self._t.start()

    def _loop(self) -> None:
        i = 0
        while not self._stop.wait(0.02):
            for a, m in self.arms.items():
                self.pubs[a].put(m.model_copy(update={"stamp": time.time()}))
            if i % 10 == 0:
                self.pubs["run"].put(self.state.model_copy(update={"stamp": time.time()}))
            if i % 50 == 0:
                self.pubs["goal"].put(self.goal)
                self.pubs["path"].put(self.path)
            i += 1

    def close(self) -> None:
        self._stop.set()
        self._t.join(5.0)
        for p in self.pubs.values():
            p.close()


def run(quick: bool = False, nodes: bool = True) -> dict[str, Any]:
    from bagit.bench.zenoh import _scenario
    from bagit.common.bus import BusConfig, Keys, LivelinessWatcher, Publisher, Subscriber, locators, open_session
    from bagit.common.messages import Command, RgbdFrame

    secs = 4.0 if quick else 10.0
    res: dict[str, Any] = {"mode": "nodes" if nodes else "stages"}
    with tempfile.TemporaryDirectory() as td:
        frames, data, prep = _prepare(Path(td), 10)
        keys = Keys(RIG)
        a = open_session(BusConfig(rig=RIG, adminspace=True))
        procs: list[tuple[str, subprocess.Popen, Any]] = []
        feed = None
        try:
            ep = locators(a)[0]
            watch = LivelinessWatcher(a, keys)
            cmds = _Commands()
            sub = Subscriber(a, keys.controller_cmd, Command, cmds)
            pub = Publisher(a, keys.camera_rgbd, RgbdFrame)
            if nodes:
                feed = _RigFeed(a, keys, prep)
            from bagit.forkserver import child_setup  # own session, and SIGTERM when this process dies: no orphans

            for name, argv in (_node_children if nodes else _stage_children)(ep, data, Path(td)):
                log = open(Path(td) / f"{name}.log", "w+", encoding="utf-8")
                procs.append((name, subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=log, stderr=subprocess.STDOUT,
                                                     preexec_fn=child_setup), log))
            for name, p, log in procs:
                if not watch.wait_for(name, True, 120):
                    log.seek(0)
                    raise RuntimeError(f"{name} did not come up (exit {p.poll()}): {log.read()[-2000:]}")
            time.sleep(0.5)
            cmds.measure(frames, pub, 10.0, 2.0)  # warm-up (first solves, the controller's reset, JIT caches)
            for hz in (10.0, 30.0):
                res[f"frame_to_cmd_{hz:g}hz"] = cmds.measure(frames, pub, hz, secs)
            sub.close()
            pub.close()
            watch.close()
        finally:
            if feed is not None:
                feed.close()
            for name, p, log in procs:
                try:
                    if nodes:
                        p.send_signal(signal.SIGTERM)
                    elif p.stdin is not None:  # (always: the stand-ins are started with stdin=PIPE)
                        p.stdin.close()
                    p.wait(10)
                except Exception:  # noqa: BLE001
                    p.kill()
                    p.wait(5)
                log.seek(0)
                res.setdefault("logs", {})[name] = log.read()[-1500:]
                log.close()
            a.close()
    res["rgbd_30hz_cross_process"] = _scenario("cross-process", secs, 30.0, None)
    g = res["rgbd_30hz_cross_process"]["rgbd"]
    res["goal_30fps_no_drops_p99_le_30ms"] = bool(g["lost"] == 0 and g["received_per_s"] >= 29.0 and g["latency"].get("p99_ms", 1e9) <= 30.0)
    return res


def _print(res: dict[str, Any]) -> None:
    print(f"frame -> command through the {'real perception and controller nodes' if res['mode'] == 'nodes' else 'in-bench stages'}")
    for k, r in res.items():
        if k.startswith("frame_to_cmd"):
            lat = r["latency"]
            print(f"{k:<22} {r['frames']:>4} frames -> {r['commands']:>4} commands; latency p50 {lat.get('median_ms', float('nan')):.1f} ms, "
                  f"p95 {lat.get('p95_ms', float('nan')):.1f}, p99 {lat.get('p99_ms', float('nan')):.1f}, "
                  f"max {lat.get('max_ms', float('nan')):.1f}; modes {r['modes']}")
            if r["hold_reasons"]:
                print(f"{'':<22} holds: {r['hold_reasons']}")
    g = res["rgbd_30hz_cross_process"]["rgbd"]
    print(f"rgbd 640x480 at 30/s across processes: {g['received_per_s']:.1f} frames/s received, {g['lost']} lost, "
          f"p50 {g['latency'].get('median_ms', float('nan')):.1f} ms, p99 {g['latency'].get('p99_ms', float('nan')):.1f} ms "
          f"(goal {'met' if res['goal_30fps_no_drops_p99_le_30ms'] else 'NOT met'})")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bagit.bench.latency", description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="~4 s per measurement instead of ~10 s")
    p.add_argument("--json", action="store_true")
    m = p.add_mutually_exclusive_group()
    m.add_argument("--nodes", dest="nodes", action="store_true", default=True, help="through the real `bagit perception` and `bagit controller` (default)")
    m.add_argument("--stages", dest="nodes", action="store_false", help="through the in-bench stages (the algorithms without the nodes)")
    p.add_argument("--role", choices=["main", "perception", "controller"], default="main", help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    p.add_argument("--data", type=Path, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.role != "main":
        return _stage(args.role, args.connect, args.data)
    res = run(quick=args.quick, nodes=args.nodes)
    print(json.dumps(res, indent=1, default=float)) if args.json else _print(res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
