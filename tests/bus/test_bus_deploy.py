"""deploy/: `bagit router` as a process, the committed per-host configs carrying traffic through
it, Procfiles and systemd units that name real commands.

zenoh.Config.from_file parses with the same zenoh-config crate as zenohd and rejects unknown
fields and values, so loading the committed files here checks them for a stock zenohd of the
same version too.
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh
from bus_support import wait_until
from suite_support import ROOT

from bagit.common.bus import BusConfig, Keys, Publisher, Subscriber, config_value, open_session
from bagit.common.messages import Command

DEPLOY = ROOT / "deploy"
HOSTS = ["host-camera-perception.json5", "host-planner-controller.json5", "host-arm-driver.json5"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_committed_configs_load_and_stay_safe():
    router = zenoh.Config.from_file(str(DEPLOY / "zenoh-router.json5"))
    assert config_value(router, "mode") == "router"
    assert config_value(router, "listen/endpoints") == ["tcp/127.0.0.1:7447"]  # loopback unless widened
    assert config_value(router, "scouting/multicast/enabled") is False
    assert config_value(router, "transport/link/tx/lease") == 1000
    for name in HOSTS:
        zc = zenoh.Config.from_file(str(DEPLOY / name))
        assert config_value(zc, "mode") == "client", name
        assert config_value(zc, "connect/endpoints") == ["tcp/bagit-router:7447"], name
        assert config_value(zc, "listen/endpoints") == [], name
        assert config_value(zc, "scouting/multicast/enabled") is False, name
        assert config_value(zc, "transport/link/tx/lease") == 1000, name


@pytest.mark.processes
def test_bagit_router_carries_traffic_between_host_configs_and_stops_on_sigterm():
    port = _free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(
        [sys.executable, "-m", "bagit.cli", "router", "--listen", endpoint, "--json"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    sessions: list[zenoh.Session] = []
    try:
        line = proc.stderr.readline()
        assert "listening on" in line and endpoint in line, line
        # one client per host config, each connecting to the router instead of bagit-router
        for name in HOSTS:
            sessions.append(open_session(BusConfig(rig="lab", config_file=DEPLOY / name, connect=[endpoint])))
        perception, planner_controller, arm = sessions
        keys = Keys("lab")
        got: list[Command] = []
        Subscriber(arm, keys.controller_cmd, Command, got.append)
        pub = Publisher(planner_controller, keys.controller_cmd, Command)
        assert wait_until(lambda: pub.matched)
        for i in range(5):
            pub.put(Command(seq=i, u=np.zeros(12)))
        assert wait_until(lambda: len(got) == 5)
        assert [c.seq for c in got] == list(range(5))  # reliable and in order through the router
    finally:
        for s in sessions:
            s.close()
        proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            raise
    assert proc.returncode == 0, err
    result = json.loads(out.strip().splitlines()[-1])
    assert result["success"] and result["listen"] == [endpoint]
    assert result["sessions_seen"] >= 3
    assert "joined" in err


def test_bagit_router_refuses_bad_input():
    from bagit.cli import main

    assert main(["router", "--listen", "localhost:7447"]) == 2
    assert main(["router", "--duration", "0"]) == 2
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen(1)
        assert main(["router", "--listen", f"tcp/127.0.0.1:{s.getsockname()[1]}", "--duration", "0.1"]) == 2


def test_bagit_router_runs_for_a_duration(capsys):
    from bagit.cli import main

    t0 = time.monotonic()
    assert main(["router", "--listen", f"tcp/127.0.0.1:{_free_port()}", "--duration", "0.3", "--json"]) == 0
    assert time.monotonic() - t0 > 0.25  # it ran its duration (and then stopped: main returned)
    assert json.loads(capsys.readouterr().out)["success"]


@pytest.mark.parametrize("procfile", sorted(p.name for p in DEPLOY.glob("Procfile.*")))
def test_procfiles_name_bagit_subcommands_with_their_host_config(procfile):
    lines = [ln for ln in (DEPLOY / procfile).read_text().splitlines() if ln and not ln.startswith("#")]
    assert lines
    for ln in lines:
        name, cmd = ln.split(":", 1)
        assert re.fullmatch(r"[a-z-]+", name)
        assert cmd.strip().startswith(f"bagit {name}"), ln
        cfg = re.search(r"--zenoh-config /etc/bagit/(\S+)", cmd)
        if name != "router":
            assert cfg and (DEPLOY / cfg.group(1)).exists(), ln


def test_systemd_units_are_well_formed():
    units = sorted((DEPLOY / "systemd").glob("*"))
    assert {u.name for u in units} >= {"bagit-router.service", "bagit@.service", "bagit.target"}
    for u in units:
        text = u.read_text()
        sections = re.findall(r"^\[(\w+)\]$", text, flags=re.M)
        assert "Unit" in sections and "Install" in sections, u.name
        if u.suffix == ".service":
            assert re.search(r"^ExecStart=\S*bagit ", text, flags=re.M), u.name
            assert "Restart=" in text and "KillSignal=SIGTERM" in text
