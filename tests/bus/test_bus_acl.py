"""The committed secure deployment (deploy/secure/) enforces who may drive the rig.

A router opened from deploy/secure/zenoh-router-secure.json5 (mutual TLS + access_control) with
throwaway certificates, and clients from deploy/secure/client.json5, all in-process on loopback.
Identities are certificate common names: a client without a CA-signed certificate cannot connect;
a CA-signed identity can only send what the rules give its name. No puts of the wrong identity
ever arrive, while the right identity's do.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import zenoh
from bus_support import wait_until

from bagit.common.bus import (
    BusConfig,
    Keys,
    LivelinessWatcher,
    Publisher,
    Subscriber,
    declare_alive,
    open_session,
    request_run_control,
    serve_run_control,
)
from bagit.common.errors import BusError
from bagit.common.messages import Command, EStop, RunControl, RunControlReply, SoiState
from bagit.common.names import ESTOP_RELEASE_SOURCES
from bagit.harness import SECURE_CLIENT_CFG, SECURE_IDENTITIES, SECURE_ROUTER_CFG, secure_rig

ROUTER_CFG, CLIENT_CFG = SECURE_ROUTER_CFG, SECURE_CLIENT_CFG
RIG = "secure"
IDENTITIES = list(SECURE_IDENTITIES)


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    """The secured router plus a client per identity ("intruder" is CA-signed but not in the rules)."""
    with secure_rig(tmp_path_factory.mktemp("pki"), RIG, tuple(IDENTITIES)) as r:
        yield {"router": r.router, "clients": r.clients, "pki": r.pki, "endpoint": r.endpoint, "port": r.port}


def _cmd(seq: int) -> Command:
    return Command(seq=seq, u=np.full(12, 1e-4))


def test_committed_configs_are_the_ones_under_test():
    zc = zenoh.Config.from_file(str(ROUTER_CFG))
    assert json.loads(zc.get_json("access_control/enabled")) is True
    assert json.loads(zc.get_json("access_control/default_permission")) == "deny"
    assert json.loads(zc.get_json("transport/link/tls/enable_mtls")) is True
    assert all(e.startswith("tls/") for e in json.loads(zc.get_json("listen/endpoints")))
    client = zenoh.Config.from_file(str(CLIENT_CFG))
    assert json.loads(client.get_json("mode")) == "client"
    assert all(e.startswith("tls/") for e in json.loads(client.get_json("connect/endpoints")))


def test_only_the_controller_can_drive_the_arms(rig):
    c = rig["clients"]
    keys = Keys(RIG)
    got: list[Command] = []
    sub = Subscriber(c["arm-driver"], keys.controller_cmd, Command, got.append)
    ctl = Publisher(c["controller"], keys.controller_cmd, Command)
    assert wait_until(lambda: ctl.matched)
    impostors = {name: Publisher(c[name], keys.controller_cmd, Command) for name in ("intruder", "perception", "dashboard", "cli")}
    time.sleep(0.2)  # give every impostor the same chance the controller had
    for i, pub in enumerate(impostors.values()):
        for _ in range(5):
            pub.put(_cmd(100 + i))
    for seq in range(3):
        ctl.put(_cmd(seq))
    assert wait_until(lambda: len(got) >= 3)
    time.sleep(0.3)  # anything else in flight would have landed by now
    assert [m.seq for m in got] == [0, 1, 2]
    assert sub.dropped == 0
    # the controller's identity gives it nothing else: it cannot pose as perception
    soi: list[SoiState] = []
    Subscriber(c["arm-driver"], keys.perception_soi, SoiState, soi.append)
    fake = Publisher(c["controller"], keys.perception_soi, SoiState)
    real = Publisher(c["perception"], keys.perception_soi, SoiState)
    assert wait_until(lambda: real.matched)
    fake.put(SoiState(seq=666, rim=np.zeros((4, 3))))
    real.put(SoiState(seq=1, rim=np.zeros((4, 3))))
    assert wait_until(lambda: len(soi) >= 1)
    time.sleep(0.3)
    assert [m.seq for m in soi] == [1]


def test_estop_only_from_the_dashboard_and_the_cli(rig):
    """Engage or release: only the operator's tools may put on estop (the arm driver also takes a
    release only from those sources, ESTOP_RELEASE_SOURCES, which on loopback is all there is)."""
    c = rig["clients"]
    keys = Keys(RIG)
    got: list[EStop] = []
    Subscriber(c["arm-driver"], keys.estop, EStop, got.append)
    pubs = {n: Publisher(c[n], keys.estop, EStop) for n in ("controller", "intruder", "planner", "dashboard", "cli")}
    assert wait_until(lambda: pubs["dashboard"].matched and pubs["cli"].matched)
    time.sleep(0.2)
    for n, p in pubs.items():
        p.put(EStop(source=n))
        p.put(EStop(engage=False, source="dashboard"))  # whatever name a release claims, the identity decides
    assert wait_until(lambda: len(got) >= 4)
    time.sleep(0.3)
    assert sorted((m.engage, m.source) for m in got) == [(False, "dashboard")] * 2 + [(True, "cli"), (True, "dashboard")]


def test_the_identities_that_may_put_on_estop_are_the_release_sources():
    """The router's rule and the arm driver's rule name the same two: ESTOP_RELEASE_SOURCES."""
    zc = zenoh.Config.from_file(str(ROUTER_CFG))
    acl = json.loads(zc.get_json("access_control"))
    rules = {r["id"]: r for r in acl["rules"]}
    estop_rules = {rid for rid, r in rules.items() if r["permission"] == "allow" and "put" in r["messages"]
                   and any(k.endswith("/estop") for k in r["key_exprs"])}
    assert estop_rules == {"operator-estop"}
    subjects = {s["id"]: set(s["cert_common_names"]) for s in acl["subjects"]}
    names = set().union(*(subjects[sid] for p in acl["policies"] if set(p["rules"]) & estop_rules for sid in p["subjects"]))
    assert names == set(ESTOP_RELEASE_SOURCES)


def test_run_control_only_from_the_dashboard_and_the_cli(rig):
    c = rig["clients"]
    keys = Keys(RIG)
    served: list[RunControl] = []
    serve_run_control(c["planner"], keys, lambda r: served.append(r) or RunControlReply(accepted=True, run_id="r1"))
    assert request_run_control(c["cli"], keys, RunControl(action="start", scenario="exp01"), timeout=5.0).accepted
    assert request_run_control(c["dashboard"], keys, RunControl(action="stop"), timeout=5.0).accepted
    for n in ("controller", "intruder"):
        with pytest.raises(BusError, match="no answer"):
            request_run_control(c[n], keys, RunControl(action="reset"), timeout=0.7)
    assert [r.action for r in served] == ["start", "stop"]


def test_a_service_can_only_announce_itself(rig):
    c = rig["clients"]
    keys = Keys(RIG)
    w = LivelinessWatcher(c["dashboard"], keys)
    own = declare_alive(c["perception"], keys, "perception")  # noqa: F841 - held
    forged = declare_alive(c["intruder"], keys, "controller")  # noqa: F841 - held
    forged2 = declare_alive(c["perception"], keys, "arm-driver")  # noqa: F841 - held
    assert w.wait_for("perception", True, 3.0)
    time.sleep(0.3)
    assert w.alive() == {"perception"}


def test_no_certificate_no_connection(rig):
    pki = rig["pki"]
    # TLS that trusts the CA but shows no client certificate: refused at the handshake
    zc = BusConfig(rig=RIG, config_file=CLIENT_CFG, connect=[rig["endpoint"]], tls_ca=pki["ca"]).to_zenoh()
    zc.insert_json5("connect/timeout_ms", "1500")
    zc.insert_json5("connect/exit_on_failure", "true")
    with pytest.raises(zenoh.ZError):
        zenoh.open(zc).close()
    # plain TCP to the TLS port: no session either
    with pytest.raises(BusError):
        s = open_session(BusConfig(rig=RIG, mode="client", connect=[f"tcp/127.0.0.1:{rig['port']}"]))
        s.close()
