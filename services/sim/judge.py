"""A run judged on the simulator's ground truth: does the true rim go round the object, high enough,
without the fabric ever passing through it? For benchmarks and the hosts' results only; no service
reads it (a real rig has no ground truth).
"""

from __future__ import annotations

import cv2
import numpy as np

from bagit.common.results import RunTruth, axis_error_cm
from bagit.common.scenario import Scenario
from bagit.services.sim.objects import object_parts, object_slice


def inside_polygon(polygon2: np.ndarray, points2: np.ndarray) -> np.ndarray:
    """Which of `points2 (k, 2)` lie strictly inside the closed `polygon2 (n, 2)`."""
    poly = np.asarray(polygon2, dtype=np.float32).reshape(-1, 1, 2)
    return np.array([cv2.pointPolygonTest(poly, (float(x), float(y)), False) > 0 for x, y in points2], dtype=bool)


def judge(final_rim: np.ndarray, scenario: Scenario, lambda_d: float, up: np.ndarray) -> tuple[bool, float, str | None]:
    """Does the final rim `(m, 3)` go round the object at least lambda_d/2 above its bottom?
    Returns (enclosed, error_cm, reason); error_cm: the paper's error (`axis_error_cm`).

    Seen along the object's axis, the rim must enclose the object's cross-section at the goal's lift
    lambda_d (or at the rim's top, if it is lower). For a prism that is V itself; for a sphere or a
    tapering object it is the narrower section the rim actually lies against: a rim resting on a
    grapefruit above its equator has the widest part inside the bag yet lies inside V seen from above.
    """
    v = scenario.object.bottom_vertices()
    c = v.mean(axis=0)
    rel = final_rim - c
    height = rel @ up
    err_cm = axis_error_cm(final_rim, v, up)
    h_ref = max(min(lambda_d, float(height.max())), 0.0)
    section = object_slice(object_parts(scenario.object), c, up, h_ref)
    if len(section) == 0:  # above the object: the rim must at least go round its axis
        section = (c + h_ref * up)[None]
    # In the bottom plane's coordinates: does the rim's projection contain the section's?
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    rim2 = np.column_stack([rel @ e1, rel @ e2])
    section2 = np.column_stack([(section - c) @ e1, (section - c) @ e2])
    if not inside_polygon(rim2, section2).all():
        return False, err_cm, "the final rim does not go round the object"
    if np.median(height) < lambda_d / 2:
        return False, err_cm, f"the rim is only {np.median(height) * 100:.1f} cm above the bottom (< lambda_d/2)"
    return True, err_cm, None


def truth_of(rim: np.ndarray, passed_through: bool, max_penetration_m: float, scenario: Scenario, up: np.ndarray,
             lift_margin_cm: float | None = None, realtime_factor: float | None = None) -> RunTruth:
    """The run's verdict on the true rim `(m, 3)`: enclosed (see `judge`) and never passed through."""
    ok, err_cm, reason = judge(np.asarray(rim, dtype=float), scenario, scenario.lambda_d(), up)
    if passed_through:
        ok, reason = False, "the bag passed through the object"
    return RunTruth(success=ok, reason=reason, error_cm=round(err_cm, 4), passed_through=bool(passed_through),
                    max_penetration_mm=round(float(max_penetration_m) * 1e3, 3), lift_margin_cm=lift_margin_cm,
                    realtime_factor=realtime_factor)
