"""The arm driver against two simulated CR5 controllers over TCP (ephemeral loopback ports).

Bring-up and shutdown sequences; streaming that is jerk-limited as the controllers receive it and
as their feedback shows; the watchdog; the e-stop reaching both controllers and staying latched;
a controller error stopping the other arm; feedback loss; a dropped connection mid-stream.

Timing claims are measured on the controllers' side: the command log's receive times and the
feedback packets, recorded on connections of their own. The machine running these may be loaded,
so the servo loop's and the simulators' own jitter is allowed for where the test says so.
"""

import threading
import time

import numpy as np
import pytest
from arm_driver_support import SIM_CFG, FeedbackRecorder, Streamer, home_poses, servo_parameter, servo_positions, start_sims, stream_at_rest
from suite_support import wait_until

from bagit.common.dobot import Alarm
from bagit.common.errors import ProtocolError
from bagit.common.messages import Command, EStop
from bagit.common.names import ESTOP_SOURCE_CLI
from bagit.common.rig import ARMS
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.driver import ArmDriver


@pytest.fixture
def rig():
    made = []

    def make(config=SIM_CFG, proxy=False, **sim_kw):
        sims = start_sims(proxy=proxy, **sim_kw)
        drv = ArmDriver(sims.rig, config)
        made.append((sims, drv))
        return sims, drv

    yield make
    for sims, drv in made:
        drv.close()
        sims.close()


def stream(drv, u_of_t, seconds, rate=30.0, t_start=None):
    """Submit `u_of_t(t)` at `rate` Hz for `seconds`; returns (monotonic time of the last accepted submit, accepted
    count). A loaded machine can hold a command back past the watchdog's time: the driver refuses it as stale."""
    t0 = time.monotonic() if t_start is None else t_start
    k, accepted, last = 0, 0, t0
    while True:
        t = k / rate
        if t >= seconds:
            return last, accepted
        wait = t0 + t - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        sent = time.monotonic()
        if drv.submit(Command(u=u_of_t(t), dt=1 / rate, seq=k)):
            accepted, last = accepted + 1, sent
        k += 1


def loop_stall(drv, t0, t1):
    """Seconds the servo loop lost to the machine between t0 and t1 (cycles that started late).

    Timing bounds below add this: they are about the driver's logic, and a loaded machine that
    keeps the process off the CPU delays every period it does not run.
    """
    starts = np.array([t for t in drv.cycle_starts if t0 - drv.period <= t <= t1 + drv.period])
    gaps = np.diff(starts)
    return float(np.sum(np.clip(gaps - drv.period, 0.0, None)[gaps > 1.2 * drv.period]))


def mount_positions(drv):
    return {a: s.tool_pose[:3].copy() for a, s in drv.states().items()}


def test_bring_up_and_shutdown_follow_the_real_rig(rig):
    sims, drv = rig()
    for r in sims.robots.values():
        assert not r.enabled
    drv.start()
    assert drv.mode == "holding"
    for a, srv in sims.servers.items():
        names = [text for _, text, _ in srv.log]
        assert names[:3] == ["ClearError()", "EnableRobot(0.3,0,0,60)", "SpeedFactor(50)"]
        assert all(reply.startswith("0,") for _, _, reply in srv.log[:3])
        assert sims.robots[a].enabled and sims.robots[a].speed_factor == 50
    states = drv.states()
    assert set(states) == {"left", "right"}
    for a, s in states.items():
        assert s.enabled and not s.error and s.robot_mode == 5
        assert np.allclose(s.tool_pose[:3], home_poses()[a][:3, 3], atol=1e-4)  # the mount, in the world
    # stream a little, then close mid-motion: the arms brake to rest before DisableRobot
    u = np.zeros(12)
    u[0] = u[6] = 0.08 / 30
    last, _ = stream(drv, lambda t: u, 0.5)
    drv.close()
    for a, srv in sims.servers.items():
        assert not sims.robots[a].enabled
        log = srv.log
        assert log[-1][1] == "DisableRobot()" and log[-1][2].startswith("0,")
        # the ServoPs around the close: tracking, then braking ones (halt_aheadtime) to the end, each step no
        # longer than the one before, the last one the pose the trajectory came to rest at
        t0 = last - 0.2  # (the last accepted command: a loaded machine may have let the watchdog brake before the close)
        ts, xyz = servo_positions(srv, t0=t0)
        ahead = [servo_parameter(text, "aheadtime") for t, text, reply in srv.commands("ServoP") if t >= t0 and reply.startswith("0,")]
        halting = np.array(ahead) == drv.cfg.halt_aheadtime
        k = int(np.argmax(halting))
        assert len(ts) == len(halting) and k > 0 and np.all(halting[k:]), ahead
        steps = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
        assert np.all(np.diff(steps[k - 1 :]) <= 1e-9), steps
        rest = drv.frames[a].flange_in_base(drv.path.commanded()[a])[:3, 3]
        assert np.allclose(xyz[-1], rest, atol=1e-6), (xyz[-1], rest)
    assert drv.mode == "off"


def test_bring_up_fails_cleanly_when_a_controller_refuses(rig):
    sims, drv = rig()
    sims.robots["right"].emergency_stop(True)  # the pendant's e-stop is pressed
    with pytest.raises(ProtocolError, match=r"right: .*EnableRobot.* refused: -3 \(emergency stop pressed\)"):
        drv.start()
    assert not sims.robots["left"].enabled  # the arm that came up is disabled again
    assert drv.mode == "off"


def test_streamed_commands_are_jerk_limited_as_received_and_in_the_feedback(rig):
    sims, drv = rig()
    rec = {a: FeedbackRecorder(s.feedback_port) for a, s in sims.servers.items()}
    try:
        drv.start()
        lim = sims.rig.safety
        # a controller-like stream: 30 Hz, per-tick increments that change abruptly (a square wave in
        # velocity, the worst case for smoothness) and two axes at once on the right arm
        def u_of_t(t):
            u = np.zeros(12)
            sgn = 1.0 if (t % 0.8) < 0.4 else -1.0
            u[0] = 0.1 * sgn / 30
            u[6] = 0.08 * sgn / 30
            u[8] = 0.06 * sgn / 30
            return u

        t0 = time.monotonic()
        stream(drv, u_of_t, 2.4)
        assert wait_until(lambda: drv.mode == "holding")
        t1 = time.monotonic()
        stalls = drv.status()["counters"].get("stalls", 0)
        P = drv.period
        peak_jerk = 0.0
        path_a, path_j = lim.path_limits()[0, 1:]
        stop_a, stop_j = lim.stop_limits()[0, 1:]
        for a, srv in sims.servers.items():
            ts, xyz = servo_positions(srv, t0, t1)
            assert len(ts) > 10
            # the watchdog's stop at the end brakes within the stop's limits, everything before within the path's:
            # a difference is judged by the limits of its last ServoP (the first braking one is sent with halt_aheadtime)
            braking = [t for t, text, reply in srv.commands("ServoP")
                       if t0 <= t <= t1 and reply.startswith("0,") and servo_parameter(text, "aheadtime") == SIM_CFG.halt_aheadtime]
            assert braking, "the watchdog's stop"
            t_brake = braking[0]
            brakes = ts >= t_brake
            # A loaded machine may starve the servo loop past the watchdog: the driver then reports a stall,
            # the arm stops at its last target, and a new stream starts from rest there. The ServoPs are
            # checked stream by stream; across a gap nothing may jump, and a change of speed there that
            # no period's limits allow must be one of the stalls the driver reported.
            cuts = np.flatnonzero(np.diff(ts) > 2 * P) + 1
            for i in cuts:
                assert np.linalg.norm(xyz[i] - xyz[i - 1]) <= lim.max_tcp_speed_mps * P * (1 + 1e-6)
            acc_all = np.linalg.norm(np.diff(xyz, 2, axis=0), axis=1) / P**2  # [k]: centred on sample k + 1
            acc_lim = np.where(brakes[2:], stop_a, path_a)
            unexplained = [i for i in cuts if (acc_all - acc_lim)[max(i - 2, 0):i].max(initial=0.0) > 0]
            stops = sum(1 for k, i in enumerate(unexplained) if k == 0 or i - unexplained[k - 1] > 3)  # a stop and its restart: one
            assert stops <= stalls, drv.status()["events"]
            for seg, seg_brakes in zip(np.split(xyz, cuts), np.split(brakes, cuts), strict=True):
                v = np.linalg.norm(np.diff(seg, 1, axis=0), axis=1) / P
                acc = np.linalg.norm(np.diff(seg, 2, axis=0), axis=1) / P**2
                jerk = np.linalg.norm(np.diff(seg, 3, axis=0), axis=1) / P**3
                assert v.max(initial=0.0) <= lim.max_tcp_speed_mps * (1 + 1e-6)
                assert np.all(acc <= np.where(seg_brakes[2:], stop_a, path_a) * (1 + 1e-6)), drv.status()
                assert np.all(jerk <= np.where(seg_brakes[3:], stop_j, path_j) * (1 + 1e-6))
                peak_jerk = max(peak_jerk, jerk[~seg_brakes[3:]].max(initial=0.0))
            # the feedback: the arm's speed within the limit, and its acceleration too, averaged over 80 ms
            # of the controller's own clock (RunTime, sampled with the state). Over shorter windows the
            # simulator's tracking of each 30 ms ServoP ramp shows, more so when a loaded machine
            # starves its stepping thread; 20 % is allowed for that. Windows over a gap between ServoPs are left out.
            t_fb, speed = rec[a].series("TCPSpeedActual", t0, t1)
            _, run = rec[a].series("RunTime", t0, t1)
            vel = speed[:, :3] / 1000.0
            assert np.linalg.norm(vel, axis=1).max() <= lim.max_tcp_speed_mps * 1.05
            keep = np.concatenate([[True], np.diff(run) > 0])  # a packet sent between two simulator steps repeats the state
            vel, tsim, t_fb = vel[keep], run[keep] / 1000.0, t_fb[keep]
            j = np.searchsorted(tsim, tsim + 0.08)
            ok = j < len(tsim)
            for i in cuts:  # a ServoP that ran out before the next came: the controller stopped the arm itself
                ok &= (t_fb + 0.2 < ts[i - 1]) | (t_fb > ts[i] + 0.2)
            fb_acc = np.linalg.norm(vel[j[ok]] - vel[ok], axis=1) / (tsim[j[ok]] - tsim[ok])
            fb_lim = np.where(t_fb[j[ok]] >= t_brake, stop_a, path_a)  # a window that reaches the stop: the stop's
            assert np.all(fb_acc <= 1.2 * fb_lim), (fb_acc / fb_lim).max()
        assert peak_jerk > 0.5 * path_j / np.sqrt(3)  # the square wave does push the path's jerk limit
        assert drv.status()["violations"] == {}
        # ServoP no faster than every servo period (Dobot's rule for ServoP: 30 ms)
        assert np.diff(np.array(drv.send_times)).min() >= drv.period - 1e-3
    finally:
        for r in rec.values():
            r.close()


def settled(rec: FeedbackRecorder, t0: float) -> bool:
    """The arm's last feedback packet since `t0` says it is below 1 mm/s."""
    _, speed = rec.series("TCPSpeedActual", t0)
    return len(speed) > 0 and float(np.linalg.norm(speed[-1, :3])) < 1.0  # mm/s


def test_the_watchdog_stops_both_arms_after_the_last_command(rig):
    sims, drv = rig()
    rec = {a: FeedbackRecorder(s.feedback_port) for a, s in sims.servers.items()}
    try:
        drv.start()
        v0 = 0.04
        u = np.zeros(12)
        u[0] = u[6] = v0 / 30
        before = mount_positions(drv)
        stream(drv, lambda t: u, 0.5)  # 15 commands: 2 cm at 4 cm/s ...
        last = u * 30 * 0.75  # ... then one last command that would carry on for 0.75 s (3 cm more)
        t_last = time.monotonic()
        assert drv.submit(Command(u=last, dt=0.75, seq=15))
        assert wait_until(lambda: drv.mode == "holding")
        for srv in sims.servers.values():
            assert wait_until(lambda: stream_at_rest(srv, t_last))
        stall = loop_stall(drv, t_last, t_last + 1.0)
        ev = [t for t, k, _ in drv.events if k == "watchdog" and t > t_last]
        # the order; how soon (the watchdog's 120 ms, braking 2 sqrt(v0 / j)) is bench/stop_time.py's
        assert len(ev) == 1  # once after the last command (a loaded machine may stall the stream before it too)
        for a, srv in sims.servers.items():
            # at the controller: braking ServoPs after the watchdog fired, sent with the halting aheadtime
            # (the commands before it with the tracking one), ending at rest
            ts, xyz = servo_positions(srv, t_last - 0.2)
            braking = ts[ts > ev[0]]
            assert len(braking)
            ahead = {t: servo_parameter(text, "aheadtime") for t, text, _ in srv.commands("ServoP")}
            assert {ahead[t] for t in ts if t >= braking[0]} == {drv.cfg.halt_aheadtime}
            assert {ahead[t] for t in ts if t < ev[0]} == {drv.cfg.aheadtime}
            # on the feedback: the arm itself settles after the braking began; it went only part of the way
            assert wait_until(lambda: settled(rec[a], braking[0]))
        after = mount_positions(drv)
        for a in before:  # it followed the stream (2 cm, less the few mm the trajectory trails a moving target by:
            # the stop no longer carries it on for 126 ms), and stopped short of the 5 cm it added up to
            assert 0.015 < after[a][0] - before[a][0] < 0.05 - 0.01 + v0 * stall
    finally:
        for r in rec.values():
            r.close()


def test_a_servo_cycle_made_before_the_estop_latched_is_not_sent_after_it(rig):
    # the servo loop makes a cycle, then (on the wall clock) waits up to a period to space its sends: an
    # e-stop latched in between must not let that cycle's ServoPs out after the EmergencyStop
    sims, drv = rig()
    drv.start()
    u = np.zeros(12)
    u[2], u[8] = 0.03 / 30, 0.03 / 30
    for _ in range(20):  # a starved stream can stall the driver (its watchdog): stream again until it moves
        stream(drv, lambda t: u, 0.2)
        made = drv.make_cycle()
        if made is not None and made[0].servo:
            break
    assert made is not None and made[0].servo  # moving: this cycle has ServoPs for both arms
    drv.estop("test: pressed between a cycle and its send")
    assert drv.send_cycle(made[0]) == []
    for a, srv in sims.servers.items():
        texts = [text for _, text, _ in srv.log]
        assert "EmergencyStop(1)" in texts and not [x for x in texts[texts.index("EmergencyStop(1)"):] if x.startswith("ServoP")], a


def test_estop_reaches_both_controllers_and_stays_latched(rig):
    sims, drv = rig()
    seen = []
    drv.on_event = lambda kind, detail: seen.append(kind)
    drv.start()
    u = np.zeros(12)
    u[1] = -0.05 / 30
    u[7] = 0.05 / 30
    th = threading.Thread(target=stream, args=(drv, lambda t: u, 1.5), daemon=True)
    th.start()
    time.sleep(0.5)
    t_call = time.monotonic()
    reached = drv.estop("test: operator pressed E-STOP")
    assert reached == {"left": True, "right": True} and "estop" in seen
    for a, srv in sims.servers.items():
        got = [t for t, text, reply in srv.log if text == "EmergencyStop(1)"]
        assert len(got) == 1 and got[0] >= t_call, got[0] - t_call
        assert sims.robots[a].estop_pressed and not sims.robots[a].enabled
        texts = [text for _, text, _ in srv.log]
        # a servo cycle made before the latch goes out before the EmergencyStop (one connection) or not at all
        assert not [x for x in texts[texts.index("EmergencyStop(1)"):] if x.startswith("ServoP")], a
    th.join()
    assert drv.status()["rejections"].get("estopped", 0) > 0  # the stream kept coming and was refused
    time.sleep(0.3)
    assert drv.mode == "estopped" and all(s.estopped for s in drv.states().values())
    for a, srv in sims.servers.items():
        assert sims.robots[a].estop_pressed  # still latched at the controller ...
        late = [text for t, text, _ in srv.log if t > t_call + 0.05 and text.startswith("ServoP")]
        assert late == []  # ... and nothing was streamed after it
    assert not drv.submit(Command(u=u))
    # only an explicit reset clears it (here as the EStop message would), and motion needs a new stream
    drv.handle_estop(EStop(engage=False, source=ESTOP_SOURCE_CLI))
    assert drv.mode in ("restarting", "holding")
    assert wait_until(lambda: drv.mode == "holding")
    for a in sims.robots:
        assert not sims.robots[a].estop_pressed and sims.robots[a].enabled and not sims.robots[a].alarms()
    before = mount_positions(drv)
    stream(drv, lambda t: u, 0.5)
    assert wait_until(lambda: drv.mode == "holding")
    after = mount_positions(drv)
    assert after["right"][1] - before["right"][1] > 0.01


def test_a_controller_error_stops_the_other_arm_until_cleared(rig):
    sims, drv = rig()
    drv.start()
    u = np.zeros(12)
    u[2] = u[8] = 0.1 / 30
    th = threading.Thread(target=stream, args=(drv, lambda t: u, 1.2), daemon=True)
    th.start()
    time.sleep(0.5)
    t_fault = time.monotonic()
    sims.robots["left"].raise_alarm(int(Alarm.FLANGE_INTERFERENCE))
    th.join()
    assert drv.mode == "fault" and "left" in drv.status()["fault"]
    # the supervisor asks the controllers which alarm tripped (GetErrorID) and adds it to the fault
    assert wait_until(lambda: "77 (flange interferes" in drv.status()["fault"]), drv.status()["fault"]
    ts, xyz = servo_positions(sims.servers["right"], t0=t_fault)
    steps = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
    assert steps[-1] < 1e-4 and steps.max() <= 0.1 / 30 * 1.5  # braked smoothly to rest
    rest = sims.robots["right"].flange_pose_world()[:3, 3].copy()
    time.sleep(0.3)
    assert np.allclose(sims.robots["right"].flange_pose_world()[:3, 3], rest, atol=1e-4)  # and it stays there
    assert not drv.submit(Command(u=u)) and drv.status()["rejections"]["fault"] > 0
    drv.clear_fault()
    assert wait_until(lambda: drv.mode == "holding")
    assert not sims.robots["left"].alarms()
    before = mount_positions(drv)
    stream(drv, lambda t: u, 0.4)
    assert wait_until(lambda: drv.mode == "holding")
    assert mount_positions(drv)["left"][2] - before["left"][2] > 0.005


def test_feedback_loss_stops_both_arms_and_a_new_stream_resumes_after_it(rig):
    sims, drv = rig(config=DriverConfig(), proxy=True)
    drv.start()
    u = np.zeros(12)
    u[0] = u[6] = 0.08 / 30
    fb_right = sims.servers["right"].feedback_port
    feed = Streamer(drv, u).start()
    time.sleep(0.4)
    sims.proxies["right"].pause(fb_right)  # the right controller's feedback goes silent
    assert wait_until(lambda: drv.mode == "link_down")  # how soon: the feedback time-out, 0.2 s after the cut
    t_down = time.monotonic()
    time.sleep(0.5)
    ts, xyz = servo_positions(sims.servers["left"], t0=t_down + 0.4)
    assert len(ts) == 0  # the left arm has braked and holds
    sims.proxies["right"].resume(fb_right)
    assert wait_until(lambda: drv.mode == "streaming")  # reconnected, restarted, the stream resumed
    feed.stop()
    st = drv.status()
    assert st["counters"]["links_lost"] >= 1 and st["counters"]["reconnects"] >= 1
    assert st["rejections"]["link_down"] > 0


def test_a_dropped_connection_mid_stream_reconnects_without_a_jump(rig):
    sims, drv = rig(proxy=True)
    rec = {a: FeedbackRecorder(s.feedback_port) for a, s in sims.servers.items()}
    try:
        drv.start()
        u = np.zeros(12)
        u[0] = 0.06 / 30
        u[6] = 0.06 / 30
        t0 = time.monotonic()
        feed = Streamer(drv, u).start()
        time.sleep(0.6)
        t_drop = time.monotonic()
        sims.proxies["left"].drop()  # both of the left controller's connections reset mid-stream
        assert wait_until(lambda: drv.status()["counters"].get("reconnects", 0) >= 1)
        assert wait_until(lambda: drv.mode == "streaming")

        def kept_going() -> bool:  # both arms went on after the reconnect (a busy machine takes longer)
            moved = [servo_positions(srv, t_drop + 0.2, time.monotonic()) for srv in sims.servers.values()]
            return all(len(ts) > 5 and np.linalg.norm(xyz[-1] - xyz[0]) > 0.01 for ts, xyz in moved)

        assert wait_until(kept_going, step=0.05)
        feed.stop()
        assert wait_until(lambda: drv.mode == "holding")
        t1 = time.monotonic()
        lim = sims.rig.safety
        for a, srv in sims.servers.items():
            # what the controller was told: never a step faster than the speed limit, across the outage too
            ts, xyz = servo_positions(srv, t0, t1)
            steps = np.linalg.norm(np.diff(xyz, axis=0), axis=1)
            assert steps.max() <= lim.max_tcp_speed_mps * drv.period * (1 + 1e-6) + 1e-3
            # what the arm did: continuous, within the speed limit
            tf, pos = rec[a].series("ToolVectorActual", t0, t1)
            _, speed = rec[a].series("TCPSpeedActual", t0, t1)
            _, run = rec[a].series("RunTime", t0, t1)  # the controller's clock, consistent with its state
            assert np.linalg.norm(speed[:, :3], axis=1).max() / 1000.0 <= lim.max_tcp_speed_mps * 1.05
            gaps = np.linalg.norm(np.diff(pos[:, :3], axis=0), axis=1) / 1000.0
            assert np.all(gaps <= lim.max_tcp_speed_mps * np.diff(run) / 1000.0 + 0.5e-3)  # no jump between packets
        assert drv.clients["left"].epoch == 2 and drv.clients["right"].epoch == 1
    finally:
        for r in rec.values():
            r.close()


def test_a_restart_while_an_arm_still_moves_starts_from_its_target_not_where_it_lags(rig):
    """A simulator starved of CPU stalls mid-motion: the link drops (no feedback) and the arm, frozen
    behind its last servo target, never settles. The restart then starts from the pose the controller
    commands (ToolVectorTarget), not the lagging actual one: a first target back behind the arm is a
    jump the controller alarms on near a wrist singularity. The next stream runs without an alarm."""
    sims, drv = rig(proxy=True)
    drv.start()
    u = np.zeros(12)
    u[0] = u[6] = 0.09 / 30
    feed = Streamer(drv, u).start()
    time.sleep(0.6)
    left = sims.robots["left"]
    step = left.step
    left.step = lambda dt: None  # the left controller stops moving where it is, mid-motion
    sims.proxies["left"].drop()
    assert wait_until(lambda: drv.status()["counters"].get("reconnects", 0) >= 1)
    feed.stop()
    rec = left.fill_feedback()
    actual = drv.frames["left"].mount_from_pose6(rec["ToolVectorActual"])
    target = drv.frames["left"].mount_from_pose6(rec["ToolVectorTarget"])
    assert np.linalg.norm(target[:3, 3] - actual[:3, 3]) > 1e-3  # the arm lags its target by over a millimetre
    assert wait_until(lambda: not drv.state.needs_reset)  # restarted without the arm settling
    start = drv.path.commanded()["left"]
    assert np.linalg.norm(start[:3, 3] - target[:3, 3]) < 1e-4, (start[:3, 3], target[:3, 3], actual[:3, 3])
    left.step = step
    feed = Streamer(drv, -u).start()
    time.sleep(0.6)
    feed.stop()
    assert not left.alarms() and drv.status()["fault"] is None, (left.alarm_log, drv.status()["fault"])


def test_servoj_streams_through_the_cr5_inverse_kinematics(rig):
    sims, drv = rig(config=SIM_CFG.model_copy(update={"servo_command": "servoj"}))
    drv.start()
    before = mount_positions(drv)
    u = np.zeros(12)
    u[2] = 0.05 / 30
    u[8] = -0.05 / 30
    # 3 cm in 0.6 s, then keep-alives until the arms are on the last target (the watchdog's stop would end
    # the motion a few mm short: it brakes at once, the trajectory trailing the moving target)
    stream(drv, lambda t: u if t < 0.6 else np.zeros(12), 1.0)
    assert wait_until(lambda: drv.mode == "holding")
    after = mount_positions(drv)
    assert after["left"][2] - before["left"][2] == pytest.approx(0.03, abs=0.002)
    assert after["right"][2] - before["right"][2] == pytest.approx(-0.03, abs=0.002)
    for srv in sims.servers.values():
        assert srv.commands("ServoJ") and not srv.commands("ServoP")


@pytest.mark.slow
def test_a_target_out_of_reach_is_approached_slowly_and_never_passed_without_a_fault(rig):
    sims, drv = rig()
    kinds: list[str] = []  # every event (the status keeps the last few: a starved loop's stalls push a slow-down out)
    drv.on_event = lambda kind, detail: kinds.append(kind)
    drv.start()
    u = np.zeros(12)
    u[[0, 2, 6, 8]] = 0.1 / 30  # both mounts out and up, inside the workspace boxes but past the arms' reach
    feed = Streamer(drv, u).start()
    # near the edge of the reach the elbow straightens and its joints speed up: the steps shorten
    assert wait_until(lambda: drv.counters["slowed"] > 0), drv.status()
    time.sleep(1.0)
    before = mount_positions(drv)
    time.sleep(0.5)
    after = mount_positions(drv)
    feed.stop()
    st = drv.status()
    assert st["fault"] is None and drv.mode in ("streaming", "stopping", "holding"), st
    assert "slowed" in kinds, kinds
    for a in ARMS:  # at the edge of the reach the arms creep at most, the controller pushing on
        assert np.linalg.norm(after[a] - before[a]) < 0.02, (a, before[a], after[a])
    for a, r in sims.robots.items():
        assert r.alarms() == [] and r.robot_mode() in (5, 7), (a, r.alarms())  # the controllers never alarmed
        assert all(reply.startswith("0,") for _, _, reply in sims.servers[a].commands("ServoP"))


def test_garbled_replies_and_feedback_are_reported_and_stop_the_arms_without_a_crash(rig):
    sims, drv = rig(proxy=True)
    drv.start()
    u = np.zeros(12)
    u[0] = u[6] = 0.05 / 30
    dash, fb = sims.servers["left"].dashboard_port, sims.servers["left"].feedback_port
    feed = Streamer(drv, u).start()
    time.sleep(0.3)
    # feedback bytes flipped here and there: packets fail their checks and are skipped, the rest is used
    flips = iter(range(10**9))
    sims.proxies["left"].mangle(fb, lambda b: bytes(x ^ 0xFF if (i + next(flips)) % 997 == 0 else x for i, x in enumerate(b)))
    time.sleep(0.4)
    sims.proxies["left"].resume(fb)
    bad = drv.status()["arms"]["left"]["bad_packets"]
    assert bad > 0 and drv.mode == "streaming"
    # replies replaced by noise: each ServoP's reply is reported malformed; three in a row are a fault
    sims.proxies["left"].mangle(dash, lambda b: b"#?!" + b[::-1])
    assert wait_until(lambda: drv.mode == "fault")
    st = drv.status()
    assert "without a good reply" in st["fault"] and st["arms"]["left"]["malformed_replies"] >= 3
    sims.proxies["left"].resume(dash)
    feed.stop()
    def right_at_rest() -> bool:  # the other arm braked to rest (timing is the watchdog test's job)
        steps = np.linalg.norm(np.diff(servo_positions(sims.servers["right"], t0=time.monotonic() - 0.2)[1], axis=0), axis=1)
        return len(steps) == 0 or steps.max() < 1e-4

    assert wait_until(right_at_rest)
    drv.clear_fault()
    assert wait_until(lambda: drv.mode == "holding")
    stream(drv, lambda t: u, 0.3)
    assert drv.status()["counters"]["accepted"] > 0 and drv.mode in ("streaming", "holding")


def test_arm_state_is_published_at_the_feedback_rate(rig):
    sims, drv = rig()
    got = {"left": [], "right": []}
    drv.on_state = lambda s: got[s.arm].append(s)
    drv.start()
    got["left"].clear()
    got["right"].clear()
    assert wait_until(lambda: min(len(v) for v in got.values()) >= 125)  # a second's worth at 125 Hz, however long that takes
    for a, states in got.items():
        assert np.all(np.diff([m.stamp for m in list(states)]) > 0)  # one state per feedback packet, in order
        s = states[-1]
        assert s.enabled and not s.estopped and s.q.shape == (6,) and np.all(np.isfinite(s.tool_pose))
        assert np.allclose(s.tool_pose[:3], home_poses()[a][:3, 3], atol=1e-4)


def test_non_finite_increments_are_refused_and_reported(rig):
    sims, drv = rig()
    drv.start()
    before = mount_positions(drv)
    bad = np.zeros(12)
    bad[3] = np.inf
    assert not drv.submit_increment(bad, 1 / 30)
    assert not drv.submit(Command.model_construct(u=np.full(12, np.nan), dt=1 / 30, mode="servo", seq=1))
    huge = np.zeros(12)
    huge[2] = 1e9  # finite but absurd: accepted, clipped to the lead limit and the box, reported
    assert drv.submit_increment(huge, 1 / 30)
    assert wait_until(lambda: drv.mode == "holding")
    st = drv.status()
    assert st["rejections"]["non_finite"] == 2 and st["violations"]["non_finite"] == 2
    assert st["violations"]["lead"] >= 1 and st["counters"]["clipped"] == 1
    after = mount_positions(drv)
    rise = after["left"][2] - before["left"][2]
    assert 0.0 < rise <= drv.cfg.max_target_lead_m + 1e-3 and abs(after["right"][2] - before["right"][2]) < 1e-3
