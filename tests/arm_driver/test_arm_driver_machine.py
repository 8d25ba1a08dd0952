"""The arm driver's supervision as a pure machine (services/arm_driver/machine.py): events in, effects out."""

import math

import pytest

from bagit.services.arm_driver import machine as m
from bagit.services.arm_driver.machine import DriverState, step


def run(events, s=None):
    """Step through `events`; the final state and every effect, in order."""
    s = s or DriverState()
    out = []
    for ev in events:
        s, eff = step(s, ev)
        out += eff
    return s, out


def running():
    s, _ = run([m.Started(), m.Restarted("ok")])
    return s


def test_start_restarts_from_the_measured_poses_and_then_streams():
    s, eff = step(DriverState(), m.Started())
    assert eff == [m.Restart(), m.Note("started", "both arms enabled")]
    assert m.mode(s, "position") == "streaming" and m.refusal(s) is None
    assert m.mode(DriverState(), "position") == "off" and m.refusal(DriverState()) == "not_running"


def test_the_estop_halts_at_once_latches_and_outranks_everything():
    s, eff = step(running(), m.EstopEngaged("operator"))
    assert eff == [m.HaltPipe(), m.Count("estops"), m.Note("estop", "operator")]
    s, _ = run([m.FaultRaised("x"), m.LinkLost("left", "gone")], s)
    assert m.blocker(s) == "estopped" and m.mode(s, "position") == "estopped"
    assert step(s, m.Cycle(10.0, False, True))[1] == []  # no restart while latched
    s, eff = step(s, m.EstopReleased())
    assert not s.estop and s.fault is None and s.needs_reset and eff == [m.Note("estop_reset", "controllers released and enabled")]
    assert step(running(), m.EstopReleased())[1] == []  # nothing latched: nothing to release


def test_an_unconfirmed_estop_is_resent_when_that_arm_reconnects():
    s, _ = run([m.EstopEngaged("op"), m.EstopSent(frozenset({"right"})), m.LinkLost("right", "reset")], running())
    s, eff = step(s, m.LinkBack("right"))
    assert eff == [m.Count("reconnects"), m.Note("reconnected", "right"), m.ResendEstop("right")]
    s2, eff = step(s, m.EstopResent("right", "refused"))
    assert s2.estop_unconfirmed == {"right"} and "still not sent" in eff[0].detail
    s3, eff = step(s, m.EstopResent("right"))
    assert s3.estop_unconfirmed == frozenset() and "re-sent" in eff[0].detail
    _, eff = step(s3, m.LinkBack("left"))
    assert m.ResendEstop("left") not in eff


def test_the_first_fault_latches_brakes_and_a_later_one_only_brakes():
    s, eff = step(running(), m.FaultRaised("left: collision"))
    assert eff == [m.Count("faults"), m.Note("fault", "left: collision"), m.StopPipe()]
    s, eff = step(s, m.FaultRaised("another"))
    assert s.fault == "left: collision" and eff == [m.StopPipe()]
    assert m.refusal(s) == "fault"
    s, eff = step(s, m.FaultCleared())
    assert s.fault is None and s.needs_reset and m.blocker(s) == "restarting"


def test_an_arm_alarm_is_counted_once_per_latched_fault():
    s, eff = step(running(), m.ArmAlarm("left", "error 22"))
    assert eff[0] == m.Count("alarms") and s.fault == "left: error 22"
    _, eff = step(s, m.ArmAlarm("left", "error 22"))
    assert m.Count("alarms") not in eff and eff == [m.StopPipe()]


def test_alarm_ids_are_asked_once_per_fault_and_added_to_its_text():
    s = running()
    assert step(s, m.AlarmsDue())[1] == []  # no fault: nothing to ask
    s, _ = step(s, m.FaultRaised("left: error"))
    s, eff = step(s, m.AlarmsDue())
    assert eff == [m.AskAlarms()]
    assert step(s, m.AlarmsDue())[1] == []  # asked already
    s, eff = step(s, m.AlarmsFound("left: 22 (collision)"))
    assert s.fault == "left: error [alarms: left: 22 (collision)]" and eff == [m.Note("alarms", "left: 22 (collision)")]
    assert step(s, m.AlarmsFound(""))[1] == []


def test_a_lost_link_brakes_marks_the_arm_stale_and_the_restart_waits_for_it():
    s, eff = step(running(), m.LinkLost("left", "feedback lost"))
    assert eff == [m.Count("links_lost"), m.Note("link_lost", "left: feedback lost"), m.ClearInFlight("left"), m.StopPipe()]
    assert not m.commandable(s, "left") and m.commandable(s, "right") and m.mode(s, "holding") == "link_down"
    s, eff = step(s, m.LinkLost("left", "again"))
    assert eff == [m.StopPipe()]  # told once
    assert step(s, m.Cycle(1.0, False, True))[1] == []  # the link is still down: no restart
    s, _ = step(s, m.LinkBack("left"))
    assert m.blocker(s) == "restarting" and not m.commandable(s, "left")  # stale until the restart
    s, _ = step(s, m.Restarted("ok"))
    assert m.commandable(s, "left") and m.blocker(s) is None


def test_the_restart_waits_for_the_arms_to_settle_or_the_settle_time_out():
    s, _ = run([m.LinkLost("left", "x"), m.LinkBack("left")], running())
    s, eff = step(s, m.Cycle(5.0, moving=True, settled=False))
    assert eff == [] and s.reset_asked == -math.inf  # still braking: not yet possible
    s, eff = step(s, m.Cycle(5.03, moving=False, settled=False))
    assert eff == [] and s.reset_asked == 5.03
    s, eff = step(s, m.Cycle(5.03 + m.SETTLE_TIMEOUT_S, moving=False, settled=False))
    assert eff == []  # exactly at the time-out: not yet
    assert step(s, m.Cycle(5.04 + m.SETTLE_TIMEOUT_S, False, False))[1] == [m.Restart()]
    assert step(s, m.Cycle(5.06, False, settled=True))[1] == [m.Restart()]


@pytest.mark.parametrize("outcome, fault", [("no_feedback", None), ("non_finite", "non-finite")])
def test_a_restart_that_cannot_start_changes_nothing_or_faults(outcome, fault):
    s, _ = step(running(), m.LinkLost("left", "x"))
    s2, eff = step(s, m.Restarted(outcome))
    assert s2.needs_reset
    assert (s2.fault is None) if fault is None else (fault in s2.fault and m.StopPipe() in eff)


def test_a_restart_outside_the_envelope_is_a_fault():
    s, _ = step(running(), m.LinkLost("left", "x"))
    s, _ = step(s, m.Restarted("ok", ("left: flange too low",)))
    assert not s.needs_reset and "outside the safety envelope: left: flange too low" in s.fault


def test_bad_servo_replies_add_up_to_a_fault_and_a_good_one_resets_the_tally():
    s = running()
    for _ in range(2):
        s, eff = step(s, m.ReplyFailed("left", "garbled", 3))
        assert eff == [m.Count("servo_failed"), m.Note("servo", "garbled")]
    s, _ = step(s, m.ReplyOk("left"))
    assert s.failed("left") == 0
    s, _ = run([m.ReplyFailed("left", "g", 3)] * 3, s)
    assert s.fault == "left: 3 motion requests in a row without a good reply (g)"


def test_a_refused_servo_is_a_fault_except_across_the_estop():
    assert step(running(), m.ReplyRejected("left: refused"))[0].fault == "left: refused"
    s, _ = step(running(), m.EstopEngaged("op"))
    assert step(s, m.ReplyRejected("left: refused")) == (s, [])


def test_closing_brakes_refuses_commands_and_stays_closed():
    s, eff = step(running(), m.Closing())
    assert eff == [m.StopPipe()] and m.refusal(s) == "not_running"
    s, eff = step(s, m.Closed())
    assert not s.started and eff == [m.Note("closed", "both arms disabled")]
    s, _ = step(s, m.Started())
    assert m.refusal(s) == "not_running"  # a driver once closed is not reopened (as before the machine)
