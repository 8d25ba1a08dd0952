"""`bench.rerun`'s selectors: which records of a file a re-run picks."""

from bagit.bench.rerun import WHERE


def test_harness_picks_the_runs_the_harness_lost_and_no_failure_of_the_method():
    lost = {"success": False, "stage_reached": "idle", "reason": "timed out: no result within 900 s of wall time"}
    crashed = {"success": False, "stage_reached": "idle", "reason": "crashed: signal 9"}
    control = {"success": False, "stage_reached": "bagging", "reason": "time limit of 40 s reached in bagging"}
    bagged = {"success": True, "stage_reached": "done", "reason": None}
    assert [WHERE["harness"](r) for r in (lost, crashed, control, bagged)] == [True, True, False, False]
