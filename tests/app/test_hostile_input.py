"""Hostile input: every file, document or flag a user can hand BagIt gets a one-line answer, never a hang.

Each case ends either in a result or in the project's own error (a BagItError / ValueError, which the
CLI prints as one line with exit status 2): never a traceback, an out-of-memory or a hang.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import signal
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from suite_support import HANG_S

from bagit.bench.probes import npy_with_header
from bagit.cli import main
from bagit.common.errors import BadScenario, BagItError
from bagit.common.scenario import MAX_SCENARIO_BYTES, MAX_SCENARIO_DEPTH, Scenario
from bagit.common.shapes import MAX_COORDINATE_M, MAX_SIZE_M
from bagit.scenarios import find_scenario

BUNDLED = sorted(Path(find_scenario("exp01")).parent.glob("*.yaml"))


def one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str], *words: str) -> str:
    """Run `bagit argv` in process; it must exit 2, not hang, with one stderr line naming `words`
    (how quickly, in CPU and wall time: `bagit bench probes`)."""
    t0 = time.monotonic()
    code = main(argv)
    elapsed = time.monotonic() - t0
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, (code, err)
    assert len(lines) == 1 and "Traceback" not in err, err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert elapsed < HANG_S, elapsed
    return lines[0]


def doc_of(name: str) -> dict:
    return yaml.safe_load(find_scenario(name).read_text())


# --- 1. coordinates and sizes are bounded where the scenario is read --------------------------------


def test_every_bundled_scenario_is_within_the_bounds():
    for path in BUNDLED:
        s = Scenario.from_file(path)
        assert np.abs(s.object.bottom_vertices()).max() <= MAX_COORDINATE_M
        assert s.object.effective_height() <= MAX_SIZE_M


@pytest.mark.parametrize("value", [1e308, -1e308, 10.5, float("inf"), float("nan")])
def test_an_object_far_away_is_refused_when_read(value, tmp_path, capsys):
    doc = doc_of("exp01")
    doc["object"]["shape"]["position"] = [value, 0.0, 0.575]
    f = tmp_path / "far.yaml"
    f.write_text(yaml.safe_dump(doc))
    for cmd in ("goal", "plan", "run"):
        one_line_error(capsys, [cmd, str(f)], "object.shape.box.position")


@pytest.mark.parametrize(
    "path, value, word",
    [
        (("object", "shape", "size"), [0.1, 0.1, 2.5], "sizes"),
        (("object", "shape", "size"), [0.1, 0.0, 0.1], "sizes"),
        (("object", "shape", "rpy"), [0.0, 0.0, 1e9], "angles"),
        (("object", "marker", "position"), [0.0, 0.0, 1e12], "position"),
        (("bag", "initial_rim", 0), [1e300, 0.0, 0.5], "within 10 m"),
        (("bag", "color"), [0.1, -1.0, 0.5], "color"),
        (("obstacles", 0, "size"), [0.1, 0.1, 1e300], "sizes"),
        (("obstacles", 0, "center"), [0.0, 11.0, 0.0], "position"),
        (("obstacles", 0, "yaw"), 1e300, "yaw"),
        (("params", "q_weight"), 1e300, "q_weight"),
        (("params", "lambda_1"), "nan", "NaN"),
    ],
)
def test_out_of_bounds_numbers_are_one_line_bad_scenarios(path, value, word):
    doc = doc_of("obstacles-a")
    node = doc
    for key in path[:-1]:
        node = node.setdefault(key, {}) if isinstance(key, str) else node[key]
    node[path[-1]] = value
    with pytest.raises(BadScenario) as e:
        Scenario.from_dict(doc)
    assert word in str(e.value) and "\n" not in str(e.value)


def test_a_bundle_spread_over_more_than_the_bound_is_refused():
    parts = [{"type": "box", "size": [0.1, 0.1, 0.1], "position": [9.0, 0.0, 0.0]}]
    doc = {"name": "x", "object": {"shape": {"type": "bundle", "parts": parts, "position": [9.0, 0.0, 0.5]}}}
    with pytest.raises(BadScenario, match="bottom outline"):
        Scenario.from_dict(doc)


# --- 2. a document too deep or too large ------------------------------------------------------------


@pytest.mark.parametrize("loader", ["CSafeLoader", "SafeLoader"])
def test_a_yaml_nested_100k_deep_is_refused(loader, monkeypatch, tmp_path, capsys):
    """libyaml and the pure-Python loader (which recurses, hence RecursionError) both end in BadScenario."""
    import bagit.common.scenario as sc

    if not hasattr(yaml, loader):
        pytest.skip(f"PyYAML built without {loader}")
    monkeypatch.setattr(sc, "_YAML_LOADER", getattr(yaml, loader))
    f = tmp_path / "deep.yaml"
    f.write_text("name: deep\nobject: " + "[" * 100_000 + "]" * 100_000 + "\n")
    one_line_error(capsys, ["goal", str(f)], str(f), "nest")  # libyaml: "maximum nesting depth"; Python: "nested too deeply"
    with pytest.raises(BadScenario, match="deep"):
        Scenario.from_text("name: x\nobject: " + "{a: " * (MAX_SCENARIO_DEPTH + 1) + "}" * (MAX_SCENARIO_DEPTH + 1))


def test_aliases_that_expand_to_a_billion_values_are_refused_before_expanding():
    lines = ["l0: &l0 [0, 0, 0, 0, 0, 0, 0, 0, 0, 0]"]
    lines += [f"l{i}: &l{i} [{', '.join([f'*l{i - 1}'] * 10)}]" for i in range(1, 9)]
    t0 = time.monotonic()
    with pytest.raises(BadScenario, match="values"):
        Scenario.from_text("\n".join(lines) + "\nname: x\nobject: {vertices: *l8}\n")
    assert time.monotonic() - t0 < HANG_S  # refused before the expansion, which would take hours


def test_a_document_that_contains_itself_is_refused():
    with pytest.raises(BadScenario, match="deep"):
        Scenario.from_text("name: x\nobject: &o {vertices: [*o]}\n")


def test_a_file_over_the_size_limit_is_not_read_whole(tmp_path):
    f = tmp_path / "big.yaml"
    f.write_text("name: big\ndescription: '" + "x" * MAX_SCENARIO_BYTES + "'\n")
    with pytest.raises(BadScenario, match="MiB"):
        Scenario.from_file(f)
    with pytest.raises(BadScenario, match="MiB"):
        Scenario.from_file("/dev/zero")


# --- 3. cloud headers are checked against the file before anything is allocated ---------------------


def ply_with_header(path: Path, n: int, fmt: str = "binary_little_endian", body: bytes = b"\0" * 24) -> Path:
    path.write_bytes(f"ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
                     f"property float z\nend_header\n".encode() + body)
    return path


def pcd_with_header(path: Path, n: int, data: str = "binary", body: bytes = b"\0" * 24) -> Path:
    path.write_bytes(f"# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\n"
                     f"HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n".encode() + body)
    return path


@pytest.mark.parametrize(
    "make, word",
    [
        (lambda d: npy_with_header(d / "huge.npy", (10**12, 3)), "over the"),
        (lambda d: npy_with_header(d / "short.npy", (1000, 3)), "need at least 24000 bytes"),
        (lambda d: npy_with_header(d / "flat.npy", (10**12,)), "shape"),
        (lambda d: npy_with_header(d / "text.npy", (10**12, 3), "<U8"), "numeric"),
        (lambda d: ply_with_header(d / "huge.ply", 10**12), "over the"),
        (lambda d: ply_with_header(d / "big.ply", 200_000_000), "over the"),
        (lambda d: ply_with_header(d / "short.ply", 1000), "need at least 12000 bytes"),
        (lambda d: ply_with_header(d / "short-ascii.ply", 1000, "ascii", b"0 0 0\n"), "need at least"),
        (lambda d: ply_with_header(d / "neg.ply", -5), "negative"),
        (lambda d: pcd_with_header(d / "huge.pcd", 10**12), "over the"),
        (lambda d: pcd_with_header(d / "short.pcd", 1000), "need at least 12000 bytes"),
        (lambda d: pcd_with_header(d / "zip.pcd", 10**7, "binary_compressed"), "need at least"),
    ],
)
def test_a_cloud_header_that_claims_too_much_is_refused_unread(make, word, tmp_path, capsys):
    from bagit.common.errors import BadCloud
    from bagit.services.perception import load_cloud

    path = make(tmp_path)
    with pytest.raises(BadCloud, match=word):
        load_cloud(path)
    one_line_error(capsys, ["extract", str(path)], str(path))


def test_clouds_within_their_headers_still_load(tmp_path):
    from bagit.services.perception import load_cloud

    np.save(tmp_path / "ok.npy", np.ones((1000, 3), np.float32))
    ply_with_header(tmp_path / "ok.ply", 2, "ascii", b"0 0 0\n1 1 1")
    pcd_with_header(tmp_path / "ok.pcd", 2, body=np.arange(6, dtype="<f4").tobytes())
    assert load_cloud(tmp_path / "ok.npy").shape == (1000, 3)
    assert np.array_equal(load_cloud(tmp_path / "ok.ply"), [[0, 0, 0], [1, 1, 1]])
    assert np.array_equal(load_cloud(tmp_path / "ok.pcd"), [[0, 1, 2], [3, 4, 5]])


# --- 4. every numeric flag refuses NaN, infinities and negatives at parse time ----------------------


def numeric_flags() -> list[tuple[str, str, object]]:
    """(command, flag, type) of every option that takes a number."""
    import argparse

    from bagit.cli import build_parser
    from bagit.commands import _args

    numeric = {_args.positive_number, _args.non_negative_number, _args.positive_seconds, _args.non_negative_seconds,
               _args.non_negative_int, _args.positive_int, _args.seed, _args.port, _args.soi_points}
    parser, _ = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    out = []
    for name, p in sub.choices.items():
        for a in p._actions:  # noqa: SLF001 - argparse has no public accessor
            if a.option_strings and a.type in numeric:
                out.append((name, a.option_strings[-1], a.type))
    return out


def test_no_flag_takes_a_bare_float_or_int():
    """`type=float` takes nan and inf, `type=int` takes -1: every number goes through bagit.commands._args."""
    import argparse

    from bagit.cli import build_parser

    parser, _ = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    bare = [(n, a.option_strings) for n, p in sub.choices.items() for a in p._actions if a.type in (int, float)]  # noqa: SLF001
    assert not bare
    assert len(numeric_flags()) >= 40


@pytest.mark.parametrize("command, flag, kind", numeric_flags())
def test_every_numeric_flag_refuses_nan_inf_and_negatives(command, flag, kind, capsys):
    for value in ("nan", "inf", "-inf", "-1", "1e999", "x"):
        line = one_line_error(capsys, [command, flag, value], flag)
        assert line.startswith(f"bagit {command}: error: argument {flag}")


@pytest.mark.parametrize("value", ["inf", "nan", "-5", "1e308", "0.001"])
def test_recorder_max_mb_is_validated_before_the_bus_opens(value, monkeypatch, capsys):
    import bagit.commands._service as service  # where the recorder opens the bus (imported here, before the patch)

    monkeypatch.setattr(service, "open_session", lambda *a, **k: pytest.fail("the recorder opened the bus"))
    one_line_error(capsys, ["recorder", "--max-mb", value, "--duration", "0.1"], "--max-mb")


def test_the_argparse_types_accept_what_they_should():
    from bagit.commands import _args

    assert _args.positive_number("2.5") == 2.5 and _args.non_negative_number("0") == 0.0
    assert _args.seed("4294967295") == 2**32 - 1 and _args.port("0") == 0 and _args.soi_points("512") == 512
    assert _args.positive_seconds("86400") == 86400.0 and _args.json_object('{"a": 1}') == {"a": 1}


# --- 5. `bagit up` refuses a bad flag before any child starts -------------------------------------


@pytest.mark.parametrize("argv, word", [(["--seed", "-1"], "--seed"), (["--seed", "1e3"], "--seed"),
                                        (["--controller", "pid"], "--controller"), (["--rig", "a b"], "--rig"),
                                        (["--timeout", "nan"], "--timeout"), (["no-such-scenario"], "no-such-scenario")])
def test_up_refuses_bad_flags_before_any_child_starts(argv, word, monkeypatch, capsys):
    import bagit.up

    monkeypatch.setattr(bagit.up.Up, "start", lambda self: pytest.fail("a child was started"))
    one_line_error(capsys, ["up", *argv], word)


# --- 6. a goal out of the arms' reach is refused before anything moves -------------------------------


def moved_scenario(dx: float = 0.0, dz: float = 0.0, name: str = "exp01") -> Scenario:
    """A bundled scenario with its object moved by (dx, 0, dz); the bag (g0) stays where it was."""
    doc = doc_of(name)
    pos = doc["object"]["shape"]["position"]
    doc["object"]["shape"]["position"] = [pos[0] + dx, pos[1], pos[2] + dz]
    return Scenario.from_dict(doc)


@pytest.mark.slow
def test_every_bundled_goal_is_within_both_arms_reach():
    from bagit.services.planner.plan import bagging_goal
    from bagit.services.planner.reach import reach_problem

    for path in BUNDLED:
        s = Scenario.from_file(path)
        goal, _ = bagging_goal(s, s.bag.g0())  # raises InfeasibleGoal otherwise
        assert reach_problem({"g†": goal.g_dagger, "g*": goal.g_star}) is None


def test_the_mounts_are_placed_where_the_simulator_clamps_the_rim():
    """The approximation: at the rim's ends along the mounts' axis, within a few cm of the simulated mounts."""
    from bagit.common.mounts import rim_frame
    from bagit.services.planner.reach import rim_mount_poses
    from bagit.services.sim.bag import bag_layout

    frame = rim_frame(np.array([0.1, 0.0, 0.5]))
    layout = bag_layout(0.68, 0.3, frame)
    poses = rim_mount_poses(layout.vertices[layout.rim])
    for a in ("left", "right"):
        assert np.linalg.norm(poses[a][:3, 3] - layout.mount_home[a][:3, 3]) < 0.03
        assert np.allclose(poses[a][:3, :3], layout.mount_home[a][:3, :3], atol=1e-9)
    assert poses["left"][1, 3] < 0 < poses["right"][1, 3]  # left at -y, as the arms stand


@pytest.mark.parametrize("dx, dz, word", [(3.0, 0.0, "workspace box"), (-1.0, 0.0, "workspace box"), (0.0, -0.5, "workspace box")])
def test_an_object_out_of_reach_is_an_infeasible_goal(dx, dz, word):
    from bagit.common.errors import InfeasibleGoal
    from bagit.services.planner.plan import bagging_goal, plan_scenario

    s = moved_scenario(dx, dz)
    with pytest.raises(InfeasibleGoal, match=f"out of the arms' reach.*{word}"):
        bagging_goal(s, s.bag.g0())
    with pytest.raises(InfeasibleGoal, match="reach"):
        plan_scenario(s)


def test_beyond_the_cr5s_reach_with_a_wide_workspace_box():
    """The box is the rig's rule; the CR5's inverse kinematics is the arm's own (0.9 m reach)."""
    from bagit.common.errors import InfeasibleGoal
    from bagit.common.rig import ARMS, RigConfig
    from bagit.services.planner.plan import bagging_goal

    rig = RigConfig()
    wide = rig.model_copy(update={"arms": {a: rig.arms[a].model_copy(update={"workspace_min": (-3.0, -3.0, -3.0),
                                                                                "workspace_max": (3.0, 3.0, 3.0)}) for a in ARMS}})
    s = moved_scenario(1.5)
    with pytest.raises(InfeasibleGoal, match="CR5 cannot reach"):
        bagging_goal(s, s.bag.g0(), wide)
    near = moved_scenario(0.1)
    bagging_goal(near, near.bag.g0(), wide)  # within reach: no error


def test_the_coordinator_fails_an_unreachable_run_at_the_goal_stage():
    from bagit.services.planner.coordinator import PlanJob, compute_plan

    s = moved_scenario(3.0)
    out = compute_plan(PlanJob("r1", s, s.bag.g0(), "cbirrt", 0, 5.0))
    assert out.failed_stage == "goal" and "out of the arms' reach" in out.reason and out.path is None


def test_the_coordinator_checks_reach_against_its_own_rig():
    """`bagit run` hosts the coordinator with the simulated rig's arms; the job carries them to compute_plan."""
    from bagit.common.messages import RunControl, SoiState
    from bagit.common.rig import ARMS, RigConfig
    from bagit.services.planner.coordinator import Coordinator, CoordinatorConfig, compute_plan

    rig = RigConfig()
    low = rig.model_copy(update={"arms": {a: rig.arms[a].model_copy(update={"workspace_max": (0.45, 0.45, 0.3)}) for a in ARMS}})
    t0 = 1000.0
    c = Coordinator(CoordinatorConfig(object_source="scenario"), now=t0, rig=low)
    for service in ("controller", "arm-driver", "perception"):
        c.on_liveliness(service, True, t0)
    assert c.start(RunControl(action="start", scenario="exp02"), t0).accepted
    (eff,) = c.on_soi(SoiState(rim=c.run.scenario.bag.g0(), source_stamp=t0 + 1.9, stamp=t0 + 1.92), t0 + 2.0)
    assert eff.job.rig is low
    out = compute_plan(eff.job)
    assert out.failed_stage == "goal" and "workspace box [-0.45, 0.45] x [-0.45, 0.45] x [0.15, 0.3] m" in out.reason


@pytest.mark.parametrize("command", ["goal", "plan", "run", "up"])
def test_the_cli_refuses_an_object_3_m_away_at_once(command, tmp_path, monkeypatch, capsys):
    import bagit.inprocess
    import bagit.up

    monkeypatch.setattr(bagit.inprocess, "run_inprocess", lambda *a, **k: pytest.fail("the run started"))
    monkeypatch.setattr(bagit.up.Up, "start", lambda self: pytest.fail("a child was started"))
    f = tmp_path / "far.yaml"
    f.write_text(moved_scenario(3.0).to_yaml())
    one_line_error(capsys, [command, str(f)], "out of the arms' reach", "workspace box")


def test_bad_run_params_are_one_line(capsys, monkeypatch):
    import bagit.inprocess

    monkeypatch.setattr(bagit.inprocess, "run_inprocess", lambda *a, **k: pytest.fail("the run started"))
    one_line_error(capsys, ["run", "exp01", "--params", '{"lambda_1": 5}'], "params.lambda_1")


# --- 7. fuzz: scenario fields, cloud headers and numeric flags --------------------------------------

FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
CLEAR_ERRORS = (BagItError, ValueError)  # what the CLI prints as one line with exit status 2


@contextlib.contextmanager
def no_hang(seconds: float = HANG_S) -> Iterator[None]:
    """Fail (instead of hanging the suite) when the body runs longer than `seconds` in Python code."""

    def alarm(*_: Any) -> None:
        raise AssertionError(f"still running after {seconds} s: a hang")

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


HOSTILE_NUMBERS = st.sampled_from([1e308, -1e308, math.inf, -math.inf, math.nan, 0, 0.0, -1, -1e-300, 1e-300, 5e-324,
                                   10**400, -(10**400), 2**63, 1e9, 10.5, 2.5, 1.5, 0.5, 999, 1000, True, "nan", "1e999"])
JUNK = st.recursive(st.none() | st.booleans() | st.text(max_size=4) | HOSTILE_NUMBERS | st.floats(),
                    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
                    max_leaves=10)
NUMBERS = st.one_of(HOSTILE_NUMBERS, st.floats(-12.0, 12.0), st.floats(-1e-3, 1e-3), st.floats(allow_nan=True, allow_infinity=True))


def _vertices_doc() -> dict:
    """exp02 with its object given as V (and a height) instead of a shape: V's numbers fuzzed directly."""
    doc = doc_of("exp02")
    obj = Scenario.from_dict(doc).object
    doc["object"] = {"vertices": obj.bottom_vertices().tolist(), "height": obj.height}
    return doc


BASES = {**{name: doc_of(name) for name in ("exp01", "exp04", "exp11", "obstacles-a")}, "vertices": _vertices_doc()}


def leaf_paths(node: Any, path: tuple = ()) -> list[tuple]:
    """Paths to every value of a document (containers included), for the fuzzer to replace."""
    out = [path] if path else []
    if isinstance(node, dict):
        for k, v in node.items():
            out += leaf_paths(v, path + (k,))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += leaf_paths(v, path + (i,))
    return out


@st.composite
def hostile_scenarios(draw: st.DrawFn) -> dict:
    """A bundled scenario with one to three of its values replaced: numbers mostly by numbers (huge, NaN,
    negative, tiny, or merely off), anything by nested junk now and then."""
    import copy

    doc = copy.deepcopy(BASES[draw(st.sampled_from(sorted(BASES)))])
    paths = leaf_paths(doc)
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(paths))
        node = doc
        try:
            for key in path[:-1]:
                node = node[key]
            numeric = isinstance(node[path[-1]], (int, float)) and not isinstance(node[path[-1]], bool)
            node[path[-1]] = draw(NUMBERS if numeric and draw(st.integers(0, 3)) else st.one_of(NUMBERS, JUNK))
        except (KeyError, IndexError, TypeError):  # an earlier replacement removed the path
            pass
    return doc


@FUZZ
@given(doc=hostile_scenarios(), as_text=st.booleans())
def test_fuzz_scenarios_load_and_make_a_goal_or_say_why(doc, as_text):
    from bagit.services.planner.plan import bagging_goal

    with no_hang():
        try:
            if as_text:
                s = Scenario.from_text(yaml.safe_dump(doc))
            else:
                s = Scenario.from_dict(doc)
        except BadScenario as e:
            assert str(e) and "\n" not in str(e), str(e)
            return
        try:
            goal, R = bagging_goal(s, s.bag.g0())
        except CLEAR_ERRORS as e:
            assert str(e).strip(), type(e)
            return
        assert np.all(np.isfinite(goal.g_dagger)) and np.all(np.isfinite(goal.g_star)) and R > 0


CLOUD_BODY = st.binary(max_size=512)
COUNTS = st.one_of(st.integers(-5, 300), st.integers(0, 10**15), st.sampled_from(["abc", "1e9", "", "-0", "99999999999999999999999"]))


@st.composite
def npy_files(draw: st.DrawFn) -> bytes:
    shape = tuple(draw(st.lists(st.integers(0, 10**13) | st.integers(0, 50), max_size=3)))
    descr = draw(st.sampled_from(["<f8", "<f4", "<i4", "|u1", "<U8", "|b1", "<c16", "|O", ">f8", "junk"]))
    header = draw(st.sampled_from([f"{{'descr': '{descr}', 'fortran_order': {draw(st.booleans())}, 'shape': {shape}, }}",
                                   draw(st.text(max_size=40))]))
    header += " " * (-(10 + len(header.encode('utf8')) + 1) % 64) + "\n"
    raw = header.encode("utf8")
    return b"\x93NUMPY\x01\x00" + len(raw).to_bytes(2, "little") + raw + draw(CLOUD_BODY)


@st.composite
def ply_files(draw: st.DrawFn) -> bytes:
    fmt = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "nonsense"]))
    kinds = st.sampled_from(["float", "double", "uchar", "int", "list uchar int", "float128", ""])
    props = "".join(f"property {draw(kinds)} {n}\n" for n in draw(st.lists(st.sampled_from("xyzw"), max_size=4)))
    elements = "".join(f"element {draw(st.sampled_from(['vertex', 'face']))} {draw(COUNTS)}\n{props}"
                       for _ in range(draw(st.integers(0, 2))))
    return f"ply\nformat {fmt} 1.0\n{elements}end_header\n".encode() + draw(CLOUD_BODY)


@st.composite
def pcd_files(draw: st.DrawFn) -> bytes:
    n = draw(COUNTS)
    lines = ["# .PCD v0.7", "VERSION 0.7", "FIELDS x y z", f"SIZE {draw(st.sampled_from(['4 4 4', '8 8 8', 'a b c', '4']))}",
             "TYPE F F F", f"COUNT {draw(st.sampled_from(['1 1 1', '2 2 2', 'x']))}", f"WIDTH {draw(COUNTS)}",
             f"HEIGHT {draw(st.sampled_from(['1', '0', '-3', '1000000']))}", "VIEWPOINT 0 0 0 1 0 0 0", f"POINTS {n}",
             f"DATA {draw(st.sampled_from(['ascii', 'binary', 'binary_compressed', 'other']))}"]
    return ("\n".join(lines) + "\n").encode() + draw(CLOUD_BODY)


@FUZZ
@given(kind=st.sampled_from([".npy", ".ply", ".pcd"]), data=st.data())
def test_fuzz_cloud_headers_load_or_say_why(kind, data, tmp_path_factory):
    from bagit.common.errors import BadCloud
    from bagit.services.perception import load_cloud

    content = data.draw({".npy": npy_files(), ".ply": ply_files(), ".pcd": pcd_files()}[kind])
    path = tmp_path_factory.mktemp("fuzz") / f"cloud{kind}"
    path.write_bytes(content)
    with no_hang():
        try:
            points = load_cloud(path)
        except BadCloud as e:
            assert str(e) and "\n" not in str(e)
            return
    assert points.ndim == 2 and points.shape[1] == 3 and len(points) <= len(content)


FLAG_TEXT = st.one_of(st.floats().map(repr), st.integers(-(10**30), 10**30).map(str), HOSTILE_NUMBERS.map(str),
                      st.text(max_size=8), st.sampled_from(["1e999", "-0", "0x10", "1_000", " 5 ", "NaN", "Infinity", "4294967296"]))


@FUZZ
@given(flag=st.sampled_from(numeric_flags()), text=FLAG_TEXT)
def test_fuzz_numeric_flags_parse_or_exit_2_with_one_line(flag, text):
    import io

    from bagit.cli import build_parser

    command, option, kind = flag
    try:
        value = kind(text)
    except argparse.ArgumentTypeError:
        value = None
    if value is not None:  # what a flag's type lets through is a finite number, never negative
        assert isinstance(value, (int, float)) and math.isfinite(value) and value >= 0
    parser, _ = build_parser()
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            parser.parse_args([command, option, text])
    except SystemExit as e:  # a refused value, or a missing positional: the same one-line form
        assert e.code == 2
        lines = err.getvalue().strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"bagit {command}: error:"), lines
        if value is None:
            assert option in lines[0]
