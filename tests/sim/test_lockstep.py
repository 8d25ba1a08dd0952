"""Lockstep's pure parts: the rig clock's arithmetic, the event schedule, and who the simulator waits for."""

from __future__ import annotations

import threading

import numpy as np

from bagit.common.clock import SIM_EPOCH0_S, SIM_QUANTUM_S, SimClock, WallClock, next_epoch, sim_time
from bagit.common.messages import StepAck
from bagit.services.sim.lockstep import Lockstep, Schedule


def test_differences_of_rig_times_do_not_depend_on_the_epoch():
    # what makes `bagit up`'s tenth run compute what `bagit run` computes: ages, dts and a time plus a
    # period round alike in every epoch (one binade, a quantised grid)
    rng = np.random.default_rng(0)
    worlds = np.cumsum(rng.uniform(0.001, 0.05, 400))
    epochs = [SIM_EPOCH0_S, next_epoch(SIM_EPOCH0_S + 7.3), next_epoch(SIM_EPOCH0_S + 86_400.2)]
    rel = []
    for e in epochs:
        t = np.array([sim_time(w, e) for w in worlds])
        rel.append([np.diff(t).tolist(), [((x + 0.03) - x) for x in t], [(x + 1 / 30) - e for x in t]])
    assert rel[0] == rel[1] == rel[2]
    assert all((sim_time(w) - SIM_EPOCH0_S) / SIM_QUANTUM_S == round((sim_time(w) - SIM_EPOCH0_S) / SIM_QUANTUM_S) for w in worlds[:20])


def test_a_new_worlds_epoch_is_after_the_clock_so_it_never_goes_back():
    for t in (SIM_EPOCH0_S, SIM_EPOCH0_S + 0.999999, SIM_EPOCH0_S + 41.0):
        e = next_epoch(t)
        assert e > t and e == int(e) and sim_time(0.0, e) > t


def test_sim_clock_moves_forward_only_and_wakes_its_waiters():
    c, stop = SimClock(SIM_EPOCH0_S), threading.Event()
    c.advance(SIM_EPOCH0_S + 1.0)
    c.advance(SIM_EPOCH0_S + 0.5)  # a late message never turns the clock back
    assert c.now() == SIM_EPOCH0_S + 1.0
    assert not c.wait_until(SIM_EPOCH0_S + 2.0, stop, timeout=0.05)
    threading.Timer(0.05, c.advance, args=(SIM_EPOCH0_S + 2.0, 7)).start()
    assert c.wait_until(SIM_EPOCH0_S + 2.0, stop, timeout=5.0)
    assert c.next_tick(6, stop, timeout=1.0) == (7, SIM_EPOCH0_S + 2.0)
    assert c.next_tick(7, stop, timeout=0.05) is None  # no newer tick: the driver does not cycle twice
    stop.set()
    assert not c.wait_until(SIM_EPOCH0_S + 9.0, stop)  # a stopping service is never stuck in a wait
    assert not WallClock().simulated and c.simulated


def test_schedule_a_tick_then_a_frame_and_tick_numbers_go_on_across_worlds():
    s = Schedule.starting(1.0, 1 / 30, 0.03)
    events, t = [], 1.0
    for _ in range(12):
        n, f = s.servo_due(t), s.frame_due(t)
        events.append((t, n, f))
        t += s.until_next(t)
    assert events[0] == (1.0, 0, True)  # both at once: the tick comes first (`bagit run` does the same)
    assert [e[1] for e in events if e[1] is not None] == list(range(len([e for e in events if e[1] is not None])))
    frames = [e[0] for e in events if e[2]]
    assert np.allclose(np.diff(frames), 1 / 30)
    assert Schedule.starting(5.0, 0.1, 0.03, ticks=s.ticks).servo_due(5.0) == s.ticks
    assert Schedule(0.1, None, 0.0, 0.0).servo_due(0.0) is None  # floating grippers: no ticks


def _ack(service: str, frame: float | None = None, **kw) -> StepAck:
    return StepAck(service=service, frame=frame, **kw)


def test_a_servo_frame_waits_for_the_whole_chain_in_any_arrival_order():
    ls = Lockstep(timeout_s=5.0)
    ls.start_run("r1")
    ls.frame_published(10.0, wall=0.0)
    assert ls.pending() == ["perception: frame 10.000"]  # the chain's first link: the coordinator answers after it
    ls.on_ack(_ack("arm-driver", cmd_seq=4), 0.01)  # the driver's receipt may overtake the controller's answer
    ls.on_ack(_ack("perception", 10.0, soi_seq=3), 0.02)  # not followed: the coordinator's answer stands for it
    assert ls.pending() == ["perception: frame 10.000"]
    ls.on_ack(_ack("planner", 10.0, soi_seq=3, stage="bagging"), 0.03)
    assert ls.pending() == ["controller: frame 10.000"]
    ls.on_ack(_ack("planner", 9.0, status_seq=4, cmd_seq=4, stage="done"), 0.05)  # another frame's: not this one's answer
    assert ls.pending() == ["controller: frame 10.000"]
    # the coordinator's answer to the tick's status stands for the controller's (the status was its answer)
    ls.on_ack(_ack("planner", 10.0, status_seq=4, cmd_seq=4, stage="done"), 0.05)
    assert ls.pending() == [] and ls.ended()


def test_a_controller_answer_on_sim_ack_still_waits_for_the_coordinators_answer_to_its_status():
    ls = Lockstep(timeout_s=5.0)
    ls.start_run("r1")
    ls.frame_published(10.0, wall=0.0)
    ls.on_ack(_ack("planner", 10.0, soi_seq=3, stage="bagging"), 0.0)
    ls.on_ack(_ack("controller", 10.0, cmd_seq=4, status_seq=4), 0.0)  # e.g. a step answered again
    assert ls.pending() == ["arm-driver: command 4", "planner: controller status 4"]
    ls.on_ack(_ack("arm-driver", cmd_seq=4), 0.0)
    ls.on_ack(_ack("planner", 10.0, status_seq=4, cmd_seq=4, stage="bagging"), 0.0)
    assert ls.pending() == [] and not ls.ended()


def test_outside_a_servo_stage_the_coordinator_ends_a_frame_and_no_run_waits_for_nothing():
    ls = Lockstep()
    ls.frame_published(1.0, wall=0.0)
    assert ls.pending() == []  # between runs the world never waits
    ls.start_run("r1")
    ls.frame_published(2.0, wall=0.0)
    ls.on_ack(_ack("planner", 2.0, stage="planning"), 0.0)  # a frame without an SOI is still answered
    assert ls.pending() == [] and not ls.ended()


def test_a_servo_tick_waits_for_the_drivers_cycle_and_its_servo_commands_to_land():
    ls = Lockstep()
    ls.start_run("r1")
    ls.servo_tick(12, {"left": 100, "right": 100}, wall=0.0)
    assert ls.pending() == ["arm-driver: servo tick 12"]
    ls.on_ack(_ack("arm-driver", tick=11, servo_sent={"left": 1, "right": 1}), 0.0)  # an old tick's answer
    assert ls.pending() == ["arm-driver: servo tick 12"]
    ls.on_ack(_ack("arm-driver", tick=12, servo_sent={"left": 1, "right": 1}), 0.0)
    ls.controllers({"left": 101, "right": 100})
    assert ls.pending() == ["right CR5: the servo command of tick 12"]
    ls.controllers({"left": 101, "right": 101})
    assert ls.pending() == []


def test_a_tick_with_a_frame_is_answered_apart_from_the_frames_chain():
    # the simulator renders and publishes the frame before the tick is answered: the world may step
    # on once the tick's ServoPs landed (`tick_pending` empty) while the frame's chain is still awaited
    ls = Lockstep()
    ls.start_run("r1")
    ls.servo_tick(40, {"left": 7, "right": 7}, wall=0.0)
    ls.frame_published(12.0, wall=0.0)
    assert ls.tick_pending() == ["arm-driver: servo tick 40"]
    assert ls.pending() == ["arm-driver: servo tick 40", "perception: frame 12.000"]
    ls.on_ack(_ack("planner", 12.0, soi_seq=9, stage="planning"), 0.0)  # the frame's chain may run ahead of the tick's answer
    ls.on_ack(_ack("arm-driver", tick=40, servo_sent={"left": 1, "right": 1}), 0.0)
    ls.controllers({"left": 8, "right": 7})
    assert ls.tick_pending() == ["right CR5: the servo command of tick 40"] == ls.pending()
    ls.controllers({"left": 8, "right": 8})
    assert ls.tick_pending() == [] == ls.pending()


def test_a_frames_silence_is_booked_to_perception_first_then_to_the_coordinator():
    ls = Lockstep(timeout_s=2.0)
    ls.start_run("r1")
    ls.frame_published(5.0, wall=10.0)
    assert ls.expire(12.5) == ["planner: frame 5.000"] and "no answer for 2 s" in ls.dropped["perception"]
    assert ls.expire(15.0) == [] and "planner" in ls.dropped  # silent again: the coordinator itself
    ls.start_run("r2")
    ls.on_alive("perception", False)  # gone: the coordinator's answer (without its SOI) is still waited for
    ls.frame_published(6.0, wall=20.0)
    assert ls.pending() == ["planner: frame 6.000"]


def test_a_service_gone_or_silent_is_dropped_for_the_run_and_said_so():
    ls = Lockstep(timeout_s=2.0)
    ls.start_run("r1")
    ls.frame_published(3.0, wall=100.0)
    ls.on_ack(_ack("planner", 3.0, soi_seq=1, stage="pre-bagging"), 100.0)
    ls.on_alive("controller", False)
    assert ls.pending() == [] and "controller" in ls.dropped and "liveliness" in ls.notes[-1]
    ls.servo_tick(1, {"left": 0, "right": 0}, wall=200.0)
    assert ls.expire(201.0) == ["arm-driver: servo tick 1"]  # not silent long enough yet
    assert ls.expire(202.5) == [] and "no answer for 2 s" in ls.dropped["arm-driver"]
    ls.start_run("r2")  # a new run waits for everyone again
    assert ls.dropped == {}


def test_schedule_keep_alive_ticks_between_frames_sparser_than_the_keep_alive_pace():
    """Frames 0.1 s apart and a keep-alive pace of 1/30 s: two keep-alive ticks after each frame (at
    +1/30 and +2/30; the third would be the next frame's), none when frames come at least that often."""
    s = Schedule.starting(1.0, 0.1, 0.03, keep_s=1 / 30)
    events, t = [], 1.0
    while t < 1.45:
        n, f = s.servo_due(t), s.frame_due(t)
        k = s.keep_due(t)
        events.append((t, n, f, k))
        t += s.until_next(t)
    frames = [e[0] for e in events if e[2]]
    keeps = [e[0] for e in events if e[3]]
    assert np.allclose(frames, [1.0, 1.1, 1.2, 1.3, 1.4])
    assert np.allclose(keeps, [1.0 + k * 0.1 + j / 30 for k in range(4) for j in (1, 2)] + [1.4 + 1 / 30])
    assert not any(e[2] and e[3] for e in events)  # never both at once
    gaps = np.diff(sorted(frames + keeps))
    assert gaps.max() < 1 / 30 + 1e-9  # the controller ticks at least every keep_s
    same = Schedule.starting(1.0, 1 / 30, 0.03, keep_s=1 / 30)
    assert same.keep_s is None  # frames at the keep-alive pace: the schedule of before, bit for bit


def test_a_keep_alive_tick_in_a_servo_stage_waits_for_the_controller_and_its_command():
    ls = Lockstep(timeout_s=5.0)
    ls.start_run("r1")
    ls.keepalive_published(10.0, 0.0)
    assert ls.pending() == []  # no frame answered yet in this run: not servoing, nothing to wait for
    ls.done_with_step()
    ls.frame_published(10.1, 0.0)
    for a in (_ack("planner", 10.1, soi_seq=1, stage="bagging"),
              _ack("arm-driver", cmd_seq=5), _ack("planner", 10.1, status_seq=5, cmd_seq=5, stage="bagging")):
        ls.on_ack(a, 0.0)
    assert ls.pending() == []
    ls.done_with_step()
    ls.keepalive_published(10.13, 0.0)
    assert ls.pending() == ["controller: frame 10.130"]
    ls.on_ack(_ack("controller", 10.13, cmd_seq=6), 0.0)
    assert ls.pending() == ["arm-driver: command 6"]
    ls.on_ack(_ack("arm-driver", cmd_seq=6), 0.0)
    assert ls.pending() == []


def test_an_answer_that_overtakes_the_announcement_of_its_step_still_counts():
    # The simulator books a step, publishes it, and a fast service's answer may be in before the booking
    # (a keep-alive's answer once beat it and the run waited 30 s for an answer already given): an answer
    # for a step later than the one booked is kept and taken up when that step is booked; older ones go.
    ls = Lockstep(timeout_s=5.0)
    ls.start_run("r1")
    ls.frame_published(10.1, 0.0)
    for a in (_ack("planner", 10.1, soi_seq=1, stage="bagging"),
              _ack("arm-driver", cmd_seq=5), _ack("planner", 10.1, status_seq=5, cmd_seq=5, stage="bagging")):
        ls.on_ack(a, 0.0)
    ls.done_with_step()
    ls.on_ack(_ack("controller", 10.1, cmd_seq=5, status_seq=5), 0.0)  # a repeat of an answered step: nothing to take up
    ls.on_ack(_ack("controller", 10.13, cmd_seq=6, run_id="r1", late="the arms' states"), 0.0)  # before its keep-alive is booked
    assert ls.inexact == ["controller answered without the arms' states"]
    ls.keepalive_published(10.13, 0.0)
    assert ls.pending() == ["arm-driver: command 6"]  # the controller's answer counted, the repeat did not
    ls.on_ack(_ack("arm-driver", cmd_seq=6), 0.0)
    assert ls.pending() == [] and len(ls.inexact) == 1 and not ls.early


def test_a_dropped_service_or_a_late_answer_makes_the_run_inexact_until_the_next_run():
    ls = Lockstep(timeout_s=5.0)
    ls.start_run("r1")
    ls.frame_published(10.0, wall=0.0)
    ls.on_ack(StepAck(service="controller", run_id="r1", frame=9.0, cmd_seq=3), wall=0.1)  # an old step's: taken as no news
    assert ls.inexact == []
    ls.on_ack(StepAck(service="planner", run_id="r1", frame=10.0, stage="bagging", late="its SOI"), wall=0.2)
    ls.on_alive("controller", False)
    assert ls.inexact == ["planner answered without its SOI", "controller no longer waited for: its liveliness token is gone"]
    ls.start_run(None)  # the run ended: why it was inexact stays for its final truth
    assert len(ls.inexact) == 2
    ls.start_run("r2")
    assert ls.inexact == [] and ls.dropped == {}


def test_sim_clock_next_event_gives_every_step_with_its_servo_tick_if_any():
    c, stop = SimClock(), threading.Event()
    assert c.next_event(0.0, stop, timeout=0.01) is None
    c.advance(1.0, servo_tick=4)
    assert c.next_event(0.0, stop, timeout=0.01) == (1.0, 4)
    c.advance(1.03)  # a frame's step, no servo tick
    assert c.next_event(1.0, stop, timeout=0.01) == (1.03, None)
    c.advance(1.03)  # heard again: no new step
    assert c.next_event(1.03, stop, timeout=0.01) is None
    woke: list[tuple[float, int | None] | None] = []
    t = threading.Thread(target=lambda: woke.append(c.next_event(1.03, stop, timeout=5.0)))
    t.start()
    c.advance(1.06, servo_tick=5)
    t.join(timeout=5.0)
    assert woke == [(1.06, 5)]


def test_sim_clock_says_which_steps_the_controller_ticks_on():
    """The arm driver publishes the arms' states only at steps the controller ticks on (a frame's, a
    keep-alive's); unknown or older steps count as such, so a state is never held back by mistake."""
    c = SimClock()
    c.advance(1.0, servo_tick=4, control_step=False)  # a servo tick alone
    assert not c.control_step_at(1.0)
    c.advance(1.0333)  # a frame's step
    assert c.control_step_at(1.0333) and c.control_step_at(1.0)  # 1.0 is no longer the newest step
    c.advance(1.06, servo_tick=5, control_step=True)  # a servo tick with a frame
    assert c.control_step_at(1.06)
    c.advance(1.09, servo_tick=6, control_step=False)
    c.advance(1.09, servo_tick=6)  # heard again: the step's kind stays
    assert not c.control_step_at(1.09)


def test_a_step_wait_ends_on_what_it_waits_for_on_stop_or_after_its_time_out():
    from bagit.common.lockstep import StepWait

    w, stop, box = StepWait(), threading.Event(), {"ready": False}
    out: list[bool] = []
    t = threading.Thread(target=lambda: out.append(w.wait(lambda: box["ready"], stop, timeout_s=30.0)))
    t.start()
    box["ready"] = True
    w.notify()  # the message it waits for arrived: it looks again at once, no polling interval
    t.join(timeout=5.0)
    assert out == [True]
    assert w.wait(lambda: False, stop, timeout_s=0.05) is False  # given up after its time-out
    stop.set()
    assert w.wait(lambda: False, stop, timeout_s=30.0) is False  # stopped: returns at once


def test_in_lockstep_the_keys_a_step_waits_on_are_reliable_and_the_rest_keep_their_qos():
    from bagit.common.bus import KEY_TABLE, BusConfig, Keys, Publisher, open_session
    from bagit.common.messages import PointCloud, RgbdFrame

    waited = {r.key for r in KEY_TABLE if r.lockstep}
    assert waited == {"camera/rgbd", "perception/soi", "perception/object", "controller/status", "arm/*/state", "run/state"}
    keys = Keys("lsqos")
    with open_session(BusConfig(rig="lsqos")) as s:  # loopback, no multicast (the BusConfig defaults)
        assert Publisher(s, keys.camera_rgbd, RgbdFrame).qos.reliability == "best_effort"
        q = Publisher(s, keys.camera_rgbd, RgbdFrame, lockstep=True).qos
        assert (q.reliability, q.congestion, q.priority) == ("reliable", "block", "data")
        assert Publisher(s, keys.perception_cloud, PointCloud, lockstep=True).qos.reliability == "best_effort"  # display only
