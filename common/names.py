"""The enumerations every part shares: run stages, controller, planner and arm names.

Defined once here and imported everywhere (the CLI's choices, the coordinator's checks, the
controller's registry, the benchmark's sweeps), so adding a name is one change.
"""

from __future__ import annotations

from typing import Literal, get_args

Stage = Literal["idle", "perceiving", "goal", "planning", "pre-bagging", "bagging", "done", "failed", "aborted"]
STAGES: tuple[str, ...] = get_args(Stage)
ACTIVE_STAGES: tuple[str, ...] = ("perceiving", "goal", "planning", "pre-bagging", "bagging")
SERVO_STAGES: tuple[str, ...] = ("pre-bagging", "bagging")  # the controller moves the arms
PERCEIVE_STAGES: tuple[str, ...] = ("perceiving", "goal")  # the object's marker is still looked for
FINAL_STAGES: tuple[str, ...] = ("done", "failed", "aborted")
FAILED_STAGES: tuple[str, ...] = ("failed", "aborted")  # final, without success
# What a controller tick did (`ControllerStatus.mode`): explored J, servoed, settled still at g†, held, or finished.
ServoMode = Literal["explore", "servo", "settle", "hold", "done"]

# The planner's refusal of a start in lockstep before the simulator's first sim/clock tick (the run would start
# at 0 and time out at that tick, 2**30 s on); `bagit up` asks again while it gets this one.
NO_SIM_CLOCK_YET = "the simulator's clock has not ticked yet"

# Who may release the e-stop (EStop(engage=False) with this `source`): the operator's own tools, the
# dashboard and the CLI. An engage is taken from anyone. On the secure rig these are also the only
# identities the router lets put on `estop` (deploy/secure/zenoh-router-secure.json5).
ESTOP_SOURCE_DASHBOARD = "dashboard"
ESTOP_SOURCE_CLI = "cli"
ESTOP_RELEASE_SOURCES: tuple[str, ...] = (ESTOP_SOURCE_DASHBOARD, ESTOP_SOURCE_CLI)

# mpc is the paper's; ibvs and ssvs its shape-servoing baselines (Table II), autobag and shakingbot the
# action-primitive methods it compares with (Table I), bimamanip the learned-dynamics MPC of Table I
ControllerName = Literal["mpc", "ibvs", "ssvs", "autobag", "shakingbot", "bimamanip"]
CONTROLLER_NAMES: tuple[str, ...] = get_args(ControllerName)
SERVO_CONTROLLER_NAMES: tuple[str, ...] = ("mpc", "ibvs", "ssvs")  # those that servo the SOI along the planned path
PRIMITIVE_CONTROLLER_NAMES: tuple[str, ...] = ("autobag", "shakingbot")  # look-act state machines over primitives
LEARNED_CONTROLLER_NAMES: tuple[str, ...] = ("bimamanip",)  # MPC through a model learned in the simulator (the `learn` extra)
DEFAULT_CONTROLLER: ControllerName = "mpc"

PlannerName = Literal["cbirrt", "ffg-rrt", "ts-rrt"]  # cbirrt is the paper's
PLANNER_NAMES: tuple[str, ...] = get_args(PlannerName)
DEFAULT_PLANNER: PlannerName = "cbirrt"

# What moves the bag's mounts in a simulated run: the two CR5s through the arm driver's motion rules
# (the rig as deployed), or floating grippers that take each increment at once (an ablation).
ArmsMode = Literal["cr5", "ideal"]
ARMS_MODES: tuple[str, ...] = get_args(ArmsMode)

# How many points an SOI may have (a scenario's bag.n_x, perception's n_x, `--n-x`): at least 4 to
# outline a rim, at most 512 (the paper uses 32; every stage's cost grows with it).
MIN_N_X = 4
MAX_N_X = 512

# The services of a rig (each one's liveliness token is alive/<name>), and those a lockstep
# simulator waits for: it steps on only when each has answered the last frame or servo tick.
ServiceName = Literal["sim", "perception", "planner", "controller", "arm-driver", "dashboard", "recorder"]
SERVICE_NAMES: tuple[str, ...] = get_args(ServiceName)
LOCKSTEP_SERVICES: tuple[ServiceName, ...] = ("perception", "planner", "controller", "arm-driver")

# What bounds a search is its iterations (`params.planner.max_iterations`): the same plan or the same failure on any
# machine. The wall clock only guards against a hang, far past what those iterations take (4000 of a
# hard search: 16 s on a lightly loaded 2-core EPYC); a 10 s budget failed such runs only when the
# machine was busy, so a run's plan depended on the load.
PLAN_WALL_GUARD_S = 300.0
# A simulated run's servoing limit (`bagit run`, `bagit up` in lockstep), on the simulated clock: runs take 10-30 s.
SIM_TIME_LIMIT_S = 40.0
