"""One glue, two hosts: the same event sequence through `bagit run`'s in-process path and through the
services' nodes (on a Zenoh session pair, lockstep) gives the same effects, message for message.

The control tick: a synthetic rim (its equations unknown to the controller) stands in for the bag, the
camera and the arms, twice, once per host; each host is handed the same frames (with and without an
SOI), keep-alive ticks between sparse frames, a stale SOI and the run's end, and the commands and
statuses they send are compared field by field (all but the solver's time). The marker: the frames a
run's marker detection is made on, in the perception node (the run's start told by run/state) and in
`bagit run` (told directly)."""

from __future__ import annotations

import threading
from collections.abc import Callable
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from bus_support import session_pair, wait_until

from bagit.common.bus import Keys, Publisher, Subscriber
from bagit.common.clock import sim_time
from bagit.common.dual_arm import apply_increment
from bagit.common.geometry import matrix_to_rpy
from bagit.common.messages import ArmState, ClockTick, Command, ControllerStatus, Path, RunState, SoiState, StepAck
from bagit.common.rig import ArmName, SafetyLimits
from bagit.inprocess import control_tick
from bagit.services.controller.node import ControllerNode, ControllerServiceConfig
from bagit.services.controller.session import KEEPALIVE, ServoRuns, tick_period
from bagit.services.controller.synthetic import SyntheticRim
from bagit.services.perception.marker import MarkerSchedule
from bagit.services.perception.node import PerceptionNode, PerceptionServiceConfig
from bagit.services.perception.sources import SourceConfig

U_GOAL = np.array([0.05, 0.03, 0.15, 0, 0, 0.2, 0.05, -0.03, 0.15, 0, 0, 0.2]) * 0.5
PARAMS = {"max_linear_speed_mps": 0.15, "max_angular_speed_rps": 0.9, "control_rate_hz": 30.0}
RUN = "r1"

WATCHDOG_S = SafetyLimits().watchdog_s  # the rig's default, which both hosts read


class Plant:
    """The bag, camera and arms of one host: each servo command moves the grippers."""

    def __init__(self, model: SyntheticRim) -> None:
        self.m = model
        self.g = model.home()

    def states(self, t: float) -> dict[ArmName, ArmState]:
        return {a: ArmState(arm=a, q=np.zeros(6), qd=np.zeros(6), tool_pose=np.r_[T[:3, 3], matrix_to_rpy(T[:3, :3])], enabled=True,
                            stamp=t) for a, T in self.g.items()}

    def soi(self, seq: int, t: float) -> SoiState:
        return SoiState(seq=seq, source_stamp=t, stamp=t, rim=self.m.rim(self.g))

    def apply(self, cmd: Command) -> None:
        if cmd.mode == "servo":
            self.g = apply_increment(self.g, cmd.u)


def events() -> list[tuple[str, float, bool]]:
    """(kind, time, with an SOI): frames at the control rate, then frames sparser than the keep-alive pace
    with keep-alive ticks between them, then frames without an SOI until it is stale, then the run's end."""
    keep = tick_period(PARAMS["control_rate_hz"], WATCHDOG_S)
    out = [("frame", k / 30, True) for k in range(40)]
    t = out[-1][1]
    for _ in range(6):  # a frame every 2.5 keep-alive periods: two keep-alive ticks between frames
        out += [("keepalive", t + keep, False), ("keepalive", t + 2 * keep, False)]
        t += 2.5 * keep
        out.append(("frame", t, True))
    for k in range(1, 25):  # no SOI: a keep-alive on the last one, then a hold once it is stale
        out.append(("frame", t + k / 30, False))
    out.append(("end", t + 25 / 30, False))
    return [(kind, sim_time(w), soi) for kind, w, soi in out]


def strip(msgs: list[Any], exclude: frozenset[str] = frozenset()) -> list[dict[str, Any]]:
    """Messages as comparable fields (the solver's time, a measurement of this machine, left out; and `exclude`)."""
    rows = []
    for m in msgs:
        d = m.model_dump(exclude={"solve_ms", *exclude})
        rows.append({k: (np.asarray(v).tobytes() if isinstance(v, (list, np.ndarray)) else v) for k, v in d.items()})
    return rows


def run_inprocess(model: SyntheticRim, state: RunState, path: Path, evs: list[tuple[str, float, bool]]) -> tuple[list[Command], list[ControllerStatus]]:
    """`bagit run`'s control ticks (`control_tick`, as its loop calls it: at each frame and keep-alive tick)."""
    plant = Plant(model)
    seq = iter(range(1, 10_000))
    servo = ServoRuns(lambda: next(seq), watchdog_s=WATCHDOG_S)
    cmds: list[Command] = []
    statuses: list[ControllerStatus] = []
    soi: SoiState | None = None
    for k, (kind, t, with_soi) in enumerate(evs):
        st = state if kind != "end" else state.model_copy(update=dict(stage="aborted", reason="operator stop"))
        if with_soi:
            soi = plant.soi(k + 1, t)
        for out in control_tick(servo, st, path, None, soi, plant.states(t), t, keepalive=kind == "keepalive"):
            if out.command is not None:
                cmds.append(out.command)
                plant.apply(out.command)
            if out.status is not None:
                statuses.append(out.status)
    return cmds, statuses


def run_node(model: SyntheticRim, state: RunState, path: Path, evs: list[tuple[str, float, bool]],
             rig: str) -> tuple[list[Command], list[ControllerStatus]]:
    """The controller node in lockstep: the same events as the bus brings them (arm states, the SOI, the
    coordinator's answer to the frame or a keep-alive tick on sim/clock), each step once it has answered."""
    plant = Plant(model)
    gen = session_pair(rig)
    a, b = next(gen)
    keys = Keys(rig)
    node = ControllerNode(a, keys, ControllerServiceConfig(), clock="sim")
    cmds: list[Command] = []
    statuses: list[ControllerStatus] = []
    answers: dict[float, StepAck] = {}
    lock = threading.Lock()

    def on(target: list[Any] | dict[float, StepAck]) -> Callable[[Any], None]:
        def put(m: Any) -> None:
            with lock:
                if isinstance(target, dict):
                    if m.service == "controller":
                        target[m.frame] = m
                else:
                    target.append(m)
                    if isinstance(m, ControllerStatus) and m.frame is not None:  # a tick's last status is its answer
                        answers[m.frame] = m.answer()
        return put

    subs = [Subscriber(b, keys.controller_cmd, Command, on(cmds)), Subscriber(b, keys.controller_status, ControllerStatus, on(statuses)),
            Subscriber(b, keys.step_ack("controller"), StepAck, on(answers))]
    pubs = {"run": Publisher(b, keys.run_state, RunState, lockstep=True), "path": Publisher(b, keys.planner_path, Path),
            "soi": Publisher(b, keys.perception_soi, SoiState, lockstep=True), "ack": Publisher(b, keys.step_ack("planner"), StepAck),
            "clock": Publisher(b, keys.sim_keepalive, ClockTick), "left": Publisher(b, keys.arm_state("left"), ArmState),
            "right": Publisher(b, keys.arm_state("right"), ArmState)}
    try:
        assert wait_until(lambda: all(p.matched for p in pubs.values()))
        pubs["run"].put(state)
        pubs["path"].put(path)
        assert wait_until(lambda: node._run_state is not None and RUN in node._paths)
        seen = 0
        seq = None
        for k, (kind, t, with_soi) in enumerate(evs):
            if kind == "end":
                pubs["run"].put(state.model_copy(update=dict(stage="aborted", reason="operator stop")))
                assert wait_until(lambda: node._run_state is not None and node._run_state.stage == "aborted")
            for arm, msg in plant.states(t).items():
                pubs[arm].put(msg)
            if with_soi:
                seq = k + 1
                pubs["soi"].put(plant.soi(seq, t))
            if kind == "keepalive":
                pubs["clock"].put(ClockTick(t=t, run_id=RUN, keepalive=True))
            else:
                stage = "aborted" if kind == "end" else state.stage
                pubs["ack"].put(StepAck(service="planner", run_id=RUN, frame=t, soi_seq=seq if with_soi else None, stage=stage, stamp=t))
            assert wait_until(lambda: t in answers, 30.0), (kind, t)
            ans = answers[t]
            assert wait_until(lambda: (ans.cmd_seq is None or any(c.seq == ans.cmd_seq for c in cmds))
                              and (ans.status_seq is None or any(s.seq == ans.status_seq for s in statuses)), 30.0)
            with lock:
                new = sorted(cmds, key=lambda c: c.seq)[seen:]
            for c in new:
                plant.apply(c)
            seen += len(new)
        with lock:
            return sorted(cmds, key=lambda c: c.seq), sorted(statuses, key=lambda s: s.seq)
    finally:
        node.close()
        for s in subs:
            s.close()
        for p in pubs.values():
            p.close()
        gen.close()


@pytest.mark.slow
def test_a_control_tick_sequence_gives_the_same_commands_and_statuses_in_bagit_run_and_in_the_controller_node():
    model = SyntheticRim(16)
    nodes = np.stack([model.rim(apply_increment(model.home(), U_GOAL * s)) for s in np.linspace(0, 1, 6)])
    state = RunState(run_id=RUN, stage="pre-bagging", controller="mpc", params=PARAMS)
    path = Path(run_id=RUN, nodes=nodes, dagger_index=4)
    evs = events()
    cmds_a, st_a = run_inprocess(model, state, path, evs)
    cmds_b, st_b = run_node(model, state, path, evs, "glue" + "both")
    # the hosts part only at the run's end: `bagit run` stops stepping, the node holds the arms once
    assert cmds_b[-1].mode == "hold" and cmds_b[-1].reason == "run aborted: operator stop"
    assert strip(cmds_a) == strip(cmds_b[:-1])
    # a status is stamped when made (wall); in lockstep a tick's last status also answers its step (frame, cmd_seq, late)
    answer = frozenset({"frame", "cmd_seq", "late"})
    assert strip(st_a, frozenset({"stamp"}) | answer) == strip(st_b[:-1], frozenset({"stamp"}) | answer)
    answering = [x for x in st_b if x.frame is not None]
    assert all(x.frame is None for x in st_a) and answering and {x.cmd_seq for x in answering} <= {c.seq for c in cmds_b}
    # ... and the sequence went through every kind of tick
    reasons = [c.reason for c in cmds_a]
    assert sum(c.mode == "servo" and c.reason != KEEPALIVE for c in cmds_a) >= 30
    assert KEEPALIVE in reasons and any(r is not None and r.startswith("SOI is stale") for r in reasons)


def test_the_marker_detection_falls_on_the_same_frames_in_bagit_run_and_in_the_perception_node():
    t0 = sim_time(3.0)
    stamps = [t0 + k / 30 for k in range(-30, 120)]  # frames from a second before the run's start
    # bagit run: told the start, asked on each frame while the run perceives (its first 2 s here)
    host = MarkerSchedule()
    host.run_started(t0)
    inproc = [t for t in stamps if t0 <= t < t0 + 2.0 and host.due(t)]
    # the node: the start from run/state (its stamp less the time elapsed), every frame offered
    gen = session_pair("glue" + "marker")
    a, _b = next(gen)
    try:
        node = PerceptionNode(a, Keys("gluemarker"), PerceptionServiceConfig(source=SourceConfig(kind="zenoh")), clock="sim")
        try:
            due = [t for t in stamps if t < t0 and node._marker_due(SimpleNamespace(stamp=t))]  # type: ignore[arg-type]
            node._on_run_state(RunState(run_id=RUN, stage="perceiving", stamp=t0 + 0.25, elapsed_s=0.25))
            in_node = [t for t in stamps if t0 <= t < t0 + 2.0 and node._marker_due(SimpleNamespace(stamp=t))]  # type: ignore[arg-type]
        finally:
            node.close()
    finally:
        gen.close()
    assert in_node == inproc == [stamps[30 + 15], stamps[30 + 45]]  # the first frame 0.5 s after the start, then 1 Hz
    assert due and due[0] == stamps[0]  # between runs the node detects at the rate (the dashboard's view)
