"""The BagIt! paper's own numbers (Tables I and II, section VII-A), to print beside ours.

Transcribed from `bagit.tex`; nothing here is measured. Planning: (successes, of, mean s, std s).
Manipulation: (successes, of). In Table II the FFG-RRT and TS-RRT rows' manipulation column is the
whole system with that planner's path; IBVS and SSVS have no planning columns.
"""

from __future__ import annotations

from bagit.common.names import PLANNER_NAMES, SERVO_CONTROLLER_NAMES

# scenario stem prefix -> the paper's name for the experiment
EXPERIMENTS: dict[str, str] = {
    "exp01": "Coffee box (Exp 1)",
    "exp02": "Canned pineapple (Exp 2)",
    "exp03": "Grapefruit (Exp 3)",
    "exp04": "Triangular prism (Exp 4)",
    "exp05": "Tea caddy (Exp 5)",
    "exp06": "Work bin, tilted (Exp 6)",
    "exp07": "Tea bucket (Exp 7)",
    "exp08": "Plastic packing (Exp 8)",
    "exp09": "Tea bucket, solid bag (Exp 9)",
    "exp10": "3D-printed cuboid (Exp 10)",
    "exp11": "Two bound, tilted (Exp 11)",
    "exp12": "Three bound, tilted (Exp 12)",
}
TABLE2_EXPERIMENTS = [f"exp{i:02d}" for i in range(1, 11)]  # the ten with numbers in Table II

PLANNERS = list(PLANNER_NAMES)  # cbirrt is the paper's "Ours"
CONTROLLERS = list(SERVO_CONTROLLER_NAMES)  # Table II's; mpc is the paper's "Ours"

# Table II, planning: experiment -> planner -> (successes, of, mean s, std s)
PLANNING: dict[str, dict[str, tuple[int, int, float, float]]] = {
    "exp01": {"ffg-rrt": (6, 10, 3.87, 1.97), "ts-rrt": (7, 10, 6.32, 1.08), "cbirrt": (9, 10, 5.13, 1.26)},
    "exp02": {"ffg-rrt": (8, 10, 2.37, 0.87), "ts-rrt": (8, 10, 5.58, 1.13), "cbirrt": (10, 10, 4.21, 0.98)},
    "exp03": {"ffg-rrt": (7, 10, 3.89, 1.18), "ts-rrt": (9, 10, 6.85, 0.56), "cbirrt": (10, 10, 4.98, 1.93)},
    "exp04": {"ffg-rrt": (6, 10, 3.58, 1.11), "ts-rrt": (7, 10, 7.32, 1.34), "cbirrt": (9, 10, 5.32, 1.56)},
    "exp05": {"ffg-rrt": (8, 10, 4.93, 1.23), "ts-rrt": (8, 10, 7.46, 0.97), "cbirrt": (10, 10, 6.16, 1.58)},
    "exp06": {"ffg-rrt": (7, 10, 3.88, 0.98), "ts-rrt": (8, 10, 6.13, 1.21), "cbirrt": (9, 10, 4.92, 0.96)},
    "exp07": {"ffg-rrt": (8, 10, 3.93, 1.06), "ts-rrt": (9, 10, 5.98, 0.72), "cbirrt": (10, 10, 5.06, 1.36)},
    "exp08": {"ffg-rrt": (7, 10, 3.67, 1.66), "ts-rrt": (7, 10, 5.96, 1.23), "cbirrt": (8, 10, 5.68, 1.29)},
    "exp09": {"ffg-rrt": (8, 10, 2.26, 0.97), "ts-rrt": (8, 10, 5.12, 0.98), "cbirrt": (9, 10, 4.06, 1.13)},
    "exp10": {"ffg-rrt": (7, 10, 3.76, 1.03), "ts-rrt": (9, 10, 5.15, 0.83), "cbirrt": (10, 10, 5.31, 1.48)},
}

# Table II, manipulation: experiment -> method -> (successes, of). Methods: controller names, and
# "mpc+ffg-rrt" / "mpc+ts-rrt" for the planner baselines' rows.
MANIPULATION: dict[str, dict[str, tuple[int, int]]] = {
    "exp01": {"mpc+ffg-rrt": (8, 8), "mpc+ts-rrt": (8, 8), "ibvs": (4, 8), "ssvs": (5, 8), "mpc": (8, 8)},
    "exp02": {"mpc+ffg-rrt": (8, 8), "mpc+ts-rrt": (8, 8), "ibvs": (7, 8), "ssvs": (7, 8), "mpc": (8, 8)},
    "exp03": {"mpc+ffg-rrt": (8, 8), "mpc+ts-rrt": (8, 8), "ibvs": (5, 8), "ssvs": (6, 8), "mpc": (8, 8)},
    "exp04": {"mpc+ffg-rrt": (8, 8), "mpc+ts-rrt": (8, 8), "ibvs": (6, 8), "ssvs": (7, 8), "mpc": (8, 8)},
    "exp05": {"mpc+ffg-rrt": (7, 8), "mpc+ts-rrt": (8, 8), "ibvs": (7, 8), "ssvs": (8, 8), "mpc": (8, 8)},
    "exp06": {"mpc+ffg-rrt": (8, 8), "mpc+ts-rrt": (8, 8), "ibvs": (7, 8), "ssvs": (7, 8), "mpc": (8, 8)},
    "exp07": {"mpc+ffg-rrt": (8, 8), "mpc+ts-rrt": (8, 8), "ibvs": (7, 8), "ssvs": (7, 8), "mpc": (8, 8)},
    "exp08": {"mpc+ffg-rrt": (6, 8), "mpc+ts-rrt": (7, 8), "ibvs": (5, 8), "ssvs": (6, 8), "mpc": (7, 8)},
    "exp09": {"mpc+ffg-rrt": (7, 8), "mpc+ts-rrt": (7, 8), "ibvs": (5, 8), "ssvs": (6, 8), "mpc": (8, 8)},
    "exp10": {"mpc+ffg-rrt": (6, 8), "mpc+ts-rrt": (7, 8), "ibvs": (6, 8), "ssvs": (6, 8), "mpc": (7, 8)},
}

# Table I (Exp. 1): method -> (successes, of, time mean s, time std s, error mean cm, error std cm)
TABLE1: dict[str, tuple[int, int, float, float, float, float]] = {
    "ShakingBot": (4, 8, 39.86, 3.74, 6.47, 1.13),
    "AutoBag": (6, 8, 32.54, 4.11, 5.36, 0.87),
    "BimaManip.": (7, 8, 44.21, 5.81, 3.50, 0.93),
    "Ours": (8, 8, 53.09, 2.92, 2.10, 0.77),
}

# Table I's methods -> the controller that runs each here (None: not built yet)
TABLE1_CONTROLLERS: dict[str, str | None] = {"ShakingBot": "shakingbot", "AutoBag": "autobag", "BimaManip.": "bimamanip", "Ours": "mpc"}

# Section VII-A: mean c1, c2 (m), c3 over 1,000 simulations of 12 shapes
SOI_STATS = {"placements": 1000, "shapes": 12, "c1": 0.826, "c2": 0.005, "c3": 0.9978}
