"""Protocol conformance of the simulated CR5 controllers over TCP (ephemeral loopback ports).

Every command the arm driver uses, its reply format and error ids; state rules (disabled, error,
emergency stop); malformed input; several clients; the feedback packet and its 8 ms period.
"""

import socket
import threading
import time

import numpy as np
import pytest
from suite_support import HANG_S

from bagit.common import cr5, dobot
from bagit.services.sim.cr5_sim import SimulatedCR5
from bagit.services.sim.dobot_server import DobotControllerServer
from bagit.services.sim.harness import DashboardText as Client

READY = [0.0, 0.0, -90.0, 0.0, 90.0, 0.0]


@pytest.fixture
def server():
    srv = DobotControllerServer(SimulatedCR5(q0=np.radians(READY)), dashboard_port=0, feedback_port=0, step_in_background=True)
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture
def client(server):
    c = Client(server.dashboard_port)
    yield c
    c.close()


def wait_mode(c: Client, mode: int, timeout: float = HANG_S) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if c.ask("RobotMode()").values == [mode]:
            return
        time.sleep(0.02)
    raise AssertionError(f"robot mode never became {mode}")


def same_pose(a: list[float], b: list[float], atol: float) -> bool:
    """Dobot poses (x, y, z mm, rx, ry, rz deg): angles compared modulo 360 (roll -180 == 180)."""
    d = np.asarray(a, float) - np.asarray(b, float)
    d[3:] = (d[3:] + 180.0) % 360.0 - 180.0
    return bool(np.all(np.abs(d) <= atol))


def test_reply_format_echoes_the_command(client):
    assert client.raw("RobotMode()") == "0,{4},RobotMode();"
    assert client.raw("EnableRobot()") == "0,{},EnableRobot();"
    assert client.raw("robotmode()") == "0,{5},robotmode();"  # names are case-insensitive
    r = client.raw("GetPose()")
    assert r.startswith("0,{") and r.endswith("},GetPose();")
    p = dobot.parse_reply(r)
    assert same_pose(p.values, [473, -141, 469, -180, 0, -90], atol=1e-3)
    a = client.ask("GetAngle()")
    assert a.ok and np.allclose(a.values, READY, atol=1e-6)
    assert client.ask("GetPose(user=0,tool=0)").ok


def test_enable_disable_and_payload_arguments(client):
    assert client.ask("EnableRobot(0.3)").ok
    assert client.ask("EnableRobot(0.3,0,0,60)").ok
    assert client.ask("EnableRobot(0.3,0,0,60,1)").ok
    assert client.ask("EnableRobot(0.3,0)").error_id == -20000
    assert client.ask("EnableRobot(9)").error_id == -60001  # CR5 payload is 0..5 kg
    assert client.ask("EnableRobot(0.3,0,0,2000)").error_id == -60004
    assert client.ask("EnableRobot(abc)").error_id == -50001
    assert client.ask("RobotMode()").values == [5]
    assert client.ask("DisableRobot()").ok
    assert client.ask("RobotMode()").values == [4]
    assert client.ask("DisableRobot(1)").error_id == -20000


@pytest.mark.slow
def test_unknown_and_malformed_commands_get_minus_10000_and_the_link_survives(client):
    assert client.raw("Mov(-500,100,200,150,0,90)") == "-10000,{},Mov(-500,100,200,150,0,90);"
    for bad in ["garbage", "EnableRobot(", "MovJ(joint={1,2,3)", "Foo(__import__('os'))", "\x00\xff\xfe"]:
        assert client.ask(bad).error_id == -10000, bad
    assert client.ask("RobotMode()").ok  # still talking


def test_parameter_errors(client):
    client.ask("EnableRobot()")
    assert client.ask("SpeedFactor()").error_id == -20000
    assert client.ask("SpeedFactor(0)").error_id == -40001
    assert client.ask("SpeedFactor(101)").error_id == -40001
    assert client.ask("SpeedFactor(50.5)").error_id == -30001
    assert client.ask("SpeedFactor(60)").ok
    assert client.ask("GetPose(user=1)").error_id == -20000
    assert client.ask("GetPose(user=1,tool=99)").error_id == -60001  # named: -60001 wherever it stands
    assert client.ask("GetPose(usr=1,tool=0)").error_id == -50001
    assert client.ask("EmergencyStop(2)").error_id == -40001
    assert client.ask("EmergencyStop()").error_id == -20000
    assert client.ask("MovJ(0,0,-90,0,90,0)").error_id == -30001  # V4 wants joint={..} or pose={..}
    assert client.ask("MovJ(joint={0,0,-90,0,90})").error_id == -30001
    assert client.ask("MovJ(joint={0,0,-90,0,90,0},v=0)").error_id == -60001
    assert client.ask("MovJ(joint={0,0,-90,0,90,0},a=20,vel=5)").error_id == -50001
    assert client.ask("ServoP(473,-141,469,-180,0)").error_id == -20000
    assert client.ask("ServoP(473,-141,x,-180,0,-90)").error_id == -30003
    assert client.ask("ServoP(473,-141,469,-180,0,-90,t=0.001)").error_id == -60001
    assert client.ask("ServoP(473,-141,469,-180,0,-90,t=0.1,aheadtime=10)").error_id == -60001
    assert client.ask("ServoP(473,-141,469,-180,0,-90,t=0.1,aheadtime=50,gain=5000)").error_id == -60001
    assert client.ask("ServoJ(0,0,-90,0,90,0,t=0.1,aheadtime=50,gain=500)").ok


def test_motion_commands_while_disabled_are_not_executed(client):
    for cmd in ["MovJ(joint={0,0,-90,0,90,0})", "MovL(pose={473,-141,469,-180,0,-90})",
                "ServoJ(0,0,-90,0,90,0)", "ServoP(473,-141,469,-180,0,-90)"]:  # fmt: skip
        assert client.ask(cmd).error_id == -1, cmd
    assert client.ask("GetAngle()").values == pytest.approx(READY)


def test_movj_movl_queue_ids_and_completion(client):
    client.ask("EnableRobot()")
    client.ask("SpeedFactor(100)")
    r1 = client.ask("MovJ(joint={10,0,-90,0,90,0},v=100)")
    r2 = client.ask("MovL(pose={450,-100,450,-180,0,-90},v=100)")
    assert r1.ok and r2.ok and r2.values[0] == r1.values[0] + 1
    assert client.ask("RobotMode()").values == [7]
    wait_mode(client, 5)
    assert same_pose(client.ask("GetPose()").values, [450, -100, 450, -180, 0, -90], atol=0.5)
    assert client.ask("GetCurrentCommandID()").values == [r2.values[0]]
    j = client.ask("MovJ(pose={400,-141,500,-180,0,-90})")
    assert j.ok
    wait_mode(client, 5)
    assert np.allclose(client.ask("GetPose()").values[:3], [400, -141, 500], atol=0.5)


def test_servo_commands_track_with_a_lag(client):
    client.ask("EnableRobot()")
    pose = np.array([473.0, -141.0, 469.0, -180.0, 0.0, -90.0])
    z0, lags = client.ask("GetPose()").values[2], []
    for _ in range(15):
        pose[2] += 2.0  # 2 mm every 30 ms: ~67 mm/s
        assert client.ask(dobot.format_command("ServoP", *pose, t=0.03, aheadtime=50, gain=500)).ok
        time.sleep(0.03)
        lags.append(pose[2] - client.ask("GetPose()").values[2])
    # following the target, never ahead of it (how far behind depends on how late this loop runs)
    assert min(lags) > -0.1 and client.ask("GetPose()").values[2] > z0 + 2.0, lags
    wait_mode(client, 5)
    assert client.ask("GetPose()").values[2] == pytest.approx(pose[2], abs=0.05)
    q = np.array(client.ask("GetAngle()").values)
    q[0] += 3.0
    assert client.ask(dobot.format_command("ServoJ", *q, t=0.1)).ok
    wait_mode(client, 5)
    assert client.ask("GetAngle()").values[0] == pytest.approx(q[0], abs=0.01)


def test_out_of_reach_target_puts_the_arm_in_error(client):
    client.ask("EnableRobot()")
    assert client.ask("ServoP(2500,-141,469,-180,0,-90)").error_id == -1
    assert client.ask("RobotMode()").values == [9]
    ids = dobot.parse_error_ids(client.ask("GetErrorID()").raw_values)
    assert ids[0] == [int(dobot.Alarm.IK_NO_SOLUTION)]
    # in error only ClearError / GetErrorID / EmergencyStop / RobotMode run
    assert client.ask("GetPose()").error_id == -2
    assert client.ask("ServoP(473,-141,469,-180,0,-90)").error_id == -2
    assert client.ask("SpeedFactor(50)").error_id == -2
    assert client.ask("ClearError()").ok
    assert client.ask("RobotMode()").values == [5]
    # a joint target beyond J3's limit: alarm 68 (J3 positive limit)
    assert client.ask("MovJ(joint={0,0,170,0,90,0})").error_id == -1
    assert dobot.parse_error_ids(client.ask("GetErrorID()").raw_values)[0] == [68]
    client.ask("ClearError()")
    # the flange folded onto the arm's own body: alarm 77
    folded = np.degrees(np.radians([0, 35, 157, 32, -146, -127]))
    assert client.ask(dobot.format_command("MovJ", joint=folded)).error_id == -1
    assert dobot.parse_error_ids(client.ask("GetErrorID()").raw_values)[0] == [77]
    client.ask("ClearError()")
    # a servo step no joint can make in t: overspeed alarm
    q = np.array(client.ask("GetAngle()").values)
    q[0] += 60.0
    assert client.ask(dobot.format_command("ServoJ", *q, t=0.05)).error_id == -1
    assert dobot.parse_error_ids(client.ask("GetErrorID()").raw_values)[0] == [48]


def test_emergency_stop_latch(client):
    client.ask("EnableRobot()")
    assert client.ask("EmergencyStop(1)").ok
    assert client.ask("RobotMode()").values == [9]
    assert client.ask("EnableRobot()").error_id == -3
    assert client.ask("GetAngle()").error_id == -3
    assert client.ask("ClearError()").ok
    assert client.ask("RobotMode()").values == [9]  # cannot clear while pressed
    assert client.ask("EmergencyStop(0)").ok
    assert client.ask("ClearError()").ok
    assert client.ask("RobotMode()").values == [4]  # released and cleared: disabled
    assert client.ask("EnableRobot()").ok


def test_kinematics_commands(client):
    p = client.ask("PositiveKin(0,0,-90,0,90,0,user=0,tool=0)")
    assert same_pose(p.values, [473, -141, 469, -180, 0, -90], atol=1e-3)
    q = client.ask("InverseKin(473,-141,469,-180,0,-90,useJointNear=1,jointNear={0,0,-90,0,90,0})")
    assert np.allclose(q.values, READY, atol=1e-3)
    assert client.ask("InverseKin(2500,0,0,0,0,0)").error_id == -1


def test_several_clients_at_once(server):
    clients = [Client(server.dashboard_port) for _ in range(4)]
    errors = []

    def hammer(c: Client) -> None:
        try:
            for _ in range(30):
                r = c.ask("GetAngle()")
                assert r.ok and len(r.values) == 6
        except Exception as e:  # noqa: BLE001 - collected and reported below
            errors.append(e)

    threads = [threading.Thread(target=hammer, args=(c,)) for c in clients]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=20)
    for c in clients:
        c.close()
    assert not errors


def _read_packets(port: int, seconds: float) -> tuple[list[np.ndarray], list[float]]:
    s = socket.create_connection(("127.0.0.1", port), timeout=2.0)
    asm = dobot.FeedbackAssembler()
    packets, stamps = [], []
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        for p in asm.feed(s.recv(65536)):
            packets.append(p)
            stamps.append(time.monotonic())
    s.close()
    return packets, stamps


def test_feedback_packets_layout_and_period(server, client):
    client.ask("EnableRobot()")
    packets, stamps = _read_packets(server.feedback_port, 0.6)
    assert len(packets) > 30
    # the push period is 8 ms of wall clock; a loaded CI machine may stretch it a little
    period = (stamps[-1] - stamps[0]) / (len(stamps) - 1)
    assert 0.006 < period < 0.02
    p = packets[-1]
    assert int(p["MessageSize"]) == 1440 and int(p["TestValue"]) == 0x0123456789ABCDEF
    assert int(p["RobotMode"]) == 5 and int(p["EnableStatus"]) == 1 and int(p["ErrorStatus"]) == 0
    assert int(p["RobotType"]) == 5
    assert np.allclose(p["QActual"], READY, atol=1e-6)
    assert same_pose(p["ToolVectorActual"], [473, -141, 469, -180, 0, -90], atol=1e-3)
    T = cr5.pose6_to_matrix(p["ToolVectorActual"])
    w, x, y, z = p["ActualQuaternion"]
    from scipy.spatial.transform import Rotation

    assert np.allclose(Rotation.from_quat([x, y, z, w]).as_matrix(), T[:3, :3], atol=1e-9)


def test_feedback_follows_the_state(server, client):
    client.ask("EnableRobot()")
    r = client.ask("MovJ(joint={20,0,-90,0,90,0})")
    time.sleep(0.05)
    packets, _ = _read_packets(server.feedback_port, 0.1)
    assert int(packets[-1]["RobotMode"]) == 7 and int(packets[-1]["RunningStatus"]) == 1
    assert int(packets[-1]["CurrentCommandId"]) == r.values[0]
    wait_mode(client, 5)
    client.ask("MovJ(joint={0,0,170,0,90,0})")
    packets, _ = _read_packets(server.feedback_port, 0.05)
    assert int(packets[-1]["RobotMode"]) == 9 and int(packets[-1]["ErrorStatus"]) == 1
    assert packets[-1]["QActual"][0] == pytest.approx(20.0, abs=0.01)


def test_several_feedback_clients_and_clean_stop():
    srv = DobotControllerServer(SimulatedCR5(), dashboard_port=0, feedback_port=0).start()
    socks = [socket.create_connection(("127.0.0.1", srv.feedback_port), timeout=2.0) for _ in range(3)]
    time.sleep(0.1)
    for s in socks:
        data = b""
        while len(data) < 1440:
            data += s.recv(1440 - len(data))
        assert dobot.parse_feedback(data[:1440])["TestValue"] == dobot.TEST_VALUE
    srv.stop()
    for s in socks:
        s.settimeout(1.0)
        with pytest.raises((ConnectionError, OSError, AssertionError)):
            while True:
                assert s.recv(65536)
        s.close()
    assert not any(t.is_alive() for t in threading.enumerate() if t.name.startswith("cr5-"))


def test_two_controllers_on_distinct_ports():
    a = DobotControllerServer(SimulatedCR5(name="left"), dashboard_port=0, feedback_port=0).start()
    b = DobotControllerServer(SimulatedCR5(name="right"), dashboard_port=0, feedback_port=0).start()
    try:
        assert len({a.dashboard_port, a.feedback_port, b.dashboard_port, b.feedback_port}) == 4
        ca, cb = Client(a.dashboard_port), Client(b.dashboard_port)
        assert ca.ask("EnableRobot()").ok
        assert ca.ask("RobotMode()").values == [5] and cb.ask("RobotMode()").values == [4]
        ca.close()
        cb.close()
        with pytest.raises(OSError):
            DobotControllerServer(SimulatedCR5(), dashboard_port=a.dashboard_port, feedback_port=0).start()
    finally:
        a.stop()
        b.stop()


# -- the V4 manual's rules that a vendor client exercised (docs/architecture.md, "Dobot V4 conformance") --------


def test_named_optional_parameter_errors_are_numbered_1_whatever_their_position(client):
    """Manual, chapter 5: an error in a named (`key=value`) optional parameter is -50001 (type) or
    -60001 (range) wherever it stands; -5000k / -6000k count positional optional parameters."""
    assert client.ask("MovJ(joint={0,0,-90,0,90,0},a=50,v=500)").error_id == -60001
    assert client.ask("MovL(pose={473,-141,469,-180,0,-90},user=0,tool=0,a=20,v=50,cp=101)").error_id == -60001
    assert client.ask("GetPose(user=0,tool=51)").error_id == -60001
    assert client.ask('MovJ(pose={473,-141,469,-180,0,-90},user=0,tool="ss",a=20)').error_id == -50001
    assert client.ask("ServoJ(0,0,-90,0,90,0,t=0.1,aheadtime=50,gain=5000)").error_id == -60001
    # positional optional parameters keep their position
    assert client.ask("EnableRobot(0.3,0,0,2000)").error_id == -60004
    assert client.ask("ServoJ(0,0,-90,0,90,0,0.1,50,5000)").error_id == -60003
    assert client.ask("ServoJ(0,0,-90,0,90,0,0.1,x)").error_id == -50002


def test_type_error_in_a_named_required_parameter_is_30001(client):
    """Manual, chapter 5: a wrong type in a named required parameter (MovJ/MovL's joint= or pose=) is
    -30001, as a well-formed command (not -10000); positional required parameters count by position."""
    assert client.ask("MovJ(pose={nan,-141,469,-180,0,-90})").error_id == -30001
    assert client.ask("MovL(joint={0,0,-90,inf,90,0},v=50)").error_id == -30001
    assert client.ask("MovJ(pose={473,-141,1e999,-180,0,-90})").error_id == -30001
    assert client.ask('MovJ(joint="a",user=1,tool=0,a=20,v=50,cp=100)').error_id == -30001  # the manual's example 1
    assert client.ask("ServoP(473,-141,nan,-180,0,-90)").error_id == -30003
    assert client.ask("MovJ(pose={1,,2})").error_id == -10000  # an empty item cannot be parsed at all


def test_servo_commands_reply_their_command_id(client):
    """Manual: ServoJ/ServoP answer `ErrorID,{ResultID},ServoP(..)`, ResultID the algorithm queue id
    that MovJ/MovL also take, and the accepted target is the current command."""
    client.ask("EnableRobot()")
    m = client.ask("MovJ(joint={0,0,-90,0,90,0})")
    wait_mode(client, 5)
    n = int(m.values[0])
    assert client.raw("ServoP(473,-141,470,-180,0,-90,t=0.1)") == f"0,{{{n + 1}}},ServoP(473,-141,470,-180,0,-90,t=0.1);"
    assert client.ask("ServoJ(0,0,-90,0,90,1,t=0.1)").values == [n + 2]
    assert client.ask("GetCurrentCommandID()").values == [n + 2]
    wait_mode(client, 5)
    assert client.ask("MovJ(joint={30,0,-90,0,90,0})").values == [n + 3]  # ~0.7 s
    assert client.ask("ServoJ(30,0,-90,0,90,0)").error_id == -1  # refused while MovJ runs: no id taken
    wait_mode(client, 5)
    assert client.ask("ServoJ(30,0,-90,0,90,2)").values == [n + 4]


def test_servo_t_ranges_from_4_ms_to_an_hour(client):
    """Firmware V4.6: ServoJ/ServoP's t ranges over [0.004, 3600] s (V4.5 manual: [0.02, 3600])."""
    client.ask("EnableRobot()")
    assert client.ask("ServoP(473.000000,-141.000000,469.000000,-180.000000,0.000000,-90.000000,t=0.010000)").ok
    assert client.ask("ServoJ(0,0,-90,0,90,0,t=0.004)").ok
    assert client.ask("ServoJ(0,0,-90,0,90,0,t=3600)").ok
    for t in ["0.0039", "3600.5", "0", "-0.01"]:
        assert client.ask(f"ServoJ(0,0,-90,0,90,0,t={t})").error_id == -60001, t
        assert client.ask(f"ServoP(473,-141,469,-180,0,-90,t={t})").error_id == -60001, t


def test_movl_blend_radius_ranges_over_0_to_100_mm(client):
    """Manual: MovL's r (the blend radius, mm; accepted and ignored here) ranges over [0, 100]."""
    client.ask("EnableRobot()")
    for r in (0, 100):
        assert client.ask(f"MovL(pose={{473,-141,469,-180,0,-90}},a=50,r={r})").ok, r
    for r in (-1, 101, 500):
        assert client.ask(f"MovL(pose={{473,-141,469,-180,0,-90}},a=50,r={r})").error_id == -60001, r
    assert client.ask("MovL(pose={473,-141,469,-180,0,-90},r=2.5)").error_id == -50001  # an int
    wait_mode(client, 5)


def test_inverse_kin_takes_joint_near_as_dobots_client_spells_it(client):
    """Manual: InverseKin(X..Rz,User,Tool,useJointNear,JointNear); with useJointNear=1 the solution
    nearest JointNear. Dobot's Python client sends `useJointNear=1,JointNear={..}`; the manual's table
    writes jointNear: both are taken (names are case-insensitive)."""
    pose = [473.0, -141.0, 469.0, -180.0, 0.0, -90.0]
    near = "{0.000000,0.000000,-90.000000,180.000000,-90.000000,180.000000}"  # the wrist flipped over
    vendor = "InverseKin({:f},{:f},{:f},{:f},{:f},{:f}".format(*pose)
    for text in [f"{vendor},useJointNear=1,JointNear={near})", f"{vendor},user=0,tool=0,useJointNear=1,jointNear={near})"]:
        q = client.ask(text)
        assert q.ok, text
        assert abs(q.values[3] - 168.1) < 1.0 and abs(q.values[4] + 90.0) < 1.0  # the solution near JointNear
        assert same_pose(client.ask(dobot.format_command("PositiveKin", *q.values)).values, pose, atol=1e-3)
    # without useJointNear=1 JointNear is ignored: the solution nearest the current angles
    assert np.allclose(client.ask(f"{vendor},JointNear={near})").values, READY, atol=1e-3)
    assert np.allclose(client.ask(f"{vendor},useJointNear=0,JointNear={near})").values, READY, atol=1e-3)
    assert client.ask(f"{vendor},useJointNear=2,JointNear={near})").error_id == -60001
    assert client.ask(f"{vendor},useJointNear=1,JointNear={{1,2,3}})").error_id == -50001


def test_stop_is_allowed_in_error_and_with_the_emergency_stop_pressed(client):
    """Manual: Stop() is always allowed; other commands stay refused (-2 in error, -3 in e-stop)."""
    client.ask("EnableRobot()")
    assert client.ask("MovJ(joint={0,0,170,0,90,0})").error_id == -1  # beyond J3's limit: alarm
    assert client.ask("RobotMode()").values == [9]
    assert client.ask("Stop()").ok
    assert client.ask("GetAngle()").error_id == -2
    assert client.ask("ClearError()").ok
    assert client.ask("EmergencyStop(1)").ok
    assert client.raw("Stop()") == "0,{},Stop();"
    assert client.ask("SpeedFactor(50)").error_id == -3
    assert client.ask("EmergencyStop(0)").ok and client.ask("ClearError()").ok
    client.ask("EnableRobot()")
    assert client.ask("MovJ(joint={60,0,-90,0,90,0})").ok
    time.sleep(0.1)
    assert client.ask("Stop()").ok  # and it still stops a motion under way
    wait_mode(client, 5)
    assert client.ask("GetAngle()").values[0] < 30.0


@pytest.mark.slow
def test_framing_one_reply_per_command_or_malformed_send(client):
    """Manual: one reply per send. A command may come in several TCP segments (here 300 ms apart); a
    malformed send (unbalanced parentheses, a 100 kB line, text left unfinished) gets exactly one
    -10000: at its end of line or closing ')', or once the client has been quiet for 1 s."""
    s = client.sock
    s.sendall(b"SpeedFactor(")
    time.sleep(0.3)
    s.sendall(b"50)")
    assert [r.command for r in client.collect(0.5)] == ["SpeedFactor(50)"]
    # ended by their closing parenthesis or newline: answered at once (a second reply would show below)
    for line in [b"MovJ(joint={" + b"1," * 50_000 + b"1})", b"A" * 100_000 + b"\n", b")" * 30 + b"\n"]:
        s.sendall(line)
        replies = client.collect(2.0, until=1)
        assert [r.error_id for r in replies] == [-10000], line[:20]
        assert len(replies[0].command) <= 256
    # unbalanced and unfinished: answered once, after the 1 s time-out
    for text in [b"RobotMode()" + b")" * 30, b"MovJ((((joint={0,0,-90,0,90,0})"]:
        s.sendall(text)
        replies = client.collect(1.6)
        assert [r.error_id for r in replies] == [-10000], text
        assert replies[0].command.startswith(text.decode()[:9])
    assert client.raw("RobotMode()") == "0,{4},RobotMode();"  # exactly one reply: the link works on
