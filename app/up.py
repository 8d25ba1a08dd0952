"""`bagit up`: the whole rig on one machine, every service its own process.

The composition root of the distributed rig. It writes, in a scratch folder, a Zenoh config
(peers, multicast scouting off, a 1 s lease on the wall clock and a 60 s one in lockstep, every peer
connected to the hub session this process listens with; each process listens on a Unix socket in that
folder, `local_endpoint`), a rig YAML (free ports for the simulated CR5s) and an arm-driver
config (link time-outs for controllers that share the CPU, `SIM_DRIVER_TIMEOUTS`), then starts
the services as child processes running `bagit <service> ...`: forked by `bagit.forkserver`, a fork of
`bagit up` made before it starts a thread, with what they share imported once (`--no-fork-server`: `python -m bagit.cli <service>`
each, as a deployed rig starts them), streams their output with
`[service]` prefixes, waits for each one's liveliness token, and can start a run on run/control
and wait for its end.

Children: each in its own session (process group) and with the parent-death signal set (Linux
PR_SET_PDEATHSIG), so `stop()` (on Ctrl-C, SIGTERM or the end of the run) takes down every
process a service started, and a SIGKILLed `bagit up` leaves no orphans either. A child that
dies while the rig is up is restarted after `restart_delay_s` (what systemd's Restart= does on a
real rig), up to `max_restarts` times; `status()` (and the --status-file) gives the child PIDs so
tests can kill one.
"""

from __future__ import annotations

import functools
import json
import os
import resource
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, TextIO

from bagit.common.bus import BusConfig, Keys, LatestCache, LivelinessWatcher, Polled, open_session, request_run_control
from bagit.common.errors import BusError
from bagit.common.lockstep import LOCKSTEP_LEASE_MS
from bagit.common.messages import ArmState, RunControl, RunControlReply, RunState, SimTruth
from bagit.common.names import FINAL_STAGES, NO_SIM_CLOCK_YET, SIM_TIME_LIMIT_S
from bagit.common.rig import RigConfig
from bagit.forkserver import ForkedProcess, ForkServer, child_env, child_setup

if TYPE_CHECKING:
    from bagit.common.scenario import BagSpec

SERVICES = ("sim", "perception", "planner", "controller", "arm-driver", "dashboard")
# A service that needs another one up before it can start (the arm driver connects to the CR5s the
# simulator serves; on a real rig the controllers are already up).
AFTER = {"arm-driver": "sim"}
SUPERVISE_S = 1.0  # the supervisor's backstop wake-up (events wake it first)
STOP_CHECK_S = 0.25  # how often a wait woken by the bus also looks at its `stop` event (Ctrl-C)
CLOCK_RETRY_S = 0.05  # a start refused for the simulator's clock not yet heard is asked again this soon
# The recorder, which no step waits for, runs at this niceness (its process and its autogroup: see
# `forkserver.renice`): on a busy machine the simulator and the services a step waits for come first. Not
# the dashboard, which carries the E-STOP button: niced, a press took 81-194 ms to reach the bus during a
# wall-clock run on 2 cores, against 24 ms at the rig's niceness (tests/app/test_up_browser.py, 2026-11-28).
OFF_PATH_NICENESS = 10
NICED = ("recorder",)
# In lockstep, with the simulator among the children and two CPUs or more, it keeps the first of them to
# itself: the other services run on the rest (`child_cpus`). Its main thread, a lockstep run's critical path
# (physics, render, noise), is then neither preempted by a service nor moved between cores, and the services'
# messages to one another wake them where they run. On 2 cores (exp02, 5 pairs alternating, 2026-11-29 11:41
# UTC): 14.53 s / 20.27 CPU s against 15.06 / 21.20 sharing both. Not on the wall clock, where a service's
# timing is its own (the arm driver's servo period beside perception on one core was not measured there).
# `--shared-cores` (UpOptions.sim_core) turns it off.


def child_cpus(name: str, names: Collection[str], available: Collection[int], lockstep: bool = True) -> frozenset[int] | None:
    """The CPUs child `name` may run on (None: all of `available`, bagit up's own): in lockstep, every CPU but
    the first for a service beside the simulator, on two CPUs or more; the simulator's render threads use them all."""
    if not lockstep or name == "sim" or "sim" not in names or len(available) < 2:
        return None
    return frozenset(sorted(available)[1:])


# Services a run does not wait for: the dashboard shows a run from its next message on, so a scenario's
# run starts once the others are up (the recorder is waited for: it records the run from its start).
WATCHERS = ("dashboard",)
# The arm driver's link time-outs for the simulated CR5s. A real CR5 sends feedback every 8 ms and
# answers at once, so the driver's defaults call 0.2 s without feedback a lost link and 0.5 s
# without a reply an error. The simulated controllers share the machine's cores with the physics,
# every other service and maybe a browser: a loaded machine keeps them off the CPU for that long
# (seen on 2 cores), and the driver would then restart the stream or fault a run over a scheduler
# pause. The watchdog on the controller's commands and every motion limit stay as they are.
WALL_TIME_LIMIT_S = 360.0  # --clock wall: a run's servoing limit, wide for a simulator slower than real time
WALL_LEASE_MS = 1000  # --clock wall: the links' lease (a silent service is declared gone after it)
SIM_DRIVER_TIMEOUTS = {"feedback_timeout_s": 1.0, "reply_timeout_s": 2.0}
UNIX_PATH_MAX = 107  # a Unix socket's path, in bytes (Linux's sun_path less its NUL); a deeper --workdir links over TCP


def free_port() -> int:
    """A TCP port on 127.0.0.1 free right now (the OS's pick)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def local_endpoint(folder: Path, name: str) -> str | None:
    """A Zenoh endpoint on the Unix socket `folder/name.sock`, or None when its path is too long for one.

    The rig's processes link over these rather than loopback TCP: the same messages for a few per cent less
    CPU (no TCP stack under each of a run's thousands of messages), and reachable only by whoever may enter the
    folder (`mkdtemp` makes it its user's alone), never from the network. Zenoh removes a socket left by a
    killed process when the next one binds it (its `.lock` file), so a restarted service listens again."""
    path = folder.resolve() / f"{name}.sock"
    return f"unixsock-stream/{path}" if len(os.fsencode(path)) <= UNIX_PATH_MAX else None


def free_ports(n: int) -> list[int]:
    """n distinct free ports (all held open until picked, so none repeats)."""
    socks = []
    try:
        for _ in range(n):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", 0))
            socks.append(s)
        return [int(s.getsockname()[1]) for s in socks]
    finally:
        for s in socks:
            s.close()


def zenoh_config(hub: str, lease_ms: int = WALL_LEASE_MS) -> dict[str, Any]:
    """The children's Zenoh config: peers on loopback, connected to the hub, no multicast."""
    return {
        "mode": "peer",
        "connect": {"endpoints": [hub]},
        "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
        "scouting": {"multicast": {"enabled": False}, "delay": 0},
        "transport": {"link": {"tx": {"lease": lease_ms, "keep_alive": 4}}},
    }


def lab_bag(world: str) -> BagSpec:
    """The bag on the simulated world's table, which a lab would describe once for its own: the arm driver's
    separation limit follows its rim's perimeter (`RigConfig.for_bag`), perception takes its binding's colour."""
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario

    return Scenario.from_file(find_scenario(world)).bag


def bag_perception_config(bag: BagSpec) -> dict[str, Any]:
    """What a lab writes once into perception's config for its bag: the binding's colour (perception never
    reads the simulator's truth, nor the scenario's binding)."""
    return {"bag_rim_color": list(bag.rim.color)}


def lab_perception_config(world: str) -> dict[str, Any]:
    """Perception's config for the bag of the simulated world `world` (`bag_perception_config`)."""
    return bag_perception_config(lab_bag(world))


@dataclass
class UpOptions:
    scenario: str | None = None
    world: str = "exp02"  # the world the simulator starts with when no scenario is given
    controller: str | None = None
    planner: str | None = None
    seed: int = 0
    rig: str = "sim"
    services: tuple[str, ...] = SERVICES
    record: Path | None = None
    # lockstep: every service on the simulator's clock, which steps on only when they have answered
    # (a slow machine makes a run slower, never different); wall: the simulator paced to the wall clock
    clock: Literal["lockstep", "wall"] = "lockstep"
    speed: float | None = None  # simulated seconds per wall second, at most (None: a lockstep run as fast as the rig answers)
    fps: float | None = None  # None: the simulator's default (`bagit.services.sim.rig_sim.camera_fps`: the run's control rate in lockstep)
    # A run's servoing limit: in lockstep on the simulator's clock, as `bagit run`'s; on the wall
    # clock the simulator runs at a fraction of real time when the machine is busy (x0.4 with the
    # dashboard, a browser and every service on 2 cores), and the run with it.
    run_time_limit_s: float | None = None

    def time_limit_s(self) -> float:
        return self.run_time_limit_s or (SIM_TIME_LIMIT_S if self.clock == "lockstep" else WALL_TIME_LIMIT_S)
    dashboard_port: int = 0
    workdir: Path | None = None
    status_file: Path | None = None
    ready_timeout_s: float = 180.0
    restart_delay_s: float = 1.0
    max_restarts: int = 5
    # Start the services as forks of one interpreter that imported what they share (`bagit.forkserver`),
    # not as an interpreter each: the same commands, a fraction of the start-up CPU.
    fork_server: bool = True
    sim_core: bool = True  # in lockstep, the simulator keeps a CPU to itself (`child_cpus`)
    extra_args: dict[str, list[str]] = field(default_factory=dict)


def follow_arm_events(session: Any, keys: Keys) -> Polled[ArmState]:
    """Where a run's result reads the arm side's event counts (`RunResult.arm_events`) once the run has ended:
    the newest left arm state (both arms' states carry the side's counts), kept by Zenoh, no thread woken per state."""
    return Polled(session, keys.arm_state("left"), ArmState, 1)


@dataclass
class Child:
    name: str
    argv: list[str]
    proc: subprocess.Popen | ForkedProcess | None = None
    restarts: int = 0
    exit_codes: list[int] = field(default_factory=list)
    waiting_for: str | None = None  # started once this service's liveliness token is up


class Up:
    """The rig's processes and the hub session (see the module docstring)."""

    def __init__(self, opts: UpOptions, log: TextIO = sys.stderr, on_line: Callable[[str, str], None] | None = None,
                 forks: ForkServer | None = None, t0: float | None = None) -> None:
        """`forks`: a fork server already started (`bagit up` starts it before its own imports, so the
        server's run alongside them); else `start` starts one when `opts.fork_server`. Closed by `stop`.
        `t0`: when the command began (`time.monotonic()`), for the time "all services up" reports."""
        self.opts = opts
        self.t0 = time.monotonic() if t0 is None else t0
        self._all_up_said = False
        self.log = log
        self.on_line = on_line
        self._own_dir = opts.workdir is None
        self.dir = Path(tempfile.mkdtemp(prefix="bagit-up-")) if opts.workdir is None else Path(opts.workdir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.driver_config = self.dir / "arm-driver.yaml"  # the arm driver's link time-outs (SIM_DRIVER_TIMEOUTS)
        self.perception_config = self.dir / "perception.yaml"  # the lab's bag: its binding colour (`bag_perception_config`)
        self.keys = Keys(opts.rig)
        self.children: dict[str, Child] = {}
        self._stopping = threading.Event()
        self._wake = threading.Event()  # the supervisor has something to look at
        self._changed = threading.Condition()  # a service came or went, or a child exited: wakes `wait_ready`
        self._print_lock = threading.Lock()
        self.session: Any = None
        self.watcher: LivelinessWatcher | None = None
        self.run_state: LatestCache | None = None
        self.truth: LatestCache | None = None  # the simulator's ground truth, to judge a run (never given to a service)
        self.final_truths: dict[str, SimTruth] = {}  # run id -> the world as that run ended
        self.arm_states: Polled | None = None  # the arm side's event counts, for the run's result (read once it has ended)
        self.hub = ""
        self.dashboard_url: str | None = None
        self._supervisor: threading.Thread | None = None
        self.forks = forks  # the services' fork server (`UpOptions.fork_server`)

    # -- set-up ----------------------------------------------------------------------------------

    def say(self, text: str, who: str = "up") -> None:
        with self._print_lock:  # one write per line: a child's line never splits another's
            self.log.write(f"[{who}] {text}\n")
            self.log.flush()
        if self.on_line is not None:
            self.on_line(who, text)

    @property
    def lease_ms(self) -> int:
        """The links' lease: in lockstep longer than any pause a run survives exactly (`LOCKSTEP_LEASE_MS`),
        so a stopped service keeps its links and its token; on the wall clock 1 s, so a hung one is seen."""
        return LOCKSTEP_LEASE_MS if self.opts.clock == "lockstep" else WALL_LEASE_MS

    def _write_configs(self) -> tuple[Path, Path]:
        hub = local_endpoint(self.dir, "hub")
        ports = free_ports(4 if hub else 5)  # the CR5s' four, and a TCP port for the hub only when it cannot have a socket
        cr5 = ports[:4]
        self.hub = hub or f"tcp/127.0.0.1:{ports[4]}"
        zpath = self.dir / "zenoh.json5"
        zpath.write_text(json.dumps(zenoh_config(self.hub, self.lease_ms), indent=2), encoding="utf-8")
        rig = RigConfig(name=self.opts.rig)
        arms = {
            "left": rig.arms["left"].model_copy(update={"dashboard_port": cr5[0], "feedback_port": cr5[1]}),
            "right": rig.arms["right"].model_copy(update={"dashboard_port": cr5[2], "feedback_port": cr5[3]}),
        }
        bag = lab_bag(self.opts.scenario or self.opts.world)  # read once: the rig and perception both describe it
        rig = rig.model_copy(update={"arms": arms}).for_bag(bag.perimeter_m())
        rpath = self.dir / "rig.yaml"
        rpath.write_text(rig.to_yaml(), encoding="utf-8")
        self.driver_config.write_text(json.dumps({"driver": SIM_DRIVER_TIMEOUTS}, indent=2), encoding="utf-8")
        self.perception_config.write_text(json.dumps(bag_perception_config(bag), indent=2), encoding="utf-8")
        return zpath, rpath

    def _argv(self, name: str, zpath: Path, rpath: Path) -> list[str]:
        o = self.opts
        bus = ["--rig", o.rig, "--zenoh-config", str(zpath), "--clock", "sim" if o.clock == "lockstep" else "wall"]
        listen = local_endpoint(self.dir, name)
        bus += ["--listen", listen] if listen else []  # else the config's loopback TCP
        if name == "sim":
            args = ["sim", o.scenario or o.world, "--rig-config", str(rpath), "--seed", str(o.seed)]
            args += ["--fps", f"{o.fps:g}"] if o.fps is not None else []
            args += ["--speed", f"{o.speed:g}"] if o.speed is not None else []
        elif name == "dashboard":
            port = o.dashboard_port or free_port()
            self.dashboard_url = f"http://127.0.0.1:{port}"
            args = ["dashboard", "--port", str(port), "--rig-config", str(rpath), "--scenario", o.scenario or o.world]
        elif name == "recorder":
            args = ["recorder", "--dir", str(o.record or "recordings")]
        elif name == "arm-driver":
            args = [name, "--config", str(self.driver_config), "--rig-config", str(rpath)]
        elif name == "perception":
            args = [name, "--config", str(self.perception_config), "--rig-config", str(rpath)]
        elif name == "controller":
            args = [name, "--rig-config", str(rpath)]
        elif name == "planner":
            args = [name, "--run-time-limit", f"{o.time_limit_s():g}"]
        else:
            args = [name]
        return args + bus + o.extra_args.get(name, [])

    def start(self) -> None:
        """Write the configs, open the hub, start every service."""
        from bagit.cli import build_parser

        _, modules = build_parser()
        names = list(self.opts.services) + (["recorder"] if self.opts.record is not None and "recorder" not in self.opts.services else [])
        missing = [n for n in names if n not in modules]
        if missing:
            raise BusError(f"no `bagit {missing[0]}` command in this build: cannot start the {missing[0]} service")
        if self.opts.fork_server and self.forks is None:  # first: its imports overlap the rest of the set-up
            self.forks = ForkServer(child_env())
        if self.forks is not None:
            self.forks.on_exit = lambda *_: self._wake.set()  # a child exited: the supervisor restarts it
        zpath, rpath = self._write_configs()
        self.session = open_session(BusConfig(rig=self.opts.rig, listen=[self.hub], lease_ms=self.lease_ms))
        self.watcher = LivelinessWatcher(self.session, self.keys, self._on_alive)
        self.run_state = LatestCache(self.session, self.keys.run_state, RunState)
        self.arm_states = follow_arm_events(self.session, self.keys)
        if "sim" in names:
            self.truth = LatestCache(self.session, self.keys.sim_truth, SimTruth, self._on_truth)  # the newest, and each run's final
        for n in names:
            self.children[n] = Child(n, self._argv(n, zpath, rpath), waiting_for=AFTER.get(n) if AFTER.get(n) in names else None)
        for c in self.children.values():
            if c.waiting_for is None:
                self._spawn(c)
        self._supervisor = threading.Thread(target=self._supervise, name="up-supervisor", daemon=True)
        self._supervisor.start()

    def _spawn(self, c: Child) -> None:
        niceness = OFF_PATH_NICENESS if c.name in NICED else 0
        cpus = child_cpus(c.name, self.children, os.sched_getaffinity(0), self.opts.clock == "lockstep") if self.opts.sim_core else None
        c.proc = None
        if self.forks is not None and self.forks.alive:
            try:
                c.proc = self.forks.spawn(c.argv, niceness, cpus)
            except OSError as e:  # the server is gone: an interpreter of its own, as without it
                self.say(f"fork server: {e}; starting {c.name} as a process of its own")
        if c.proc is None:
            c.proc = subprocess.Popen(
                [sys.executable, "-m", "bagit.cli", *c.argv], stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT, env=child_env(), preexec_fn=functools.partial(child_setup, niceness, cpus=cpus),
                text=True, errors="replace", bufsize=1,
            )
        threading.Thread(target=self._pump, args=(c.name, c.proc), name=f"log-{c.name}", daemon=True).start()
        self.say(f"started {c.name} (pid {c.proc.pid})")
        self._write_status()

    def _pump(self, name: str, proc: subprocess.Popen | ForkedProcess) -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            self.say(line.rstrip("\n"), who=name)
        self._wake.set()  # its output ended: it exited (the supervisor restarts it)

    def _on_alive(self, service: str, alive: bool) -> None:
        self.say(f"service {service} {'up' if alive else 'gone'}")
        if alive and not self._all_up_said and self.watcher is not None and not self.not_up(tuple(self.children)):
            self._all_up_said = True  # said once, when the last comes up (a run may be going already: see WATCHERS)
            self.say(f"all services up in {time.monotonic() - self.t0:.1f} s: {', '.join(sorted(self.children))}; hub {self.hub}")
        self._wake.set()  # a service waited for may be up
        self._notify_changed()

    def _notify_changed(self) -> None:
        with self._changed:
            self._changed.notify_all()

    def _supervise(self) -> None:
        """Start the services waiting for another once it is up; restart the ones that exited. Woken by
        liveliness changes and ended outputs (the timed wake-up is only a backstop)."""
        while not self._stopping.is_set():
            self._wake.wait(SUPERVISE_S)
            self._wake.clear()
            if self._stopping.is_set():
                return
            for c in list(self.children.values()):
                if c.waiting_for is not None and self.watcher is not None and c.waiting_for in self.watcher.alive():
                    c.waiting_for = None
                    self._spawn(c)
                if c.proc is None or c.proc.poll() is None:
                    continue
                code = c.proc.poll()
                assert code is not None
                c.exit_codes.append(code)
                if c.restarts >= self.opts.max_restarts:
                    self.say(f"{c.name} exited with {code}; not restarted ({c.restarts} restarts already)")
                    c.proc = None
                    self._notify_changed()  # `wait_ready` gives up on it
                    continue
                self.say(f"{c.name} exited with {code}; restarting in {self.opts.restart_delay_s:g} s")
                c.proc = None
                if self._stopping.wait(self.opts.restart_delay_s):
                    return
                c.restarts += 1
                self._spawn(c)

    def _on_truth(self, t: SimTruth) -> None:
        if t.final and t.run_id is not None:
            self.final_truths[t.run_id] = t

    # -- status ----------------------------------------------------------------------------------

    def cpu_s(self) -> dict[str, float]:
        """CPU seconds (user + system) each running child has used so far, from /proc (Linux)."""
        tick = os.sysconf("SC_CLK_TCK")
        out: dict[str, float] = {}
        for n, c in self.children.items():
            if c.proc is None or c.proc.poll() is not None:
                continue
            try:
                fields = Path(f"/proc/{c.proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            out[n] = round((int(fields[11]) + int(fields[12])) / tick, 2)  # utime, stime
        return out

    def own_cpu_s(self) -> dict[str, float]:
        """CPU seconds so far of `bagit up` itself and of its fork server (the imports the services share)."""
        me = resource.getrusage(resource.RUSAGE_SELF)
        return {"bagit up": round(me.ru_utime + me.ru_stime, 2), "fork server": round(self.forks.cpu_s(), 2) if self.forks is not None else 0.0}

    def rig_cpu_s(self) -> float:
        """CPU seconds so far of every running child, of this process (`bagit up` itself) and of the fork server."""
        return sum(self.cpu_s().values()) + sum(self.own_cpu_s().values())

    def status(self) -> dict[str, Any]:
        return {
            "pid": os.getpid(),
            "rig": self.opts.rig,
            "connect": self.hub,
            "zenoh_config": str(self.dir / "zenoh.json5"),
            "rig_config": str(self.dir / "rig.yaml"),
            "dashboard_url": self.dashboard_url,
            "children": {n: (c.proc.pid if c.proc is not None and c.proc.poll() is None else None) for n, c in self.children.items()},
            "restarts": {n: c.restarts for n, c in self.children.items()},
            "cpu_s": self.cpu_s(),
        }

    def _write_status(self) -> None:
        """The status as JSON in the workdir (and the --status-file), rewritten at every (re)start of a child."""
        for path in (self.dir / "status.json", self.opts.status_file):
            if path is not None:
                tmp = Path(str(path) + ".tmp")
                tmp.write_text(json.dumps(self.status()), encoding="utf-8")
                tmp.replace(path)

    def not_up(self, names: tuple[str, ...]) -> tuple[str, ...]:
        """Those of `names` whose liveliness token is not on the bus now."""
        assert self.watcher is not None
        alive = self.watcher.alive()
        return tuple(n for n in names if n not in alive)

    def wait_ready(self, timeout: float | None = None, stop: threading.Event | None = None, but: tuple[str, ...] = ()) -> list[str]:
        """Wait for the liveliness token of every service not in `but`; returns the ones still missing (empty: all up)."""
        assert self.watcher is not None
        deadline = time.monotonic() + (timeout if timeout is not None else self.opts.ready_timeout_s)
        want = set(self.children) - set(but)
        while True:
            with self._changed:  # checked under the condition: a change after the check wakes the wait
                missing = sorted(want - self.watcher.alive())
                if not missing or time.monotonic() > deadline or (stop is not None and stop.is_set()):
                    return missing
                dead = [n for n in missing if self.children[n].restarts >= self.opts.max_restarts and self.children[n].proc is None]
                if dead:
                    return missing
                self._changed.wait(min(STOP_CHECK_S, max(0.0, deadline - time.monotonic())))  # the backstop: `stop`

    # -- runs ------------------------------------------------------------------------------------

    def start_run(self, scenario: str, timeout: float = 10.0) -> RunControlReply:
        """Ask the coordinator to start `scenario`; asked again while it has not heard the simulator's clock
        (a lockstep start just after "all up"), at most `timeout` s in all."""
        o = self.opts
        req = RunControl(action="start", scenario=scenario, controller=o.controller, planner=o.planner, seed=o.seed)
        deadline = time.monotonic() + timeout
        while True:
            rep = request_run_control(self.session, self.keys, req, timeout=max(0.1, deadline - time.monotonic()))
            if rep.accepted or not (rep.reason or "").startswith(NO_SIM_CLOCK_YET) or time.monotonic() > deadline:
                return rep
            time.sleep(CLOCK_RETRY_S)

    def wait_run(self, run_id: str, stop: threading.Event, timeout: float | None = None) -> RunState | None:
        """Follow run/state until run `run_id` ends (done, failed, aborted); None if stopped first."""
        assert self.run_state is not None
        deadline = None if timeout is None else time.monotonic() + timeout
        last_stage, seen = None, 0.0
        while not stop.is_set() and (deadline is None or time.monotonic() < deadline):
            item = self.run_state.get_with_time()
            if item is not None:
                s, seen = item
                if s.run_id == run_id and s.stage != last_stage:
                    last_stage = s.stage
                    self.say(f"run {run_id}: {s.stage}" + (f" ({s.reason})" if s.reason else ""))
                if s.run_id == run_id and s.stage in FINAL_STAGES:
                    return s
            # woken by the next state (`stop` is looked at every STOP_CHECK_S)
            self.run_state.wait(STOP_CHECK_S if deadline is None else max(0.0, min(STOP_CHECK_S, deadline - time.monotonic())), newer_than=seen)
        return None

    # -- tear-down -------------------------------------------------------------------------------

    def stop(self, grace_s: float = 10.0) -> dict[str, int | None]:
        """SIGTERM every child's process group, SIGKILL what is left after `grace_s`; their exit codes."""
        self._stopping.set()
        self._wake.set()
        if self._supervisor is not None:
            self._supervisor.join(timeout=2.0)
        procs = {n: c.proc for n, c in self.children.items() if c.proc is not None}
        deadline = time.monotonic() + grace_s
        codes: dict[str, int | None] = {}
        # The services another one needs (the simulator, whose CR5s the arm driver disables as it closes)
        # stop after the rest, which stop side by side: so each closes against live peers, not time-outs.
        needed = set(AFTER.values())
        last = {n: p for n, p in procs.items() if n in needed}
        for group in ({n: p for n, p in procs.items() if n not in last}, last):
            for p in group.values():
                _signal_group(p, signal.SIGTERM)
            for n, p in group.items():
                try:
                    codes[n] = p.wait(timeout=max(0.1, deadline - time.monotonic()))
                except subprocess.TimeoutExpired:
                    self.say(f"{n} did not stop in {grace_s:g} s: killed")
                    _signal_group(p, signal.SIGKILL)
                    codes[n] = p.wait(timeout=5)
                _signal_group(p, signal.SIGKILL)  # anything the service started and left behind
        for x in (self.run_state, self.truth, self.arm_states, self.watcher):
            if x is not None:
                x.close()
        if self.session is not None:
            self.session.close()
            self.session = None
        if self.forks is not None:
            self.forks.close()
            self.forks = None
        if self._own_dir:  # a scratch folder of ours (generated configs, status): gone with the rig
            shutil.rmtree(self.dir, ignore_errors=True)
        return codes

    def __enter__(self) -> Up:
        return self

    def __exit__(self, *_: Any) -> None:
        self.stop()


def _signal_group(p: subprocess.Popen | ForkedProcess, sig: int) -> None:
    try:
        os.killpg(p.pid, sig)  # the child is its own process group's leader (setsid)
    except (ProcessLookupError, PermissionError):
        pass
