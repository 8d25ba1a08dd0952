"""`bagit sim`: runs the rig with its controllers for a while, reports ports and speed; bad input exits 2."""

import json

from bagit.cli import main


def test_sim_runs_for_a_duration_and_reports(capsys):
    rc = main(["sim", "exp01", "--duration", "0.3", "--speed", "50", "--no-camera", "--ephemeral-ports", "--json"])
    out = capsys.readouterr()
    assert rc == 0
    r = json.loads(out.out)
    assert r["success"] and r["scenario"] == "coffee-box" and not r["interrupted"]
    assert r["sim_s"] >= 0.3 - 1e-9 and r["frames"] == 0
    assert set(r["ports"]) == {"left", "right"} and r["robot_modes"] == {"left": 4, "right": 4}
    assert "left CR5: dashboard 127.0.0.1:" in out.err


def test_sim_renders_frames_at_the_requested_rate(capsys):
    rc = main(["sim", "exp01", "--duration", "0.2", "--speed", "50", "--fps", "10", "--ephemeral-ports", "--json"])
    r = json.loads(capsys.readouterr().out)
    assert rc == 0 and r["frames"] == 3  # at 0, 0.1 and 0.2 s


def test_sim_bad_input_exits_2(capsys):
    assert main(["sim", "no-such-scenario", "--duration", "0.1"]) == 2
    assert main(["sim", "exp01", "--speed", "0"]) == 2
    assert main(["sim", "exp01", "--duration", "-1"]) == 2
    assert "error:" in capsys.readouterr().err
