"""The rig split across machines, proven on one: `bagit bench multihost` (as root).

Four Linux network namespaces stand in for the lab's machines (deploy/README.md), each with its own
address from 198.18.0.0/15 (the range set aside for network tests) and joined only by veth links:

    plan   198.18.0.10  the router, planner, controller, dashboard, recorder; a bridge (the lab switch)
    cam    198.18.0.11  the simulator (its camera) and perception           -- veth to plan's bridge
    arms   198.18.0.12  the arm driver; 198.19.5.1 on the robot LAN         -- veth to plan's bridge
    robot  198.19.5.11 / .12  the two simulated CR5 controllers             -- veth to arms only

No default route, nothing bridged to a real interface: traffic cannot leave. Every service is started
from the committed Procfiles (deploy/Procfile.*) with the committed host configs installed per host
(as a lab installs them under /etc/bagit; here under a scratch folder per host, the Procfile's paths
rewritten to it), on the secured rig (deploy/secure/: mutual TLS and the ACL, throwaway certificates).
The simulator runs on `cam` (its camera is cam's) and opens its CR5 listeners on the robot LAN
(`bagit sim --cr5-netns`). The bench itself is the operator's console on `plan` (identity `cli`).

Scenarios, in order: a lockstep run against `bagit run` (bit for bit); a wall-clock run (real-time
factor, watchdog stops); cam's clock 0.3 s ahead, then behind (libfaketime); the arms' cable pulled
mid-run and plugged back; the recorder's disk full (a small tmpfs); cam's services restarted. Every
namespace, link, mount and process is removed at the end, after a failure or Ctrl-C too; their names
start with PREFIX, so what a killed bench left is removed by the next start (`clean_leftovers`).

    bagit bench multihost [--json] [--quick] [--scenario exp02] [--out DIR]

`--quick` (the integration test) brings the rig up on the wall clock and pulls the cable in a run's
servoing, then starts the next run. Not root: one line, exit status 2.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

import numpy as np

from bagit.bench.common import RESULTS_DIR, machine
from bagit.bench.stop_time import TARGET_S
from bagit.common.errors import BagItError
from bagit.forkserver import child_setup
from bagit.up import NICED, OFF_PATH_NICENESS, follow_arm_events

log = logging.getLogger("bagit.bench.multihost")

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
PREFIX = "bagit-mh"  # namespaces PREFIX-<host>, scratch folders PREFIX-*; links start with LINK
LINK = "bmh"  # interface names (at most 15 characters): bmh-br, bmh-cam0/bmh-cam1, ...
RIG = "mh"
LAN = "198.18.0"  # the lab network (plan's bridge), /24
ROBOT_LAN = "198.19.5"  # the robot LAN between arms and the CR5s, /24
ROUTER_PORT = 7447
# host -> (address, the Procfile it runs, the Zenoh host config it installs)
HOSTS: dict[str, tuple[str, str | None, str | None]] = {
    "plan": (f"{LAN}.10", "Procfile.planner-controller", "host-planner-controller.json5"),
    "cam": (f"{LAN}.11", "Procfile.camera-perception", "host-camera-perception.json5"),
    "arms": (f"{LAN}.12", "Procfile.arm-driver", "host-arm-driver.json5"),
    "robot": (f"{ROBOT_LAN}.11", None, None),
}
ARMS_ON_ROBOT_LAN = f"{ROBOT_LAN}.1"
CR5_ADDRESSES = {"left": f"{ROBOT_LAN}.11", "right": f"{ROBOT_LAN}.12"}
SKEWS_S = (0.3, -0.3)
WATCHDOG_GOAL_MS = 1000.0 * TARGET_S  # the arms still within this of the last command that reached them (bench.stop_time's goal)
STILL_MM_S = 1.0  # "still": both controllers' TCP speed below this
MOVING_MPS = 0.01  # the cable is pulled right after a command asking at least this speed of a mount
FAKETIME_LIB = Path("/usr/lib/x86_64-linux-gnu/faketime/libfaketimeMT.so.1")  # Debian's `faketime`
TMPFS_KB = 3072  # the recorder's disk in the full-disk scenario (the 3 MB)
READY_S = 240.0  # services up (imports on a loaded machine)
RUN_S = 600.0  # one run's wall time at most


class NotRoot(BagItError):
    """Namespaces need root: said in one line, exit status 2."""


def need_root() -> None:
    if os.geteuid() != 0:
        raise NotRoot("bagit bench multihost needs root (Linux network namespaces); run it as root, or skip it")


def ns_name(host: str) -> str:
    return f"{PREFIX}-{host}"


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    r = subprocess.run(["ip", *args], capture_output=True, text=True)
    if check and r.returncode != 0:
        raise BagItError(f"ip {' '.join(args)}: {r.stderr.strip()}")
    return r


def clean_leftovers() -> list[str]:
    """Remove what an earlier bench left (its processes, namespaces, /etc/netns entries, tmpfs mounts,
    scratch folders): everything named with PREFIX/LINK. Returns what was removed."""
    removed = []
    for line in _ip("netns", "list", check=False).stdout.splitlines():
        name = line.split()[0] if line.strip() else ""
        if name.startswith(f"{PREFIX}-"):
            for pid in _ip("netns", "pids", name, check=False).stdout.split():
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            _ip("netns", "del", name, check=False)
            removed.append(f"netns {name}")
    for line in _ip("-o", "link", "show", check=False).stdout.splitlines():
        parts = line.split(":")
        if len(parts) > 1 and parts[1].strip().split("@")[0].startswith(f"{LINK}-"):
            dev = parts[1].strip().split("@")[0]
            _ip("link", "del", dev, check=False)
            removed.append(f"link {dev}")
    for d in Path("/etc/netns").glob(f"{PREFIX}-*"):
        shutil.rmtree(d, ignore_errors=True)
        removed.append(str(d))
    tmp = Path(tempfile.gettempdir())
    for line in Path("/proc/mounts").read_text().splitlines():
        mnt = line.split()[1]
        if mnt.startswith(str(tmp / PREFIX)):
            subprocess.run(["umount", "-l", mnt], capture_output=True)
            removed.append(f"mount {mnt}")
    for d in tmp.glob(f"{PREFIX}-*"):
        shutil.rmtree(d, ignore_errors=True)
        removed.append(str(d))
    return removed


def procfile(path: Path) -> dict[str, str]:
    """A Procfile's processes: name -> command line (as honcho reads it)."""
    out = {}
    for ln in path.read_text().splitlines():
        if ln.strip() and not ln.lstrip().startswith("#"):
            name, _, cmd = ln.partition(":")
            out[name.strip()] = cmd.strip()
    return out


def bagit_exe() -> str:
    exe = Path(sys.executable).with_name("bagit")
    return shlex.quote(str(exe)) if exe.exists() else f"{shlex.quote(sys.executable)} -m bagit.cli"


@dataclass
class Proc:
    host: str
    name: str
    cmd: str
    env: dict[str, str]
    log: Path
    popen: subprocess.Popen[bytes] | None = None


@dataclass
class Lab:
    """The namespaces, links, per-host files and processes (a context manager; see the module doc)."""

    clock: str = "wall"  # "lockstep" (BAGIT_CLOCK=sim) or "wall"
    scenario: str = "exp02"
    seed: int = 0
    root: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix=f"{PREFIX}-")))
    procs: dict[str, Proc] = field(default_factory=dict)
    mounts: list[Path] = field(default_factory=list)
    _root_ns: int | None = None

    # -- the network ---------------------------------------------------------------------------

    def __enter__(self) -> Lab:
        need_root()
        left = clean_leftovers()
        if left:
            log.info("removed what an earlier run left: %s", ", ".join(left))
        self.root.mkdir(parents=True, exist_ok=True)
        try:
            self._network()
            self.write_files()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _network(self) -> None:
        for h in HOSTS:
            _ip("netns", "add", ns_name(h))
            _ip("-n", ns_name(h), "link", "set", "lo", "up")
        plan = ns_name("plan")
        _ip("-n", plan, "link", "add", f"{LINK}-br", "type", "bridge")
        _ip("-n", plan, "addr", "add", f"{HOSTS['plan'][0]}/24", "dev", f"{LINK}-br")
        _ip("-n", plan, "link", "set", f"{LINK}-br", "up")
        for h in ("cam", "arms"):  # a cable from each host to the switch on plan
            _ip("link", "add", f"{LINK}-{h}0", "netns", plan, "type", "veth", "peer", "name", f"{LINK}-{h}1", "netns", ns_name(h))
            _ip("-n", plan, "link", "set", f"{LINK}-{h}0", "master", f"{LINK}-br")
            _ip("-n", plan, "link", "set", f"{LINK}-{h}0", "up")
            _ip("-n", ns_name(h), "addr", "add", f"{HOSTS[h][0]}/24", "dev", f"{LINK}-{h}1")
            _ip("-n", ns_name(h), "link", "set", f"{LINK}-{h}1", "up")
        robot = ns_name("robot")  # the robot LAN: arms' second interface, the two controllers
        _ip("link", "add", f"{LINK}-rob0", "netns", ns_name("arms"), "type", "veth", "peer", "name", f"{LINK}-rob1", "netns", robot)
        _ip("-n", ns_name("arms"), "addr", "add", f"{ARMS_ON_ROBOT_LAN}/24", "dev", f"{LINK}-rob0")
        _ip("-n", ns_name("arms"), "link", "set", f"{LINK}-rob0", "up")
        for a in CR5_ADDRESSES.values():
            _ip("-n", robot, "addr", "add", f"{a}/24", "dev", f"{LINK}-rob1")
        _ip("-n", robot, "link", "set", f"{LINK}-rob1", "up")
        for h in HOSTS:  # each host's /etc/hosts names the router (deploy/README.md step 2); `ip netns exec` mounts it
            d = Path("/etc/netns") / ns_name(h)
            d.mkdir(parents=True, exist_ok=True)
            (d / "hosts").write_text(f"127.0.0.1 localhost\n{HOSTS['plan'][0]} bagit-router\n")

    def cable(self, host: str, up: bool) -> None:
        """Plug or pull `host`'s cable at the switch."""
        _ip("-n", ns_name("plan"), "link", "set", f"{LINK}-{host}0", "up" if up else "down")

    def namespaces(self) -> dict[str, str]:
        """Each running service's network namespace (its /proc/PID/ns/net inode)."""
        out = {}
        for key, p in self.procs.items():
            if p.popen is not None and p.popen.poll() is None:
                try:
                    out[key] = os.readlink(f"/proc/{p.popen.pid}/ns/net")
                except OSError:
                    pass
        return out

    # -- files ---------------------------------------------------------------------------------

    def etc(self, host: str) -> Path:
        return self.root / host / "etc" / "bagit"

    def write_files(self) -> None:
        """What a lab installs on each host (deploy/README.md steps 4 and 'Securing'): the secured client
        config as the host's Zenoh config, the router's, the rig file, the service configs, the certificates."""
        from bagit.common.rig import RigConfig
        from bagit.deploy.certs import SERVICES, write_lab_pki
        from bagit.up import SIM_DRIVER_TIMEOUTS, lab_perception_config

        pki = self.root / "pki"
        write_lab_pki(pki, list(SERVICES), ["bagit-router", HOSTS["plan"][0]])
        rig = RigConfig(name=RIG)
        rig = rig.model_copy(update={"arms": {a: rig.arms[a].model_copy(update={"host": CR5_ADDRESSES[a], "dashboard_port": 29999,
                                                                                 "feedback_port": 30004}) for a in rig.arms}})
        for h, (_, _, zcfg) in HOSTS.items():
            etc = self.etc(h)
            (etc / "tls").mkdir(parents=True, exist_ok=True)
            (etc / "secure").mkdir(exist_ok=True)
            for f in pki.iterdir():
                if f.name != "ca.key":  # the CA key stays on the trusted machine
                    shutil.copy2(f, etc / "tls" / f.name)
            self._install(DEPLOY / "secure" / "client.json5", etc / "secure" / "client.json5")
            if zcfg is not None:  # a secured rig: every host's Zenoh config is the secure client's
                self._install(DEPLOY / "secure" / "client.json5", etc / zcfg)
            (etc / "rig.yaml").write_text(rig.to_yaml())
        self._install(DEPLOY / "secure" / "zenoh-router-secure.json5", self.etc("plan") / "secure" / "zenoh-router-secure.json5")
        from bagit.common.names import SIM_TIME_LIMIT_S
        from bagit.up import WALL_TIME_LIMIT_S

        limit = SIM_TIME_LIMIT_S if self.clock == "lockstep" else WALL_TIME_LIMIT_S
        configs = {
            ("plan", "planner.yaml"): {"coordinator": {"run_time_limit_s": limit}},
            ("plan", "controller.yaml"): {"rig_config": "rig.yaml"},
            ("cam", "perception.yaml"): {"source": {"kind": "zenoh"}, "rig_config": "rig.yaml", **lab_perception_config(self.scenario)},
            ("arms", "arm-driver.yaml"): {"rig_config": "rig.yaml", "driver": SIM_DRIVER_TIMEOUTS},
        }
        for (h, name), data in configs.items():
            (self.etc(h) / name).write_text(json.dumps(data, indent=2))

    def _install(self, src: Path, dst: Path) -> None:
        """Copy a committed file to a host, its /etc/bagit paths pointing at the host's folder."""
        host = dst.relative_to(self.root).parts[0]
        dst.write_text(src.read_text().replace("/etc/bagit", str(self.etc(host))))

    # -- processes -------------------------------------------------------------------------------

    def env(self, host: str, extra: dict[str, str] | None = None) -> dict[str, str]:
        from bagit.common.headless import headless_gl

        env = headless_gl(dict(os.environ, PYTHONUNBUFFERED="1", BAGIT_RIG=RIG, BAGIT_TLS=str(self.etc(host) / "tls"),
                               BAGIT_RECORDINGS=str(self.recordings)))
        env.pop("BAGIT_CLOCK", None)
        if self.clock == "lockstep":
            env["BAGIT_CLOCK"] = "sim"
        return {**env, **(extra or {})}

    @property
    def recordings(self) -> Path:
        return self.root / "plan" / "recordings"

    def commands(self, host: str) -> dict[str, str]:
        """The host's processes: its Procfile's lines, for this host's files (and cam's simulator)."""
        _, pf, zcfg = HOSTS[host]
        out: dict[str, str] = {}
        if host == "plan":
            out.update(procfile(DEPLOY / "Procfile.router"))
        if host == "cam":  # the simulated rig: camera and world on cam, its two CR5s on the robot LAN
            out["sim"] = (f"bagit sim {self.scenario} --rig ${{BAGIT_RIG:-lab}} --zenoh-config /etc/bagit/{zcfg} --rig-config /etc/bagit/rig.yaml "
                          f"--seed {self.seed} --cr5-netns {ns_name('robot')} --tls-ca $BAGIT_TLS/ca.pem --tls-cert $BAGIT_TLS/sim.pem "
                          f"--tls-key $BAGIT_TLS/sim.key ${{BAGIT_CLOCK:+--clock $BAGIT_CLOCK}}")
        if pf is not None:
            out.update(procfile(DEPLOY / pf))
        exe = bagit_exe()
        return {n: exe + c.removeprefix("bagit").replace("/etc/bagit", str(self.etc(host))) for n, c in out.items()}

    def start_host(self, host: str, extra_env: dict[str, str] | None = None) -> None:
        for name, cmd in self.commands(host).items():
            env = self.env(host, extra_env)
            if name == "router":
                etc = self.etc("plan")
                env["BAGIT_ROUTER_ARGS"] = (f"--zenoh-config {etc}/secure/zenoh-router-secure.json5 --listen tls/0.0.0.0:{ROUTER_PORT} "
                                            f"--tls-ca {etc}/tls/ca.pem --tls-cert {etc}/tls/router.pem --tls-key {etc}/tls/router.key")
            self.start(host, name, cmd, env)

    def start(self, host: str, name: str, cmd: str, env: dict[str, str]) -> None:
        logs = self.root / "logs"
        logs.mkdir(exist_ok=True)
        p = Proc(host, name, cmd, env, logs / f"{host}-{name}.log")
        nice = OFF_PATH_NICENESS if name in NICED else 0  # as bagit up runs them
        setup = functools.partial(child_setup, nice, signal.SIGKILL)  # SIGKILL when the bench dies: never outlive it
        with p.log.open("a") as out:
            p.popen = subprocess.Popen(["ip", "netns", "exec", ns_name(host), "sh", "-c", f"exec {cmd}"], env=env, stdin=subprocess.DEVNULL,
                                       stdout=out, stderr=subprocess.STDOUT, preexec_fn=setup)
        self.procs[f"{host}/{name}"] = p
        log.info("started %s on %s (pid %d)", name, host, p.popen.pid)

    def start_service(self, host: str, name: str) -> None:
        self.start(host, name, self.commands(host)[name], self.env(host))

    def stop_service(self, host: str, name: str) -> None:
        self.stop_host(host, only=name)

    def stop_host(self, host: str, sig: int = signal.SIGTERM, grace_s: float = 10.0, only: str | None = None) -> None:
        """Stop `host`'s processes (SIGTERM, SIGKILL after `grace_s`), as a host that shuts down."""
        mine = [k for k, p in self.procs.items() if p.host == host and only in (None, p.name)]
        for k in mine:
            _signal(self.procs[k].popen, sig)
        deadline = time.monotonic() + grace_s
        for k in mine:
            pp = self.procs.pop(k).popen
            if pp is None:
                continue
            try:
                pp.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                _signal(pp, signal.SIGKILL)
                pp.wait(5)

    def stop_all(self) -> None:
        for h in ("arms", "cam", "plan", "robot"):  # the arm driver first: it disables the arms against live CR5s
            self.stop_host(h)

    def exited(self) -> dict[str, int]:
        return {k: p.popen.returncode for k, p in self.procs.items() if p.popen is not None and p.popen.poll() is not None}

    # -- the disk ------------------------------------------------------------------------------

    def small_disk(self, path: Path, kb: int = TMPFS_KB) -> None:
        path.mkdir(parents=True, exist_ok=True)
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={kb}k", f"{PREFIX}-disk", str(path)], capture_output=True, text=True)
        if r.returncode != 0:
            raise BagItError(f"mount tmpfs on {path}: {r.stderr.strip()}")
        self.mounts.append(path)

    # -- the end ---------------------------------------------------------------------------------

    def close(self) -> None:
        """Every process, mount, namespace (with its links) and file of this lab, whatever happened."""
        try:
            self.stop_all()
        finally:
            for m in self.mounts:
                subprocess.run(["umount", "-l", str(m)], capture_output=True)
            self.mounts.clear()
            for h in HOSTS:
                for pid in _ip("netns", "pids", ns_name(h), check=False).stdout.split():
                    try:
                        os.kill(int(pid), signal.SIGKILL)
                    except (ProcessLookupError, ValueError):
                        pass
                _ip("netns", "del", ns_name(h), check=False)
                shutil.rmtree(Path("/etc/netns") / ns_name(h), ignore_errors=True)
            shutil.rmtree(self.root, ignore_errors=True)


def _signal(p: subprocess.Popen[bytes] | None, sig: int) -> None:
    if p is None:
        return
    try:
        os.killpg(p.pid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def leftovers() -> list[str]:
    """What of a bench is still on this machine (namespaces, links, /etc/netns entries, mounts): nothing, after one."""
    out = [ln.split()[0] for ln in _ip("netns", "list", check=False).stdout.splitlines() if ln.startswith(f"{PREFIX}-")]
    out += [ln.split(":")[1].strip() for ln in _ip("-o", "link", "show", check=False).stdout.splitlines() if f" {LINK}-" in ln]
    out += [str(d) for d in Path("/etc/netns").glob(f"{PREFIX}-*")]
    out += [ln.split()[1] for ln in Path("/proc/mounts").read_text().splitlines() if f"/{PREFIX}-" in ln.split()[1]]
    return out


@contextmanager
def signals_raise() -> Iterator[None]:
    """SIGTERM (and SIGINT) end the bench through KeyboardInterrupt, so the lab's `with` cleans up."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def on_signal(signum: int, frame: FrameType | None) -> None:
        if frame is not None and frame.f_code.co_filename == logging.__file__:
            # inside logging: its at-fork hooks (a Popen starting a service) swallow what is raised there;
            # SIGALRM brings the handler back in 50 ms, past them
            signal.setitimer(signal.ITIMER_REAL, 0.05)
            return
        raise KeyboardInterrupt

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGALRM)}
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        for s, h in previous.items():
            signal.signal(s, h)


# -- the operator's console on plan ------------------------------------------------------------

SERVICES = ("sim", "perception", "planner", "controller", "arm-driver", "dashboard", "recorder")


class Console:
    """The bench's own Zenoh session, a client of the secured router on `plan` with the `cli` identity:
    starts runs, follows run/state, and watches what `bagit up` watches to judge a run (the
    simulator's truth, the arm side's events), the commands and the recorder's status."""

    def __init__(self, lab: Lab) -> None:
        from bagit.common.bus import BusConfig, Keys, LatestCache, LivelinessWatcher, Subscriber, open_session
        from bagit.common.messages import Command, RecorderStatus, RunState, SimTruth
        from bagit.common.netns import entered_netns

        etc = lab.etc("plan")
        self.lab = lab
        self.keys = Keys(RIG)
        cfg = BusConfig(rig=RIG, config_file=etc / "secure" / "client.json5", connect=[f"tls/{HOSTS['plan'][0]}:{ROUTER_PORT}"],
                        tls_ca=etc / "tls" / "ca.pem", tls_cert=etc / "tls" / "cli.pem", tls_key=etc / "tls" / "cli.key")
        with entered_netns(ns_name("plan")):  # the session's threads and sockets are plan's
            self.session = open_session(cfg)
        self.watcher = LivelinessWatcher(self.session, self.keys)
        self.run_state = LatestCache(self.session, self.keys.run_state, RunState)
        self.truth = LatestCache(self.session, self.keys.sim_truth, SimTruth)
        self.arm_states = follow_arm_events(self.session, self.keys)
        self.recorder = LatestCache(self.session, self.keys.recorder_status, RecorderStatus)
        self.final_truths: dict[str, SimTruth] = {}
        self.cmds: list[tuple[float, Command]] = []
        self.on_cmd: Any = None
        self._subs: list[Subscriber[Any]] = [Subscriber(self.session, self.keys.sim_truth, SimTruth, self._on_truth),
                      Subscriber(self.session, self.keys.controller_cmd, Command, self._on_cmd)]

    def _on_truth(self, t: Any) -> None:
        if t.final and t.run_id is not None:
            self.final_truths[t.run_id] = t

    def _on_cmd(self, c: Any) -> None:
        t = time.monotonic()
        self.cmds.append((t, c))
        if self.on_cmd is not None:
            self.on_cmd(t, c)

    def wait_alive(self, services: tuple[str, ...] = SERVICES, timeout: float = READY_S) -> list[str]:
        """Wait until every one of `services` holds its liveliness token; the ones still missing."""
        deadline = time.monotonic() + timeout
        while True:
            missing = sorted(set(services) - self.watcher.alive())
            if not missing or time.monotonic() > deadline:
                return missing
            dead = self.lab.exited()
            if dead:
                raise BagItError(f"exited before the rig was up: {dead}; logs in {self.lab.root / 'logs'}")
            time.sleep(0.2)

    def run(self, scenario: str, seed: int, on_stage: Any = None, until: Any = None, timeout: float = RUN_S) -> Any:
        """One run started as the CLI starts it, followed to its end (or until `until(state)`, then stopped as
        the dashboard's Stop does); its RunResult as `bagit up` gives it."""
        from bagit.commands.up import recording_of_run, run_result
        from bagit.common.bus import request_run_control
        from bagit.common.messages import RunControl
        from bagit.common.names import FINAL_STAGES
        from bagit.common.results import RunResult

        t0 = time.monotonic()
        before = self.recorder.get()
        rep = request_run_control(self.session, self.keys, RunControl(action="start", scenario=scenario, seed=seed), timeout=30.0)
        if not rep.accepted:
            return RunResult(scenario=scenario, seed=seed, reason=f"run refused: {rep.reason}")
        stages: list[str] = []
        state = None
        stop = threading.Event()
        while time.monotonic() - t0 < timeout:
            s = self.run_state.get()
            if s is not None and s.run_id == rep.run_id:
                if not stages or stages[-1] != s.stage:
                    stages.append(s.stage)
                    log.info("run %s: %s%s", rep.run_id, s.stage, f" ({s.reason})" if s.reason else "")
                    if on_stage is not None:
                        on_stage(s)
                    if until is not None and until(s) and s.stage not in FINAL_STAGES:
                        until = None
                        request_run_control(self.session, self.keys, RunControl(action="stop"), timeout=30.0)
                if s.stage in FINAL_STAGES:
                    state = s
                    break
            time.sleep(0.02)
        args = argparse.Namespace(scenario=scenario, controller=None, planner=None, seed=seed, timeout=timeout,
                                  clock="lockstep" if self.lab.clock == "lockstep" else "wall")
        recording = recording_of_run(self.recorder, before)
        res = run_result(self, rep.run_id, state, stop, args, time.monotonic() - t0, recording)
        self.stages = stages
        return res

    def close(self) -> None:
        for sub in self._subs:
            sub.close()
        self.run_state.close()
        self.truth.close()
        self.arm_states.close()
        self.recorder.close()
        self.watcher.close()
        self.session.close()

    def __enter__(self) -> Console:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def bring_up(lab: Lab, clock: str) -> None:
    """Every host's services on `clock`, started as a lab starts them: the router host first, then cam
    (the simulator's CR5s are the robot LAN's controllers), then the arms once those are up."""
    lab.stop_all()
    lab.clock = clock
    lab.write_files()
    lab.start_host("plan")
    lab.start_host("cam")


def finish_bring_up(lab: Lab, con: Console) -> None:
    missing = con.wait_alive(("sim",))
    if missing:
        raise BagItError(f"the simulator is not up after {READY_S:g} s; logs in {lab.root / 'logs'}")
    lab.start_host("arms")
    missing = con.wait_alive()
    if missing:
        raise BagItError(f"services not up after {READY_S:g} s: {', '.join(missing)}; logs in {lab.root / 'logs'}")


def restart_cam(lab: Lab, con: Console, extra_env: dict[str, str] | None = None) -> None:
    """cam's services stopped (a host that reboots) and started again, maybe with another environment."""
    lab.stop_host("cam")
    con.watcher.wait_for("perception", False, 10.0)
    lab.start_host("cam", extra_env)
    missing = con.wait_alive()
    if missing:
        raise BagItError(f"cam's services not back after {READY_S:g} s: {', '.join(missing)}")


# -- the scenarios -------------------------------------------------------------------------------


def soi_judgement(cmds: list[tuple[float, Any]], offset_s: float, max_age_s: float, tol_s: float = 0.02) -> dict[str, int]:
    """The controller's commands against the SOIs' true ages (cam's clock `offset_s` off plan's): holds
    for a stale SOI that was fresh, and servo steps on one that was stale (beyond `tol_s`, the transit the
    controller does not see)."""
    fresh_as_stale = stale_as_fresh = judged = 0
    for _, c in cmds:
        if not c.source_stamp or not c.stamp:
            continue
        true_age = c.stamp - (c.source_stamp - offset_s)
        judged += 1
        stale_hold = c.mode == "hold" and (c.reason or "").startswith("SOI is stale")
        if stale_hold and true_age < max_age_s - tol_s:
            fresh_as_stale += 1
        if c.mode == "servo" and true_age > max_age_s + tol_s:
            stale_as_fresh += 1
    return {"commands": judged, "fresh_taken_as_stale": fresh_as_stale, "stale_taken_as_fresh": stale_as_fresh}


def arms_still_after(last_cmd: float, recs: dict[str, Any], horizon_s: float = 3.0) -> dict[str, float] | None:
    """From `last_cmd` (monotonic) until both arms' feedback stays below STILL_MM_S (the later arm): `ms` on
    the controllers' own clock (RunTime: the simulated CR5s step with the world, which a loaded machine
    slows below the wall clock; a real CR5's is the wall clock), `wall_ms` on this one's, and the
    controllers' real-time factor meanwhile. None if they still move at the end of the window."""
    ctl, wall, rtf = [], [], []
    for rec in recs.values():
        tf, speed = rec.series("TCPSpeedActual", last_cmd - 0.2, last_cmd + horizon_s)
        _, run_ms = rec.series("RunTime", last_cmd - 0.2, last_cmd + horizon_s)
        after = np.flatnonzero(tf >= last_cmd)
        if after.size == 0 or after[0] == 0:
            return None
        k = after[0] - 1  # the controller's last packet before the command: its clock then
        v = np.linalg.norm(speed[:, :3], axis=1)
        moving = np.flatnonzero(v[k:] >= STILL_MM_S) + k
        i = moving[-1] + 1 if moving.size else k
        if i >= len(v):
            return None
        ctl.append(float(run_ms[i] - run_ms[k]))
        wall.append(1e3 * float(tf[i] - last_cmd))
        rtf.append(float(run_ms[-1] - run_ms[k]) / 1e3 / max(float(tf[-1] - tf[k]), 1e-9))
    return {"ms": round(max(ctl), 1), "wall_ms": round(max(wall), 1), "controllers_rtf": round(float(np.mean(rtf)), 3)}


def tcp_speed_mm_s(rec: Any, t: float) -> float:
    """An arm's TCP speed (mm/s, its feedback) at monotonic time `t` (the packet nearest before it; 0 without one)."""
    tf, speed = rec.series("TCPSpeedActual", t - 0.1, t)
    return round(float(np.linalg.norm(speed[-1, :3])), 1) if tf.size else 0.0


def cut_cable(lab: Lab, con: Console, scenario: str, seed: int, quick: bool) -> dict[str, Any]:
    """The arms' cable pulled in the run's servoing, right after a command passed the router; plugged
    back after the run failed; then the next run (to its end, or with `quick` to its servoing)."""
    from bagit.common.names import SERVO_STAGES
    from bagit.common.netns import entered_netns
    from bagit.services.sim.harness import FeedbackRecorder

    with entered_netns(ns_name("robot")):  # the controllers' feedback, read on the robot LAN
        recs = {a: FeedbackRecorder(30004, host) for a, host in CR5_ADDRESSES.items()}
    cut: dict[str, float] = {}
    servoing, trigger = threading.Event(), threading.Event()

    def on_cmd(t: float, c: Any) -> None:  # some way into the servoing, right after a command that moves the arms went by
        if servoing.is_set() and c.mode == "servo" and c.seq > 30 and float(np.linalg.norm(c.u[:3])) / c.dt > MOVING_MPS:
            trigger.set()

    def pull() -> None:  # on its own thread: the commands' arrival times stay true meanwhile
        if trigger.wait(RUN_S):
            cut["start"] = time.monotonic()
            lab.cable("arms", up=False)
            cut["t"] = time.monotonic()

    puller = threading.Thread(target=pull, name="pull-cable", daemon=True)
    puller.start()
    con.on_cmd = on_cmd
    try:
        res = con.run(scenario, seed, on_stage=lambda s: servoing.set() if s.stage in SERVO_STAGES else None)
    finally:
        con.on_cmd = None
        trigger.set()
        puller.join()
    if "t" not in cut:
        lab.cable("arms", up=True)
        for r in recs.values():
            r.close()
        return {"success": False, "reason": f"the run never servoed long enough to pull the cable: {res.reason}"}
    # The last command that reached the arms: at the latest the last one past the router before the pull
    # began (one that passed while `ip` ran may have reached them too: then the arms stopped sooner than said).
    cut["last_cmd"] = max(t for t, _ in con.cmds if t <= cut["start"])
    stages = list(con.stages)
    still = arms_still_after(cut["last_cmd"], recs)
    speed = max(tcp_speed_mm_s(r, cut["last_cmd"]) for r in recs.values())
    for r in recs.values():
        r.close()
    after_cut = [c.seq for t, c in con.cmds if t > cut["t"]]
    pull_ms = round(1e3 * (cut["t"] - cut["start"]), 1)
    lab.cable("arms", up=True)
    back = con.watcher.wait_for("arm-driver", True, 60.0)
    running = {k: p.popen.poll() is None for k, p in lab.procs.items() if p.popen is not None}
    nxt = next_run(con, scenario, seed, quick)
    return {"arms_stopped_ms": still["ms"] if still else None, "arms_stopped_wall_ms": still["wall_ms"] if still else None,
            "controllers_rtf": still["controllers_rtf"] if still else None, "goal_ms": WATCHDOG_GOAL_MS, "moving_mm_s": speed,
            "pull_ms": pull_ms, "reason": res.reason,
            "run_success": res.success, "stages": stages, "arm_driver_back": back, "all_processes_running": all(running.values()),
            "commands_seen_after_cut": len(after_cut), **nxt}


def next_run(con: Console, scenario: str, seed: int, quick: bool) -> dict[str, Any]:
    """The next run: to its end, or (quick) until the arms servo in it (then it is stopped)."""
    from bagit.common.names import SERVO_STAGES

    r = con.run(scenario, seed, until=(lambda s: s.stage in SERVO_STAGES) if quick else None)
    if quick:
        return {"next_run_servoing": any(st in SERVO_STAGES for st in con.stages), "next_run_stages": list(con.stages)}
    return {"next_run_success": r.success, "next_run_reason": r.reason}


def lockstep_run(con: Console, scenario: str, seed: int) -> dict[str, Any]:
    """A lockstep run across the hosts against `bagit run`'s run of the same scenario and seed."""
    from bagit.bench.deployed import alone, compare
    from bagit.common.names import DEFAULT_CONTROLLER

    up = con.run(scenario, seed)
    run, _ = alone(scenario, seed, DEFAULT_CONTROLLER)
    return {**compare(run, up), "exact": up.exact, "success": up.success, "reason": up.reason, "object_from": up.object_from,
            "up": {"error_cm": up.error_cm, "ticks": up.ticks, "duration_s": up.duration_s},
            "run": {"error_cm": run.error_cm, "ticks": run.ticks, "duration_s": run.duration_s}}


def wall_run(con: Console, scenario: str, seed: int, offset_s: float = 0.0) -> dict[str, Any]:
    """A run on the wall clock: its result, real-time factor, watchdog stops and how the SOIs' ages were judged."""
    from bagit.services.controller.session import SOI_MAX_AGE_S

    con.cmds.clear()
    r = con.run(scenario, seed)
    return {"success": r.success, "reason": r.reason, "error_cm": r.error_cm, "object_from": r.object_from,
            "realtime_factor": r.truth.realtime_factor if r.truth is not None else None,
            "watchdog_stops": r.arm_events.get("watchdog_stops"), "soi": soi_judgement(list(con.cmds), offset_s, SOI_MAX_AGE_S),
            "recording": r.recording.model_dump(mode="json") if r.recording is not None else None}


def skewed(lab: Lab, con: Console, scenario: str, seed: int, offset_s: float) -> dict[str, Any]:
    """cam's wall clock `offset_s` off (libfaketime on cam's processes; their monotonic clocks stay true)."""
    if not FAKETIME_LIB.exists():
        return {"success": False, "reason": f"no {FAKETIME_LIB} (apt-get install faketime)"}
    restart_cam(lab, con, {"LD_PRELOAD": str(FAKETIME_LIB), "FAKETIME": f"{offset_s:+g}", "FAKETIME_DONT_FAKE_MONOTONIC": "1"})
    return wall_run(con, scenario, seed, offset_s)


def disk_full(lab: Lab, con: Console, scenario: str, seed: int) -> dict[str, Any]:
    """The recorder's folder on a small tmpfs, filled before the run; emptied after it."""
    lab.stop_service("plan", "recorder")
    con.watcher.wait_for("recorder", False, 10.0)
    d = lab.recordings
    lab.small_disk(d)
    filler = d / "filler"
    with filler.open("wb") as f:
        try:
            while True:
                f.write(b"\0" * 65536)
                f.flush()
        except OSError:
            pass
    lab.start_service("plan", "recorder")
    if con.wait_alive(("recorder",)):
        return {"run_success": False, "reason": "the recorder did not come back"}
    r = con.run(scenario, seed)
    files = sorted(p.name for p in d.glob("*.mcap"))
    rec = r.recording
    before = con.recorder.get()
    filler.unlink()
    deadline = time.monotonic() + 30.0
    resumed = False
    while time.monotonic() < deadline and not resumed:
        now = con.recorder.get()
        resumed = bool(now is not None and before is not None and now.messages > before.messages)
        time.sleep(0.2)
    lab.stop_service("plan", "recorder")
    subprocess.run(["umount", "-l", str(d)], capture_output=True)
    lab.mounts.remove(d)
    lab.start_service("plan", "recorder")
    con.wait_alive(("recorder",))
    return {"run_success": r.success, "run_reason": r.reason, "recording_reported": bool(rec is not None and not rec.ok),
            "messages_lost": rec.lost if rec is not None else None, "recording": rec.model_dump(mode="json") if rec is not None else None,
            "files_while_full": files, "resumed": resumed}


def measure(scenario: str = "exp02", seed: int = 0, quick: bool = False) -> dict[str, Any]:
    """Every scenario on one lab (see the module doc); the record's body."""
    out: dict[str, Any] = {"scenario": scenario, "seed": seed, "quick": quick, "tls": True}
    with signals_raise(), Lab(scenario=scenario, seed=seed) as lab:
        out["hosts"] = {h: {"address": a, "namespace": ns_name(h), "services": []} for h, (a, _, _) in HOSTS.items()}
        out["hosts"]["arms"]["robot_lan"] = ARMS_ON_ROBOT_LAN
        out["hosts"]["robot"]["cr5"] = dict(CR5_ADDRESSES)
        if not quick:
            bring_up(lab, "lockstep")
            with Console(lab) as con:
                finish_bring_up(lab, con)
                out["lockstep"] = lockstep_run(con, scenario, seed)
        bring_up(lab, "wall")
        with Console(lab) as con:
            finish_bring_up(lab, con)
            for p in lab.procs.values():
                out["hosts"][p.host]["services"].append(p.name)
            spaces = lab.namespaces()
            out["namespaces"] = {k: v for k, v in sorted(spaces.items())}
            out["distinct_namespaces"] = len(set(spaces.values()))
            if not quick:
                out["wall"] = wall_run(con, scenario, seed)
                out["skew"] = {f"{o:+g}": skewed(lab, con, scenario, seed, o) for o in SKEWS_S}
                restart_cam(lab, con)  # cam's clock true again
            out["cut"] = cut_cable(lab, con, scenario, seed, quick)
            if not quick:
                out["disk_full"] = disk_full(lab, con, scenario, seed)
                restart_cam(lab, con)
                r = con.run(scenario, seed)
                out["restart"] = {"next_run_success": r.success, "reason": r.reason}
    out["leftovers"] = leftovers()
    return summarise(out)


def summarise(out: dict[str, Any]) -> dict[str, Any]:
    """The issue's keys at the top, and whether every check passed."""
    cut = out["cut"]
    checks = {
        "namespaces": out.get("distinct_namespaces", 0) >= 3,
        "cut_reason": "arm-driver" in (cut.get("reason") or ""),
        "cut_next": bool(cut.get("next_run_success", cut.get("next_run_servoing"))),
        "clean": not out["leftovers"],
    }
    if not out["quick"]:
        w, ls = out["wall"], out["lockstep"]
        out["bit_for_bit"] = ls["identical"]
        out["realtime_factor"] = w["realtime_factor"]
        out["watchdog_stops"] = w["watchdog_stops"]
        out["acl_object_from"] = ls["object_from"]
        checks.update({
            "bit_for_bit": bool(ls["identical"]),
            "wall": bool(w["success"]) and w["watchdog_stops"] == 0,
            "skew": all(s.get("success") and not s["soi"]["fresh_taken_as_stale"] and not s["soi"]["stale_taken_as_fresh"]
                        for s in out["skew"].values()),
            "arms_stopped": cut.get("arms_stopped_ms") is not None and cut["arms_stopped_ms"] <= WATCHDOG_GOAL_MS,
            "disk_full": bool(out["disk_full"].get("recording_reported")) and not out["disk_full"].get("files_while_full"),
            "restart": bool(out["restart"]["next_run_success"]),
            "marker_through_acl": ls["object_from"] == "marker",
        })
    out["checks"] = checks
    out["success"] = all(checks.values())
    return out


def markdown(r: dict[str, Any]) -> str:
    from bagit.bench.common import metric_table

    rows: list[tuple[str, Any]] = [("success", r["success"]), ("checks", ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in r["checks"].items())),
                                   ("hosts", "; ".join(f"{h} {v['address']}: {', '.join(v['services']) or '(the CR5s)'}" for h, v in r["hosts"].items())),
                                   ("distinct network namespaces of the services", r.get("distinct_namespaces")), ("mutual TLS + ACL", r["tls"])]
    if not r["quick"]:
        ls, w = r["lockstep"], r["wall"]
        rows += [("lockstep vs `bagit run`: bit for bit", f"{ls['identical']} (up {ls['up']}, run {ls['run']}; object from {ls['object_from']})"),
                 ("wall clock: success, real-time factor, watchdog stops", f"{w['success']}, {w['realtime_factor']}, {w['watchdog_stops']}")]
        for k, s in r["skew"].items():
            rows.append((f"cam's clock {k} s: success, SOI ages misjudged", f"{s.get('success')} ({s.get('reason')}), {s.get('soi')}"))
    c = r["cut"]
    rows += [("cable pulled: arms still after the last command, ms on the controllers' clock (goal 250) / wall ms / their real-time factor",
              f"{c.get('arms_stopped_ms')} / {c.get('arms_stopped_wall_ms')} / {c.get('controllers_rtf')}"),
             ("cable pulled: the arms' speed at the last command (mm/s)", c.get("moving_mm_s")),
             ("cable pulled: the run's reason", c.get("reason")),
             ("cable back: next run", c.get("next_run_success", c.get("next_run_servoing")))]
    if not r["quick"]:
        d = r["disk_full"]
        full = (d.get("run_success"), d.get("recording_reported"), d.get("messages_lost"), len(d.get("files_while_full") or []), d.get("resumed"))
        rows += [("disk full: run success, recording reported failed, messages lost, files left, resumed", ", ".join(map(str, full))),
                 ("cam restarted: next run", r["restart"]["next_run_success"])]
    rows.append(("left on the machine afterwards", ", ".join(r["leftovers"]) or "nothing"))
    return metric_table("A rig across machines (`bagit bench multihost`)", r, rows)


def run_from_args(args: Any) -> dict[str, Any]:
    """`bagit bench multihost [--quick] [--only SCENARIO] [--out DIR]`."""
    from bagit.bench.common import write_results

    need_root()
    scenario = (args.only or ["exp02"])[0]
    load_before = [round(v, 2) for v in os.getloadavg()]
    t0 = time.monotonic()
    r = measure(scenario, 0, quick=args.quick)
    r.update(machine=machine(), load_before=load_before, load_after=[round(v, 2) for v in os.getloadavg()], wall_s=round(time.monotonic() - t0, 1),
             params={"scenario": scenario, "seed": 0, "quick": args.quick, "skews_s": list(SKEWS_S), "tmpfs_kb": TMPFS_KB, "rig": RIG})
    if not args.quick or args.out is not None:  # a quick run never overwrites the published records
        jp, mp = write_results(f"multihost-{time.strftime('%Y%m%d-%H%M%S')}", r, markdown(r), args.out or RESULTS_DIR)
        r["files"] = {"json": str(jp), "markdown": str(mp)}
    return r
