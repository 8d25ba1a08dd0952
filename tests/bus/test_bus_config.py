"""Bus configuration: loopback by default, json5 files as the base with explicit overrides, the
key space and its QoS table, and clear errors for bad input."""

from __future__ import annotations

import argparse
import json
import socket

import pytest
import zenoh
from pydantic import ValidationError
from suite_support import ROOT

from bagit.common.bus import (
    KEY_TABLE,
    BusConfig,
    Keys,
    add_bus_arguments,
    bus_config_from_args,
    key_table_markdown,
    open_session,
)
from bagit.common.errors import BusError
from bagit.common.messages import ArmState, Command, EStop, RunControl, SoiState, StepAck
from bagit.common.names import LOCKSTEP_SERVICES


def _get(zc: zenoh.Config, key: str):
    return json.loads(zc.get_json(key))


def test_defaults_stay_on_loopback_without_multicast():
    zc = BusConfig().to_zenoh()
    assert _get(zc, "mode") == "peer"
    assert _get(zc, "listen/endpoints") == ["tcp/127.0.0.1:0"]
    assert _get(zc, "connect/endpoints") == []
    assert _get(zc, "scouting/multicast/enabled") is False
    assert _get(zc, "transport/link/tx/lease") == 1000
    assert _get(zc, "scouting/delay") == 0
    assert _get(BusConfig(mode="router").to_zenoh(), "listen/endpoints") == ["tcp/127.0.0.1:7447"]
    assert _get(BusConfig(mode="client", connect=["tcp/127.0.0.1:7447"]).to_zenoh(), "listen/endpoints") == []
    assert _get(BusConfig(multicast_scouting=True).to_zenoh(), "scouting/delay") == 500


def test_config_file_is_the_base_and_explicit_fields_override(tmp_path):
    f = tmp_path / "z.json5"
    f.write_text(
        """{
          // a client of the lab router
          mode: "client",
          connect: { endpoints: ["tcp/10.0.0.1:7447"] },
          transport: { link: { tx: { lease: 3000 } } },
        }"""
    )
    zc = BusConfig(config_file=f).to_zenoh()
    assert _get(zc, "mode") == "client"
    assert _get(zc, "connect/endpoints") == ["tcp/10.0.0.1:7447"]
    assert _get(zc, "transport/link/tx/lease") == 3000
    assert _get(zc, "listen/endpoints") == []  # a client that the file did not give listeners: none
    zc2 = BusConfig(config_file=f, connect=["tcp/127.0.0.1:9999"], lease_ms=500).to_zenoh()
    assert _get(zc2, "connect/endpoints") == ["tcp/127.0.0.1:9999"]
    assert _get(zc2, "transport/link/tx/lease") == 500
    assert _get(zc2, "mode") == "client"

    g = tmp_path / "peer.json5"
    g.write_text('{ mode: "peer" }')
    assert _get(BusConfig(config_file=g).to_zenoh(), "listen/endpoints") == ["tcp/127.0.0.1:0"]  # not [::]
    h = tmp_path / "wide.json5"
    h.write_text('{ mode: "router", listen: { endpoints: ["tcp/0.0.0.0:7447"] } }')
    assert _get(BusConfig(config_file=h).to_zenoh(), "listen/endpoints") == ["tcp/0.0.0.0:7447"]  # explicit: kept


def test_bad_config_input_gives_clear_errors(tmp_path):
    with pytest.raises(BusError, match="zenoh config"):
        BusConfig(config_file=tmp_path / "missing.json5").to_zenoh()
    bad = tmp_path / "bad.json5"
    bad.write_text("{ mode: ")
    with pytest.raises(BusError, match="zenoh config"):
        BusConfig(config_file=bad).to_zenoh()
    with pytest.raises(ValidationError, match="endpoint"):
        BusConfig(connect=["localhost:7447"])
    with pytest.raises(ValidationError, match="rig name"):
        BusConfig(rig="lab/1")
    with pytest.raises(ValidationError):
        BusConfig(mode="server")
    with pytest.raises(BusError, match="rig name"):
        Keys("a*b")
    with pytest.raises(BusError, match="service name"):
        Keys("lab").alive("")
    with pytest.raises(BusError, match="left"):
        Keys("lab").arm_state("middle")  # type: ignore[arg-type]


def test_open_session_on_a_taken_port_is_a_bus_error():
    s = socket.socket()
    s.bind(("127.0.0.1", 0))
    s.listen(1)
    port = s.getsockname()[1]
    try:
        with pytest.raises(BusError, match="cannot open"):
            open_session(BusConfig(listen=[f"tcp/127.0.0.1:{port}"]))
    finally:
        s.close()


def test_flags_overlay_the_service_config():
    p = argparse.ArgumentParser()
    add_bus_arguments(p)
    base = BusConfig(rig="lab", connect=["tcp/10.0.0.1:7447"])
    cfg = bus_config_from_args(p.parse_args(["-m", "client", "-e", "tcp/127.0.0.1:7447", "-e", "tcp/127.0.0.1:7448"]), base)
    assert cfg.rig == "lab" and cfg.mode == "client"
    assert cfg.connect == ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7448"]
    assert "listen" not in cfg.model_fields_set
    cfg2 = bus_config_from_args(p.parse_args(["--rig", "r2", "-l", "tcp/127.0.0.1:0", "--multicast-scouting"]))
    assert cfg2.rig == "r2" and cfg2.listen == ["tcp/127.0.0.1:0"] and cfg2.multicast_scouting
    assert bus_config_from_args(p.parse_args([])) == BusConfig()
    with pytest.raises(BusError, match="bus config"):
        bus_config_from_args(p.parse_args(["-e", "nonsense"]))


def test_key_space():
    k = Keys("lab2")
    assert k.camera_rgbd == "bagit/lab2/camera/rgbd"
    assert k.perception_cloud == "bagit/lab2/perception/cloud"
    assert k.perception_soi == "bagit/lab2/perception/soi"
    assert k.planner_goal == "bagit/lab2/planner/goal"
    assert k.planner_path == "bagit/lab2/planner/path"
    assert k.controller_cmd == "bagit/lab2/controller/cmd"
    assert k.controller_status == "bagit/lab2/controller/status"
    assert k.arm_state("left") == "bagit/lab2/arm/left/state"
    assert k.run_state == "bagit/lab2/run/state"
    assert k.run_control == "bagit/lab2/run/control"
    assert k.estop == "bagit/lab2/estop"
    assert k.alive("perception") == "bagit/lab2/alive/perception"
    assert k.spec(k.arm_state("right")).message is ArmState
    assert k.spec(k.controller_cmd).message is Command
    assert k.spec(k.run_control).message is RunControl and k.spec(k.run_control).kind == "query"
    assert k.spec(k.alive("x")).kind == "liveliness"
    assert k.spec("bagit/other/perception/soi") is None  # another rig
    assert k.spec("bagit/lab2/nothing") is None
    assert k.spec(k.perception_soi).message is SoiState


def test_each_service_answers_lockstep_on_its_own_key():
    """A service subscribes only to the answers it waits for; the wildcard (tools') hears them all."""
    k = Keys("lab2")
    assert k.step_ack("planner") == "bagit/lab2/sim/ack/planner"
    everyone = zenoh.KeyExpr(k.sim_ack)
    for s in LOCKSTEP_SERVICES:
        for key in (k.step_ack(s), k.status_ack(s)):
            assert everyone.includes(zenoh.KeyExpr(key))
            assert k.spec(key).message is StepAck
    assert not zenoh.KeyExpr(k.step_ack("planner")).includes(zenoh.KeyExpr(k.step_ack("controller")))
    # the coordinator's answers to statuses are not its answers to frames, which the controller follows
    assert not zenoh.KeyExpr(k.step_ack("planner")).includes(zenoh.KeyExpr(k.status_ack("planner")))
    with pytest.raises(BusError, match="service name"):
        k.step_ack("planner/*")


def test_qos_table_follows_the_policy():
    rows = {r.key: r for r in KEY_TABLE}
    for key in ("camera/rgbd", "perception/cloud", "perception/soi", "perception/object", "arm/*/state", "run/state", "controller/status"):
        q = rows[key].qos
        assert q.reliability == "best_effort" and q.congestion == "drop", key
    for key in ("controller/cmd", "run/control", "planner/goal", "planner/path"):
        q = rows[key].qos
        assert q.reliability == "reliable" and q.congestion == "block", key
    es = rows["estop"].qos
    assert rows["estop"].message is EStop
    assert (es.reliability, es.congestion, es.priority, es.express) == ("reliable", "block", "real_time", True)
    # nothing else shares the e-stop's priority
    assert [r.key for r in KEY_TABLE if r.qos and r.qos.priority == "real_time"] == ["estop"]
    kw = es.publisher_kwargs()
    assert kw["priority"] == zenoh.Priority.REAL_TIME and kw["express"] is True
    assert kw["reliability"] == zenoh.Reliability.RELIABLE and kw["congestion_control"] == zenoh.CongestionControl.BLOCK


def test_markdown_table_lists_every_key():
    md = key_table_markdown()
    lines = md.splitlines()
    assert len(lines) == 2 + len(KEY_TABLE)
    for r in KEY_TABLE:
        assert f"`{r.key}`" in md
    assert all(line.count("|") == lines[0].count("|") for line in lines)  # no stray pipes break the table


def test_the_architecture_doc_shows_the_table_in_code():

    doc = (ROOT / "docs" / "architecture.md").read_text()
    assert "## Zenoh key space and QoS" in doc
    assert key_table_markdown() in doc, "docs/architecture.md's key table is out of date: paste key_table_markdown()"
