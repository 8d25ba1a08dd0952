"""Dobot TCP/IP V4 primitives: the feedback packet's layout, command and reply formats, error ids."""

import numpy as np
import pytest

from bagit.common import dobot
from bagit.common.errors import ProtocolError


def test_feedback_dtype_matches_the_documented_offsets():
    dt = dobot.FEEDBACK_DTYPE
    assert dt.itemsize == 1440
    documented = {
        "MessageSize": 0, "DigitalInputs": 8, "RobotMode": 24, "TimeStamp": 32, "TestValue": 48,
        "SpeedScaling": 64, "QTarget": 192, "QActual": 432, "QDActual": 480, "ToolVectorActual": 624,
        "TCPSpeedActual": 672, "ToolVectorTarget": 768, "VActual": 960, "User": 1012, "Tool": 1013,
        "VelocityRatio": 1016, "BrakeStatus": 1025, "EnableStatus": 1026, "RunningStatus": 1028,
        "ErrorStatus": 1029, "RobotType": 1031, "CollisionState": 1038, "VibrationDisZ": 1104,
        "CurrentCommandId": 1112, "MActual": 1120, "Load": 1168, "UserValue": 1200, "ToolValue": 1248,
        "TargetQuaternion": 1352, "ActualQuaternion": 1384, "AutoManualMode": 1416,
    }  # fmt: skip
    for name, off in documented.items():
        assert dt.fields[name][1] == off, name
    assert dt.fields["QActual"][0].itemsize == 48
    assert dt.fields["ToolVectorActual"][0].shape == (6,)
    assert dt.fields["RobotMode"][0] == np.dtype("<u8")


def test_feedback_round_trip_and_raw_bytes():
    rec = dobot.new_feedback()
    rec["RobotMode"] = dobot.RobotMode.ENABLE
    rec["QActual"] = [10, 20, 30, 40, 50, 60]
    rec["ToolVectorActual"] = [473, -141, 469, -180, 0, -90]
    rec["EnableStatus"] = 1
    rec["CurrentCommandId"] = 7
    raw = rec.tobytes()
    assert len(raw) == 1440
    # little-endian at the documented places, independently of numpy's view
    assert int.from_bytes(raw[0:2], "little") == 1440
    assert int.from_bytes(raw[48:56], "little") == 0x0123456789ABCDEF
    assert int.from_bytes(raw[24:32], "little") == 5
    assert np.frombuffer(raw[432:480], "<f8").tolist() == [10, 20, 30, 40, 50, 60]
    assert raw[1026] == 1
    assert int.from_bytes(raw[1112:1120], "little") == 7
    back = dobot.parse_feedback(raw)
    assert back["QActual"].tolist() == [10, 20, 30, 40, 50, 60]
    assert int(back["RobotMode"]) == 5


def test_parse_feedback_rejects_bad_packets():
    raw = bytearray(dobot.new_feedback().tobytes())
    with pytest.raises(ProtocolError, match="bytes"):
        dobot.parse_feedback(raw[:-1])
    swapped = bytearray(raw)
    swapped[48:56] = (0x0123456789ABCDEF).to_bytes(8, "big")
    with pytest.raises(ProtocolError, match="test value"):
        dobot.parse_feedback(swapped)


def test_feedback_assembler_cuts_a_stream():
    a = dobot.new_feedback()
    b = dobot.new_feedback()
    b["CurrentCommandId"] = 2
    stream = a.tobytes() + b.tobytes() + a.tobytes()[:100]
    asm = dobot.FeedbackAssembler()
    got = asm.feed(stream[:700]) + asm.feed(stream[700:2000]) + asm.feed(stream[2000:])
    assert [int(p["CurrentCommandId"]) for p in got] == [0, 2]
    assert asm.pending == 100
    asm2 = dobot.FeedbackAssembler()
    with pytest.raises(ProtocolError):
        asm2.feed(b"\x00" * 1440)


def test_format_and_parse_commands():
    s = dobot.format_command("ServoP", -500, 100.5, 200, 150, 0, 90, t=0.1, aheadtime=50, gain=500)
    assert s == "ServoP(-500,100.5,200,150,0,90,t=0.1,aheadtime=50,gain=500)"
    c = dobot.parse_command(s)
    assert c.key == "servop" and c.args == [-500, 100.5, 200, 150, 0, 90]
    assert c.named == {"t": 0.1, "aheadtime": 50, "gain": 500}
    m = dobot.parse_command("  movl( pose = {-500, 100,200,150,0,90} , user = 1,tool=0, a=20 ) ")
    assert m.key == "movl" and m.named["pose"] == (-500, 100, 200, 150, 0, 90) and m.named["user"] == 1
    assert m.text.startswith("movl(")
    assert dobot.parse_command("EnableRobot()").args == []
    assert dobot.format_command("MovJ", joint=np.radians([0, 90, 0, 0, 0, 0]) * 0 + [1, 2, 3, 4, 5, 6]) == "MovJ(joint={1,2,3,4,5,6})"
    assert dobot.parse_command("RunScript(demo_1)").args == ["demo_1"]
    assert dobot.parse_command("SpeedFactor(1e2)").args == [100.0]
    # a word inside a vector is a parameter of the wrong type for the controller to number, not malformed text
    assert dobot.parse_command("MovJ(pose={nan,1,2,3,4,5})").named["pose"] == ("nan", 1.0, 2.0, 3.0, 4.0, 5.0)


@pytest.mark.parametrize(
    "bad",
    ["", "EnableRobot", "EnableRobot(", "9Robot()", "MovL(pose={1,2,3)", "MovL(pose=1,2})", "GetPose(user=1,user=2)",
     "MovJ(joint={1,2},3)", "Foo(a=1, 2)", "Foo(__import__('os'))", "Foo(1;2)", "Foo(,)", "x" * 5000 + "()"],
)
def test_parse_command_rejects_malformed(bad):
    with pytest.raises(ProtocolError):
        dobot.parse_command(bad)


def test_format_command_refuses_what_cannot_travel():
    with pytest.raises(ProtocolError):
        dobot.format_command("ServoP", float("nan"), 0, 0, 0, 0, 0)
    with pytest.raises(ProtocolError):
        dobot.format_command("Bad Name")
    with pytest.raises(ProtocolError):
        dobot.format_command("RunScript", "a)b")


def test_command_splitter():
    sp = dobot.CommandSplitter()
    assert sp.feed(b"EnableRobot()ServoP(1,2,3,4,5,6,t=0.1)\nMovL(pose={1,2,3") == [
        "EnableRobot()", "ServoP(1,2,3,4,5,6,t=0.1)"
    ]
    assert sp.feed(b",4,5,6});GetPose()") == ["MovL(pose={1,2,3,4,5,6})", "GetPose()"]
    assert sp.feed(b"garbage\nRobotMode()") == ["garbage", "RobotMode()"]
    assert sp.feed(b"A" * 5000) == []  # too long: one malformed frame once it ends (newline, ')' or a pause)
    rest = sp.flush()
    assert rest == "A" * 4097 and rest.malformed


def test_command_splitter_frames_one_reply_per_send():
    sp = dobot.CommandSplitter(timeout_s=1.0)
    assert sp.feed(b"SpeedFactor(", now=0.0) == [] and sp.expire(now=0.5) is None
    assert sp.feed(b"50)", now=0.8) == ["SpeedFactor(50)"]  # two segments, one command
    bad = sp.feed(b"RobotMode()" + b")" * 20 + b"\nGetPose()", now=1.0)
    assert bad == ["RobotMode()" + ")" * 20, "GetPose()"] and [f.malformed for f in bad] == [True, False]
    assert sp.feed(b"))))", now=2.0) == [] and sp.feed(b"))))", now=2.5) == [] and sp.expire(now=3.0) is None
    late = sp.expire(now=3.6)
    assert late == ")" * 8 and late.malformed and not sp.pending  # one frame for the whole pause-free send
    long = b"MovJ(joint={" + b"1," * 50_000 + b"1})"
    frames = [f for i in range(0, len(long), 4096) for f in sp.feed(long[i : i + 4096], now=4.0)]
    assert len(frames) == 1 and frames[0].malformed and len(frames[0]) == 4097


def test_replies():
    r = dobot.format_reply(0, [473.0, -141.0, 469.0, -180.0, 0.0, -90.0], "GetPose()")
    assert r == "0,{473.000000,-141.000000,469.000000,-180.000000,0.000000,-90.000000},GetPose();"
    p = dobot.parse_reply(r)
    assert p.ok and p.values == [473, -141, 469, -180, 0, -90] and p.command == "GetPose()"
    q = dobot.parse_reply("0,{1},MovL(pose={-500,100,200,150,0,90});")
    assert q.values == [1.0] and q.command == "MovL(pose={-500,100,200,150,0,90})"
    e = dobot.parse_reply(dobot.format_reply(dobot.ErrorId.UNKNOWN_COMMAND, None, "Mov(1)"))
    assert e.error_id == -10000 and e.values == [] and not e.ok
    ids = dobot.format_error_ids([17, 77])
    assert ids == "[[17,77],[],[],[],[],[],[]]"
    g = dobot.parse_reply(dobot.format_reply(0, ids, "GetErrorID()"))
    assert dobot.parse_error_ids(g.raw_values) == [[17, 77], [], [], [], [], [], []]
    assert dobot.format_reply(0, [5], "RobotMode()") == "0,{5},RobotMode();"
    for bad in ["", "0,{},GetPose()", "ok", "x,{},A();"]:
        with pytest.raises(ProtocolError):
            dobot.parse_reply(bad)
    done, rest = dobot.split_replies("0,{},A();0,{5},RobotMode();-1,{},Mo")
    assert done == ["0,{},A();", "0,{5},RobotMode();"] and rest == "-1,{},Mo"


def test_error_ids_and_alarms():
    assert dobot.param_error(dobot.ErrorId.REQUIRED_TYPE, 1) == -30001
    assert dobot.param_error(dobot.ErrorId.REQUIRED_RANGE, 2) == -40002
    assert dobot.param_error(dobot.ErrorId.OPTIONAL_TYPE, 1) == -50001
    assert dobot.param_error(dobot.ErrorId.OPTIONAL_RANGE, 3) == -60003
    with pytest.raises(ValueError):
        dobot.param_error(dobot.ErrorId.FAILED, 1)
    assert dobot.joint_limit_alarm(2, True) == 68 and dobot.joint_limit_alarm(2, False) == 69
    assert dobot.overspeed_alarm(5) == 53
    assert dobot.describe_alarm(53) == "joint 6 overspeed" and dobot.describe_alarm(69) == "joint 3 beyond its negative limit"
    assert dobot.describe_alarm(17) == "no inverse kinematics solution" and dobot.describe_alarm(999) == "alarm 999"
    assert dobot.RobotMode.ERROR == 9 and dobot.RobotMode.ENABLE == 5 and dobot.RobotMode.DISABLED == 4
