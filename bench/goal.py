"""Bagging-SOI statistics over random placements of twelve bottom shapes (the paper's 1,000 simulations).

    python -m bagit.bench.goal [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bagit.bench.common import stats_ms
from bagit.common.errors import InfeasibleGoal
from bagit.common.geometry import rpy_to_matrix
from bagit.services.planner import bagging_soi

PAPER = {"c1": 0.826, "c2": 0.005, "c3": 0.9978}
R = 0.68


def _circle(r: float, n: int = 24) -> np.ndarray:
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([r * np.cos(t), r * np.sin(t)], 1)


def _poly(n: int, r: float) -> np.ndarray:
    return _circle(r, n)


def _rect(w: float, h: float) -> np.ndarray:
    return np.array([[w, h], [-w, h], [-w, -h], [w, -h]]) / 2


def shapes() -> dict[str, np.ndarray]:
    """Twelve bottom outlines (2-D, metres), sized like the paper's objects."""
    return {
        "square": _rect(0.09, 0.09),
        "rectangle": _rect(0.12, 0.08),
        "long-rectangle": _rect(0.16, 0.06),
        "circle": _circle(0.045),
        "large-circle": _circle(0.065),
        "ellipse": _circle(1.0) * [0.07, 0.045],
        "triangle": _poly(3, 0.07),
        "right-triangle": np.array([[0.0, 0.0], [0.11, 0.0], [0.0, 0.08]]) - [0.037, 0.027],
        "pentagon": _poly(5, 0.06),
        "hexagon": _poly(6, 0.06),
        "two-bound": np.vstack([_circle(0.035, 16) + [0.036, 0], _circle(0.035, 16) - [0.036, 0]]),
        "l-shape": np.array([[0, 0], [0.12, 0], [0.12, 0.04], [0.04, 0.04], [0.04, 0.10], [0, 0.10]]) - [0.05, 0.04],
    }


def run(quick: bool = False) -> dict:
    n = 120 if quick else 1000
    rng = np.random.default_rng(0)
    outlines = shapes()
    names = list(outlines)
    c1, c2, c3, times = [], [], [], []
    valid = 0
    for k in range(n):
        xy = outlines[names[k % len(names)]]
        rpy = [rng.uniform(-0.35, 0.35), rng.uniform(-0.35, 0.35), rng.uniform(-np.pi, np.pi)]  # tilts up to 20 deg
        v = np.column_stack([xy, np.zeros(len(xy))]) @ rpy_to_matrix(rpy).T + rng.uniform([-0.1, -0.1, 0.4], [0.1, 0.1, 0.6])
        t0 = time.perf_counter()
        try:
            g = bagging_soi(v, R, 32)
        except InfeasibleGoal:
            continue
        times.append((time.perf_counter() - t0) * 1e3)
        valid += 1
        c1.append(g.c1)
        c2.append(g.c2)
        if g.c3_applied:  # C3 means nothing for a disc or a regular polygon
            c3.append(g.c3)
    return {
        "placements": n,
        "shapes": len(names),
        "valid_share": valid / n,
        "mean_c1": float(np.mean(c1)),
        "mean_c2": float(np.mean(c2)),
        "mean_c3": float(np.mean(c3)),
        "c3_applied_share": len(c3) / max(valid, 1),
        "paper": PAPER,
        "time": stats_ms(times),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    r = run(ap.parse_args().quick)
    print(f"{r['placements']} placements of {r['shapes']} shapes: {r['valid_share']:.1%} valid goals")
    print(f"mean c1 {r['mean_c1']:.3f} (paper {PAPER['c1']}), c2 {r['mean_c2']:.4f} m (paper {PAPER['c2']}), "
          f"c3 {r['mean_c3']:.4f} (paper {PAPER['c3']}; over the {r['c3_applied_share']:.0%} with a principal axis)")
    t = r["time"]
    print(f"time per goal: median {t['median_ms']:.2f} ms, p95 {t['p95_ms']:.2f} ms, min {t['min_ms']:.2f} ms")


if __name__ == "__main__":
    main()
