"""`bagit bench probes`: the probes themselves against a simulated CR5, a probe that breaks is a failed
row (never a stopped run), and docs/testing.md's table is the one generated from the newest record."""

from __future__ import annotations

import numpy as np
import pytest

from bagit.bench import probes
from bagit.common.results import provenance
from bagit.services.sim.cr5_sim import SimulatedCR5
from bagit.services.sim.dobot_server import DobotControllerServer
from bagit.services.sim.harness import DashboardText, FeedbackRecorder


@pytest.mark.slow
def test_the_v4_probes_pass_against_the_simulated_controller():
    """The same probe code `bagit bench probes` runs against `bagit sim`, on an in-process controller."""
    srv = DobotControllerServer(SimulatedCR5(q0=np.radians([0.0, 0.0, -90.0, 0.0, 90.0, 0.0])), dashboard_port=0, feedback_port=0,
                                step_in_background=True).start()
    rows: list[probes.ProbeRow] = []
    ctl = DashboardText(srv.dashboard_port)
    try:
        probes._v4_probes(probes.Rows("v4", rows), ctl, lambda: FeedbackRecorder(srv.feedback_port))  # noqa: SLF001
    finally:
        ctl.close()
        srv.stop()
    assert [r.id for r in rows] == [f"v4-{i}" for i in range(1, 10)]
    assert all(r.passed for r in rows), [(r.id, r.observed) for r in rows if not r.passed]


def test_a_probe_that_breaks_or_sees_nothing_is_a_failed_row():
    rows: list[probes.ProbeRow] = []
    group = probes.Rows("g", rows)
    with group.probe("boom", "it broke", "no exception") as c:
        c.check(True, "fine so far")
        raise ConnectionError("the controller closed the connection")
    with group.probe("empty", "nothing checked", "a check") as c:
        pass
    with group.probe("ok", "-", "-") as c:
        c.check(True, "fine")
    assert [(r.id, r.passed) for r in rows] == [("boom", False), ("empty", False), ("ok", True)]
    assert "ConnectionError: the controller closed the connection" in rows[0].observed


def _record(passed: bool) -> probes.ProbeRecord:
    row = probes.ProbeRow(id="x-1", group="g", finding="a | b", expected="e", observed="o", passed=passed, seconds=0.1)
    return probes.ProbeRecord(when="now", provenance=provenance(), load_avg={"before": [1.0, 1.0, 1.0], "after": [1.0, 1.0, 1.0]},
                              seconds=1.0, rows=[row])


def test_the_table_is_generated_from_a_record_and_replaces_the_doc_section():
    body = probes.table(_record(False))
    assert "0/1 probes pass" in body and "| `x-1` | a \\| b | e | o | **no** |" in body
    doc = f"# T\n\nintro\n{probes.BEGIN}\nold table\n{probes.END}\nafter\n"
    out = probes.doc_with(doc, body)
    assert out.startswith("# T\n\nintro\n") and out.endswith(f"{probes.END}\nafter\n") and "old table" not in out and body in out
    with pytest.raises(ValueError, match="no probe section"):
        probes.doc_with("# no markers\n", body)


def test_the_testing_doc_and_probes_md_show_the_newest_record_with_every_row_passing():
    """The published table is generated from the record, never typed: both copies are what the newest
    record in bench/results/probes.jsonl generates, and every row of it passes."""
    rec = probes.last_record()
    body = probes.table(rec)
    doc = probes.DOC.read_text(encoding="utf-8")
    assert probes.doc_with(doc, body) == doc
    assert probes.TABLE.read_text(encoding="utf-8").endswith(body)
    assert {r.id.split("-")[0] for r in rec.rows} == {"v4", "cli", "rec", "arm"}
    assert all(r.passed for r in rec.rows), [(r.id, r.observed) for r in rec.rows if not r.passed]
