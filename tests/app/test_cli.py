"""The `bagit` command line: one entry point, --json everywhere, one-line errors."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from suite_support import ROOT

from bagit.cli import COMMAND_MODULES, build_parser, main


def run_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "bagit.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.processes
def test_help_lists_every_subcommand():
    res = run_cli("--help")
    assert res.returncode == 0
    _, modules = build_parser()
    assert len(modules) == len(COMMAND_MODULES)
    for name in modules:
        assert name in res.stdout


def test_every_subcommand_takes_json():
    parser, modules = build_parser()
    for name in modules:
        sub = parser._subparsers._group_actions[0].choices[name]  # noqa: SLF001 - argparse has no public accessor
        assert any("--json" in a.option_strings for a in sub._actions), name


@pytest.mark.slow
@pytest.mark.processes
def test_bad_input_is_one_line_error_without_traceback(tmp_path):
    res = run_cli("extract", str(tmp_path / "missing.ply"), "--n-x", "32")
    assert res.returncode == 2
    assert "Traceback" not in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "error" in res.stderr
    bad = tmp_path / "nan.npy"
    np.save(bad, np.full((100, 3), np.nan))
    res = run_cli("extract", str(bad), "--n-x", "32")
    assert res.returncode == 2 and "Traceback" not in res.stderr


def test_extract_json_output(tmp_path, capsys):
    t = np.linspace(0, 2 * np.pi, 3000, endpoint=False)
    rng = np.random.default_rng(0)
    cloud = np.stack([0.12 * np.cos(t), 0.09 * np.sin(t), 0.4 + 0 * t], axis=1) + rng.normal(0, 0.001, (3000, 3))
    f = tmp_path / "c.npy"
    np.save(f, cloud)
    assert main(["extract", str(f), "--n-x", "16", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    soi = np.asarray(out["soi"])
    assert soi.shape == (16, 3)
    r = np.hypot(soi[:, 0] / 0.12, soi[:, 1] / 0.09)
    assert np.all(np.abs(r - 1) < 0.05)


@pytest.mark.processes
def test_no_command_prints_help():
    res = run_cli()
    assert res.returncode == 2 and "usage" in res.stdout.lower()


def test_demo_sample_extracts_from_the_bundled_cloud(capsys):
    assert main(["demo", "--sample", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert np.asarray(out["soi"]).shape == (32, 3) and out["n_points"] == 12000


def test_goal_and_plan_commands(capsys):
    assert main(["goal", "exp04", "--json"]) == 0
    g = json.loads(capsys.readouterr().out)
    assert g["c1"] <= 0.912 and np.asarray(g["g_star"]).shape == (32, 3)
    assert main(["goal", "exp01"]) == 0  # the coffee box has a principal axis: C3 gives way to the bag's opening
    assert "oriented like the bag's opening" in capsys.readouterr().out
    assert main(["plan", "exp04", "--seed", "2", "--json"]) == 0
    p = json.loads(capsys.readouterr().out)
    assert p["success"] and len(p["path"]) == p["n_nodes"] and 0 < p["dagger_index"] < p["n_nodes"]
    for key in ("time_s", "iterations"):
        assert key in p


@pytest.mark.processes
def test_too_large_object_exits_2_with_the_needed_perimeter(tmp_path):
    doc = tmp_path / "big.yaml"
    doc.write_text("name: big\nobject: {shape: {type: box, size: [0.4, 0.3, 0.1], position: [0, 0, 0.5]}}\nbag: {rim_perimeter: 0.68}\n")
    res = run_cli("goal", str(doc))
    assert res.returncode == 2 and "at least" in res.stderr and "Traceback" not in res.stderr


def test_the_service_example_configs_load():
    """deploy/{perception,controller,arm-driver}.yaml validate against the services' config models."""
    import argparse

    from bagit.commands._service import load_service_config
    from bagit.common.errors import BagItError
    from bagit.services.arm_driver.config import ArmDriverServiceConfig
    from bagit.services.controller.node import ControllerServiceConfig
    from bagit.services.perception.node import PerceptionServiceConfig

    deploy = ROOT / "deploy"
    args = argparse.Namespace(rig="lab")
    p, bus = load_service_config(PerceptionServiceConfig, deploy / "perception.yaml", {"n_x": 24}, args)
    assert p.source.kind == "realsense" and p.n_x == 24 and bus.rig == "lab"
    c, _ = load_service_config(ControllerServiceConfig, deploy / "controller.yaml", {"soi_max_age_s": 0.4}, args)
    assert c.soi_max_age_s == 0.4 and c.rig_config == "rig.yaml"
    a, _ = load_service_config(ArmDriverServiceConfig, deploy / "arm-driver.yaml", {"driver": {"servo_command": "servoj"}}, args)
    assert a.driver.servo_command == "servoj" and a.driver.feedback_timeout_s == 0.2 and a.rig_config == "rig.yaml"
    with pytest.raises(BagItError, match="soi_max_age_s"):
        load_service_config(ControllerServiceConfig, deploy / "controller.yaml", {"soi_max_age_s": -1}, args)


def test_planner_run_time_limit_is_validated(capsys, tmp_path):
    """`bagit up` lengthens the coordinator's wall-clock limit for a simulator that may run slowly."""
    assert main(["planner", "--run-time-limit", "-3", "--duration", "1"]) == 2  # refused by the flag's type
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--run-time-limit" in err[0] and "> 0" in err[0]
    assert main(["planner", "--run-time-limit", "5000", "--duration", "1"]) == 2  # the coordinator's own bound
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--run-time-limit" in err[0] and "less than or equal to 3600" in err[0]
    from bagit.up import Up, UpOptions

    up = Up(UpOptions(run_time_limit_s=400.0, workdir=tmp_path))
    assert up._argv("planner", Path("z.json5"), Path("rig.yaml"))[:3] == ["planner", "--run-time-limit", "400"]


def test_the_controller_reads_the_watchdog_from_the_rig_config_and_refuses_the_settings_that_moved(tmp_path, capsys):
    """The watchdog is the rig's (`safety.watchdog_s`, what the arm driver enforces), given to the
    controller by the same rig config as the driver's (`bagit up` passes both); the controller, its
    parameters and the control rate are the run's: a config or a flag setting one is refused, naming
    where it is now."""
    import argparse

    from bagit.commands._service import load_service_config, service_rig
    from bagit.common.errors import BagItError
    from bagit.common.rig import RigConfig, SafetyLimits
    from bagit.services.controller.node import ControllerServiceConfig
    from bagit.up import Up, UpOptions

    rig = RigConfig(safety=SafetyLimits(watchdog_s=0.3))
    (tmp_path / "rig.yaml").write_text(rig.to_yaml())
    (tmp_path / "controller.yaml").write_text("rig_config: rig.yaml\n")  # relative to the file
    args = argparse.Namespace(rig="lab")
    cfg, _ = load_service_config(ControllerServiceConfig, tmp_path / "controller.yaml", {}, args)
    assert service_rig(cfg.rig_config, None, str(tmp_path / "controller.yaml")).safety.watchdog_s == 0.3
    up = Up(UpOptions(workdir=tmp_path))
    zpath, rpath = up._write_configs()
    argv = up._argv("controller", zpath, rpath)
    assert argv[argv.index("--rig-config") + 1] == str(rpath)

    for key, where in [("control_rate_hz", "the run's parameter control_rate_hz"), ("driver_watchdog_s", "the rig config's safety.watchdog_s"),
                       ("controller", "the run's choice"), ("params", "the run's parameters")]:
        (tmp_path / "old.yaml").write_text(f"{key}: null\n")
        with pytest.raises(BagItError, match=f"{key} is no longer a controller setting: it is {where}"):
            load_service_config(ControllerServiceConfig, tmp_path / "old.yaml", {}, args)
    for flag, where in [("--rate", "control_rate_hz"), ("--controller", "the run's choice")]:
        assert main(["controller", flag, "15", "--duration", "1"]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and flag in err[0] and where in err[0], err


def test_the_camera_rate_is_the_runs_control_rate_in_lockstep_unless_given(tmp_path):
    """`bagit up` leaves the camera rate to the simulator, which in lockstep takes each run's control rate
    (its params, as `bagit run` does: a frame per control tick) and WALL_FPS on the wall clock."""
    from bagit.services.sim.rig_sim import WALL_FPS, camera_fps
    from bagit.up import Up, UpOptions

    assert camera_fps(None, True, 15.0) == 15.0 and camera_fps(None, False, 15.0) == WALL_FPS and camera_fps(20.0, True, 15.0) == 20.0
    up = Up(UpOptions(workdir=tmp_path))
    zpath, rpath = up._write_configs()
    assert "--fps" not in up._argv("sim", zpath, rpath)
    argv = Up(UpOptions(workdir=tmp_path, fps=12.0))._argv("sim", zpath, rpath)
    assert argv[argv.index("--fps") + 1] == "12"


def test_beside_the_simulator_every_service_runs_on_every_cpu_but_the_first_and_the_flag_turns_it_off():
    """`bagit up`: the simulator keeps the first CPU to itself (its main thread is a lockstep run's critical path)
    and runs on all of them; without a simulator among the children, or on one CPU, nobody is confined."""
    import argparse

    from bagit.commands.up import add_arguments, options
    from bagit.up import SERVICES, child_cpus

    names = SERVICES
    assert child_cpus("sim", names, {0, 1}) is None
    assert all(child_cpus(n, names, {0, 1}) == {1} for n in names if n != "sim")
    assert child_cpus("recorder", (*names, "recorder"), {4, 2, 7}) == {4, 7}  # bagit up's own CPUs, whichever they are
    assert child_cpus("perception", ("perception", "planner"), {0, 1}) is None  # no simulator: a real rig's services
    assert child_cpus("perception", names, {3}) is None  # one CPU: nothing to keep
    p = argparse.ArgumentParser()
    add_arguments(p)
    assert options(p.parse_args(["exp02"])).sim_core is True
    assert options(p.parse_args(["exp02", "--shared-cores"])).sim_core is False


def test_up_gives_the_arm_driver_link_timeouts_for_simulated_controllers(tmp_path):
    """`bagit up` drives simulated CR5s that share the CPU: its arm driver waits longer for their
    feedback and replies than the defaults for a real CR5, and every motion limit stays the rig's."""
    import argparse

    from bagit.commands._service import load_service_config
    from bagit.services.arm_driver.config import ArmDriverServiceConfig, DriverConfig
    from bagit.up import SIM_DRIVER_TIMEOUTS, Up, UpOptions

    up = Up(UpOptions(workdir=tmp_path))
    zpath, rpath = up._write_configs()
    argv = up._argv("arm-driver", zpath, rpath)
    cfg_path = Path(argv[argv.index("--config") + 1])
    assert argv[argv.index("--rig-config") + 1] == str(rpath)
    cfg, _ = load_service_config(ArmDriverServiceConfig, cfg_path, {"rig_config": str(rpath)}, argparse.Namespace(rig="sim"))
    default = DriverConfig()
    assert cfg.driver.feedback_timeout_s == SIM_DRIVER_TIMEOUTS["feedback_timeout_s"] > default.feedback_timeout_s
    assert cfg.driver.reply_timeout_s == SIM_DRIVER_TIMEOUTS["reply_timeout_s"] > default.reply_timeout_s
    assert cfg.driver.model_copy(update={k: getattr(default, k) for k in SIM_DRIVER_TIMEOUTS}) == default  # nothing else


@pytest.mark.slow
def test_demo_runs_a_whole_bagging_through_bagit_run(capsys):
    """`bagit demo` is `bagit run exp02` with its defaults: the CR5s, mpc, cbirrt, seed 0."""
    from bagit.common.results import RunResult

    code = main(["demo", "--json"])
    r = RunResult.model_validate(json.loads(capsys.readouterr().out))
    assert (r.scenario, r.controller, r.planner, r.seed, r.arms) == ("exp02-canned-pineapple", "mpc", "cbirrt", 0, "cr5")
    assert code == 0 and r.success, r.reason
    # the canned pineapple, end to end from camera frames, judged on the simulator's ground truth
    assert r.stage_reached == "done" and r.truth is not None and not r.truth.passed_through
    assert r.error_cm is not None and r.error_cm < 2.0 and r.duration_s < 40.0
    # the true rim went round V with room to spare when the lift from g† began (cm)
    assert r.lift_margin_cm is not None and r.lift_margin_cm > 1.0, r.lift_margin_cm
