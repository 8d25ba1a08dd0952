"""`bagit up`'s fork server: one interpreter imports what every service imports, once, then forks the services.

Six services started as six `python -m bagit.cli SERVICE` interpreters each import numpy, scipy,
pydantic, Zenoh and `bagit.common` (about a CPU second each on a 2-core EPYC): on one machine most
of a rig's start-up. `bagit up` instead forks this server from itself once its own imports are made
(numpy, scipy, pydantic, Zenoh, `bagit.common`: most of `PRELOAD`) and while it still runs one thread,
no Zenoh session open (`ForkServer(inherit=True)`; otherwise, and for `python -m bagit.forkserver FD`,
a fresh interpreter). The server imports the rest of `PRELOAD` and then, for each request on its
socket, forks a child that runs `bagit.cli.main(argv)` as the
command line `bagit SERVICE ...` would: the same code, arguments, environment and exit status, only
without the shared imports (a service's own heavy imports, MuJoCo, Open3D, viser, happen in its
child, in parallel with the others). Nothing of a run is computed here, so results cannot differ.

A child gets what `bagit up` gives a process it starts itself: its own session and process group
(`setsid`), its niceness, the CPUs it may run on, the parent-death signal (the server's own is `bagit up`'s: a SIGKILLed
`bagit up` takes the server down and the server its children), stdin on /dev/null and stdout and
stderr on the pipe `bagit up` passed with the request. The server reaps its children and reports
each exit status (as `subprocess` gives it: negative for a signal) on the socket; it leaves when
the socket closes and its last child has exited, so every child's CPU time reaches `bagit up`'s.

Protocol (SOCK_SEQPACKET, one JSON object a packet): request {"argv": [...], "niceness": n, "cpus": [...] or null} with the
output pipe's write end as SCM_RIGHTS; replies {"pid": p} (in request order) and {"exit": p, "code": c}.
Only `bagit up` uses it: a deployed rig (Procfiles, systemd units) starts `bagit SERVICE` as before.
"""

from __future__ import annotations

import atexit
import importlib
import json
import os
import select
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Collection, Mapping, Sequence
from typing import IO, Any

# What every service imports before it does anything of its own (seen with `python -X importtime`): the
# CLI (with every subcommand's parser), the bus and its messages, the rig and scenario models (scipy.spatial
# through `bagit.common.geometry`), the service glue, and what two services or more import. Not a library only
# one service uses: each child imports its own (MuJoCo, Open3D, viser), so those imports still run in parallel.
# Not OpenCV either (perception, planner, simulator): it starts a thread pool as it loads, and a fork keeps
# only the forking thread.
PRELOAD: tuple[str, ...] = (
    "numpy",
    "scipy.linalg",
    "scipy.spatial",
    "scipy.sparse",
    "scipy.optimize",  # the planner's and perception's (with scipy.fft)
    "scipy.fft",
    "bagit.cli",
    "bagit.commands._service",
    "bagit.common.bus",
    "bagit.common.rig",
    "bagit.common.scenario",
    "bagit.common.lockstep",
    "bagit.common.dual_arm",
    "bagit.common.cr5",
    "bagit.services.controller",  # the controller's, and the simulator's (its control session)
)
MAX_PACKET = 1 << 16


def child_env() -> dict[str, str]:
    """The services' environment: this one, headless OpenGL, unbuffered output (each line reaches its prefix at once)."""
    from bagit.common.headless import headless_gl

    return dict(headless_gl(dict(os.environ, PYTHONUNBUFFERED="1")))


def child_setup(  # pragma: no cover - runs in a child between fork and exec/run
    niceness: int = 0, death_signal: int = signal.SIGTERM, cpus: Collection[int] | None = None
) -> None:
    """Its own session and process group, its niceness, the CPUs it may run on (None: its parent's), and
    `death_signal` when its parent dies (Linux)."""
    import ctypes

    os.setsid()
    renice(niceness)
    if cpus:
        try:
            os.sched_setaffinity(0, cpus)  # its threads, started later, inherit it
        except OSError:  # a CPU gone offline since it was chosen: the parent's CPUs, as without
            pass
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, death_signal)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def renice(niceness: int) -> None:
    """Add `niceness` to this process's, and give its scheduling autogroup the same. With autogroup on
    (Linux's default on desktops and Debian's kernels) a new session is a group of its own, the scheduler
    shares a core between groups first, and a niceness counts only among a group's own processes: a niced
    service in its own session would take as much CPU as the simulator beside it. A process may raise its
    group's niceness but not lower it: a value under 0 is left to the process's own."""
    if not niceness:
        return
    os.nice(niceness)
    if niceness < 0:
        return
    try:
        with open("/proc/self/autogroup", "w") as f:
            f.write(str(niceness))
    except OSError:  # no autogroup (a kernel without it, or off): the process's own niceness is the one
        pass


def name_process(name: str) -> None:
    """The name `ps -o comm`, `top` and `pgrep` show for this process (Linux keeps 15 bytes): a forked service
    is then told from its siblings, whose command lines are all the server's."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(15, name.encode()[:15])  # PR_SET_NAME
    except OSError:
        pass


def preload(modules: Sequence[str] = PRELOAD) -> None:
    """Import `modules` and build the CLI's parser once (its subcommands import their argument helpers)."""
    for m in modules:
        importlib.import_module(m)
    from bagit.cli import build_parser

    build_parser()


def _cpus(value: Any) -> set[int] | None:
    """A request's CPU set: a list of CPU numbers, else None (the server's CPUs)."""
    if isinstance(value, list) and value and all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in value):
        return set(value)
    return None


def _send(sock: socket.socket, msg: dict[str, Any]) -> None:
    try:
        sock.send(json.dumps(msg).encode())
    except OSError:  # `bagit up` is gone: its children are told by their parent-death signal
        pass


def serve(sock: socket.socket) -> list[str] | None:
    """The server's loop. Returns in a forked child with the argv it is to run; in the server, None once
    the socket has closed and every child has been reaped."""
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    signal.signal(signal.SIGCHLD, lambda *_: None)  # a handler, so the wake-up fd hears of exits
    children: set[int] = set()
    open_ = True
    while open_ or children:
        watch: list[Any] = [sock, wake_r] if open_ else [wake_r]
        ready, _, _ = select.select(watch, [], [])
        if wake_r in ready:
            os.read(wake_r, 512)
        while children:  # reap: whatever woke us, an exit may be pending
            pid, status = os.waitpid(-1, os.WNOHANG)
            if pid == 0:
                break
            children.discard(pid)
            _send(sock, {"exit": pid, "code": os.waitstatus_to_exitcode(status)})
        if open_ and sock in ready:
            data, fds, _, _ = socket.recv_fds(sock, MAX_PACKET, 1)
            if not data:
                open_ = False
                continue
            req = json.loads(data)
            server = os.getpid()
            pid = os.fork()
            if pid == 0:  # the child: the server's descriptors and signal set-up are not its own
                signal.set_wakeup_fd(-1)
                signal.signal(signal.SIGCHLD, signal.SIG_DFL)
                for fd in (wake_r, wake_w):
                    os.close(fd)
                sock.close()
                child_setup(int(req.get("niceness", 0)), cpus=_cpus(req.get("cpus")))
                if os.getppid() != server:  # the server died before the parent-death signal was set
                    os._exit(1)
                out = fds[0]
                os.dup2(out, 1)
                os.dup2(out, 2)
                os.close(out)
                return [str(a) for a in req["argv"]]
            for fd in fds:
                os.close(fd)
            children.add(pid)
            _send(sock, {"pid": pid})
    return None


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m bagit.forkserver FD`: preload, then serve the socket FD; in a child, run its command
    and exit with its status."""
    args = list(sys.argv[1:] if argv is None else argv)
    _serve_and_run(socket.socket(fileno=int(args[0])))
    return 0  # not reached: the server and its children leave by os._exit


def _serve_and_run(sock: socket.socket) -> None:
    """Preload, serve `sock`; in a forked child, run its command. Never returns (os._exit)."""
    preload()
    cmd = serve(sock)
    if cmd is None:  # every child reaped and reported: nothing of the server's is left to close or flush
        os._exit(0)
    from bagit.cli import main as cli_main

    name_process(cmd[0] if cmd else "bagit")
    sys.argv = ["bagit", *cmd]
    code = cli_main(cmd)
    # The command has returned: its sessions, servers and files are closed by its own code. A forked child
    # ends as multiprocessing's do, without the interpreter's finalization (about a second of tearing down
    # every module, for a process that is about to be gone): the exit handlers run, the output is flushed.
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        stream.flush()
    os._exit(code)


class _ForkedServer:
    """The server forked from this process, with the part of `subprocess.Popen` ForkServer uses."""

    def __init__(self, pid: int) -> None:
        self.pid = pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            try:
                pid, status = os.waitpid(self.pid, os.WNOHANG)
            except ChildProcessError:  # reaped elsewhere
                self.returncode = -signal.SIGTERM
                return self.returncode
            if pid:
                self.returncode = os.waitstatus_to_exitcode(status)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if self.poll() is None:
            _await_end(self.pid, timeout)
        code = self.poll()
        if code is None:
            raise subprocess.TimeoutExpired(f"fork server {self.pid}", timeout or 0.0)
        return code

    def kill(self) -> None:
        try:
            os.kill(self.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def _fork_server(theirs: socket.socket, ours: socket.socket, env: Mapping[str, str]) -> _ForkedServer:
    """Fork this process into the server (see ForkServer's `inherit`): the child gets what `python -m
    bagit.forkserver` gets from ForkServer's Popen (the services' environment, its own session and the
    parent-death signal, stdin and stdout on /dev/null) and output that reaches its pipe line by line, as
    PYTHONUNBUFFERED gives a fresh interpreter."""
    for stream in (sys.stdout, sys.stderr):
        stream.flush()  # nothing buffered here is written twice
    pid = os.fork()
    if pid:
        return _ForkedServer(pid)
    try:  # pragma: no cover - the forked server; leaves only by os._exit
        ours.close()
        os.environ.clear()
        os.environ.update(env)
        child_setup()
        null = os.open(os.devnull, os.O_RDWR)
        os.dup2(null, 0)
        os.dup2(null, 1)
        os.close(null)
        for stream in (sys.stdout, sys.stderr):
            stream.reconfigure(line_buffering=True, write_through=True)  # type: ignore[union-attr]
        _serve_and_run(theirs)
    finally:
        os._exit(1)


class ForkedProcess:
    """A service forked by the server, with the part of `subprocess.Popen` that `bagit up` uses."""

    def __init__(self, server: ForkServer, pid: int, stdout: IO[str]) -> None:
        self._server = server
        self.pid = pid
        self.stdout = stdout
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None:
            self.returncode = self._server.exit_code(self.pid)
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        if not self._server.wait_exit(self.pid, timeout):
            raise subprocess.TimeoutExpired(f"pid {self.pid}", timeout or 0.0)
        code = self.poll()
        assert code is not None
        return code


class ForkServer:
    """`bagit up`'s end: starts the server process, asks it for children, follows their exits."""

    def __init__(self, env: Mapping[str, str], on_exit: Callable[[int, int], None] | None = None, inherit: bool = False) -> None:
        """`inherit`: the server is a fork of this process, sharing the imports it has made (`bagit up`'s,
        most of the services'), not a fresh interpreter importing them again; only while this process runs
        one thread (else a fresh interpreter all the same)."""
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_SEQPACKET)
        self._sock = ours
        self.proc: subprocess.Popen[bytes] | _ForkedServer
        if inherit and threading.active_count() == 1:
            self.proc = _fork_server(theirs, ours, env)
        else:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "bagit.forkserver", str(theirs.fileno())], stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL, env=env, pass_fds=(theirs.fileno(),), preexec_fn=child_setup,
            )
        theirs.close()
        self.on_exit = on_exit  # called on the reader thread with (pid, exit status)
        self._cond = threading.Condition()
        self._pids: list[int] = []  # spawn replies not yet taken, in request order
        self._exits: dict[int, int] = {}
        self._closed = False  # the server's end is gone
        self._spawn_lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, name="fork-server", daemon=True)
        self._reader.start()

    @property
    def alive(self) -> bool:
        return not self._closed and self.proc.poll() is None

    def _read(self) -> None:
        while True:
            try:
                data = self._sock.recv(MAX_PACKET)
            except OSError:
                data = b""
            if not data:
                with self._cond:
                    self._closed = True
                    self._cond.notify_all()
                return
            msg = json.loads(data)
            with self._cond:
                if "exit" in msg:
                    self._exits[int(msg["exit"])] = int(msg["code"])
                else:
                    self._pids.append(int(msg["pid"]))
                self._cond.notify_all()
            if "exit" in msg and self.on_exit is not None:
                self.on_exit(int(msg["exit"]), int(msg["code"]))

    def spawn(self, argv: Sequence[str], niceness: int = 0, cpus: Collection[int] | None = None) -> ForkedProcess:
        """Fork `bagit ARGV...` on `cpus` (None: the server's), its output on a new pipe (read from the returned
        process's stdout). Waits for the server to answer however long its imports take (a request given up on
        would still be forked: a service twice); OSError if the server is gone."""
        r, w = os.pipe()
        try:
            with self._spawn_lock:
                socket.send_fds(self._sock, [json.dumps({"argv": list(argv), "niceness": niceness, "cpus": sorted(cpus) if cpus else None}).encode()], [w])
                with self._cond:
                    self._cond.wait_for(lambda: self._pids or self._closed)
                    if not self._pids:
                        raise OSError("the fork server is gone")
                    pid = self._pids.pop(0)
        except BaseException:
            os.close(r)
            raise
        finally:
            os.close(w)
        return ForkedProcess(self, pid, os.fdopen(r, "r", encoding="utf-8", errors="replace"))

    def exit_code(self, pid: int) -> int | None:
        """The child's exit status once reaped; if the server died first, -SIGTERM once the child is gone
        (its parent-death signal), since nobody is left to report it."""
        with self._cond:
            if pid in self._exits:
                return self._exits[pid]
            closed = self._closed
        if closed and not _pid_alive(pid):
            return -signal.SIGTERM
        return None

    def wait_exit(self, pid: int, timeout: float | None) -> bool:
        """Wait for the child's exit report; if the server is gone, for the child itself to be gone."""
        deadline = None if timeout is None else time.monotonic() + timeout
        with self._cond:
            self._cond.wait_for(lambda: pid in self._exits or self._closed, timeout)
            if pid in self._exits:
                return True
            if not self._closed:
                return False
        # an orphan now (its parent-death signal is on its way): woken by its end, not by polling
        _await_end(pid, None if deadline is None else max(0.0, deadline - time.monotonic()))
        return self.exit_code(pid) is not None

    def cpu_s(self) -> float:
        """The server's own CPU seconds so far (its imports; its children's count as theirs)."""
        try:
            fields = open(f"/proc/{self.proc.pid}/stat").read().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            return 0.0
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self, timeout_s: float = 10.0) -> int | None:
        """Close the socket (the server leaves once its children have exited) and reap the server."""
        try:
            self._sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._sock.close()
        try:
            return self.proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(timeout=5)


def _await_end(pid: int, timeout: float | None) -> None:
    """Until process `pid` has ended (or `timeout` s): woken by its end through a pidfd, not by polling."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return
    try:
        select.select([fd], [], [], timeout)
    finally:
        os.close(fd)


def _pid_alive(pid: int) -> bool:
    """Whether `pid` is a live (not zombie) process."""
    try:
        state = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


if __name__ == "__main__":  # pragma: no cover - started by ForkServer
    raise SystemExit(main())
