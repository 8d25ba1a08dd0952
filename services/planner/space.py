"""The SOI state space the planners search: sampling, the paper's ellipse regularisation (C4, C5),
the perimeter constraint, steering and edge checks. States are rims `(n_x, 3)` whose point i means
the same place on the rim in every state.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bagit.common.errors import NumericalFailure
from bagit.common.geometry import align_cyclic, closed_polyline_length, ramanujan_perimeter
from bagit.services.planner.collision import RimCollision

EDGE_RESOLUTION_M = 0.01  # collision-check an edge every this much point motion
MAX_NODE_STEP_M = 0.05  # no rim point moves more than this between consecutive path nodes


FIT_OVERSAMPLE = 3  # n_y = this * n_x ellipse points in the Chamfer fit
FIT_ROUNDS = 6  # nearest-assignment / reweighting rounds
FIT_MIN_DIST_M = 1e-4  # IRLS weights 1 / max(d, this)
SAMPLE_TRIES = 5  # fresh draws when one cannot be regularised


def fit_ellipse_pca(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form start: centre `(3,)` and axes `A (3, 2)` of the ellipse c + A [cos t, sin t] through
    `x (n, 3)` taken in order, t_i = 2 pi i / n (a linear least-squares fit)."""
    n = len(x)
    if n < 3 or not np.all(np.isfinite(x)):
        raise NumericalFailure(f"ellipse fit needs at least 3 finite rim points, got {n} (finite: {bool(np.all(np.isfinite(x)))})")
    t = 2 * np.pi * np.arange(n) / n
    B = np.column_stack([np.ones(n), np.cos(t), np.sin(t)])  # (n, 3)
    try:
        W = np.linalg.lstsq(B, x, rcond=None)[0].T  # (3, 3): [c, a_1, a_2]
    except np.linalg.LinAlgError as e:
        raise NumericalFailure(f"ellipse fit failed: {e}") from None
    return W[:, 0], W[:, 1:]


def fit_ellipse(
    x: np.ndarray, centre_limit: float | None = None, rounds: int = FIT_ROUNDS, oversample: int = FIT_OVERSAMPLE
) -> tuple[np.ndarray, np.ndarray]:
    """Centre `(3,)` and axes `A (3, 2)` of the ellipse Y = {c + A [cos t_j, sin t_j]} (n_y = oversample * n
    points) minimising the symmetric Chamfer distance CD(Y, x) to `x (n, 3)` (eq. 13), with C5
    (||c - centroid(x)|| <= centre_limit) as a hard constraint.

    Y is linear in W = [c, A], so with the nearest-neighbour pairs of both Chamfer terms held fixed the
    weighted squared error is a 3x3 linear solve; weights 1/d (IRLS) make it the Chamfer sum of plain
    distances. Alternating pairs and solves never raises the objective much and converges in a few
    rounds; it needs no generic optimiser, which keeps the planner's inner loop fast.
    """
    n = len(x)
    c, A = fit_ellipse_pca(x)
    cbar = x.mean(axis=0)
    m = oversample * n
    t = 2 * np.pi * np.arange(m) / m
    B = np.column_stack([np.ones(m), np.cos(t), np.sin(t)])  # (m, 3)
    W = np.column_stack([c, A])
    for _ in range(rounds):
        y = B @ W.T  # (m, 3)
        d2 = ((x[:, None, :] - y[None, :, :]) ** 2).sum(-1)  # (n, m)
        j_of_x = d2.argmin(axis=1)  # x_i -> nearest y
        i_of_y = d2.argmin(axis=0)  # y_j -> nearest x
        w_x = 1.0 / (n * np.maximum(np.sqrt(d2[np.arange(n), j_of_x]), FIT_MIN_DIST_M))
        w_y = 1.0 / (m * np.maximum(np.sqrt(d2[i_of_y, np.arange(m)]), FIT_MIN_DIST_M))
        # pairs (target point, basis row, weight) of both Chamfer directions
        P = np.vstack([x, x[i_of_y]])
        Bp = np.vstack([B[j_of_x], B])
        w = np.concatenate([w_x, w_y])[:, None]
        try:
            W = np.linalg.solve((Bp * w).T @ Bp + 1e-12 * np.eye(3), (Bp * w).T @ P).T
        except np.linalg.LinAlgError as e:
            raise NumericalFailure(f"Chamfer ellipse fit failed: {e}") from None
        if centre_limit is not None and np.linalg.norm(W[:, 0] - cbar) > centre_limit:
            off = W[:, 0] - cbar
            c = cbar + off * (centre_limit / np.linalg.norm(off))  # C5 active: centre on its bound
            Ba = Bp[:, 1:]
            try:
                A = np.linalg.solve((Ba * w).T @ Ba + 1e-12 * np.eye(2), (Ba * w).T @ (P - c)).T
            except np.linalg.LinAlgError as e:
                raise NumericalFailure(f"Chamfer ellipse fit (C5 active) failed: {e}") from None
            W = np.column_stack([c, A])
    if not np.all(np.isfinite(W)):
        raise NumericalFailure("the ellipse fit is not finite")
    return W[:, 0], W[:, 1:]


def ellipse_rim(c: np.ndarray, A: np.ndarray, n: int, phase: float = 0.0) -> np.ndarray:
    """`(n, 3)` points c + A [cos t_i, sin t_i], t_i = phase + 2 pi i / n."""
    t = phase + 2 * np.pi * np.arange(n) / n
    return c + np.column_stack([np.cos(t), np.sin(t)]) @ A.T


def scale_to_perimeter(rim: np.ndarray, perimeter: float) -> np.ndarray:
    """`rim (n, 3)` scaled about its centroid so its polyline length is `perimeter` (the constraint projection)."""
    c = rim.mean(axis=0)
    return c + (rim - c) * (perimeter / closed_polyline_length(rim))


def regularize(x_rand: np.ndarray, lambda_4: float, lambda_5: float) -> np.ndarray:
    """The paper's Regularization (eq. 13-15): the ellipse `(n, 3)` nearest `x_rand (n, 3)` in Chamfer
    distance under C4 (|R_x / R_y - 1| <= lambda_4) and C5 (centre within lambda_5 of x_rand's centroid).

    C5 is kept inside the fit; C4 by scaling the fitted ellipse about its centre, only as far as the
    nearer bound of C4 (the least change to the Chamfer optimum), so it holds exactly.
    """
    n = len(x_rand)
    c, A = fit_ellipse(x_rand, lambda_5)
    y = ellipse_rim(c, A, n)
    r_x, r_y = closed_polyline_length(x_rand), closed_polyline_length(y)
    if not r_y > 1e-9:
        raise NumericalFailure("the regularised ellipse collapsed to a point")
    ratio = r_x / r_y
    if abs(ratio - 1) > lambda_4:
        target = r_x / (1 + np.clip(ratio - 1, -lambda_4, lambda_4))  # R_y on C4's nearer bound
        y = c + (y - c) * (target / r_y)
    return y


def max_step(a: np.ndarray, b: np.ndarray) -> float:
    """Largest single-point displacement between two rims."""
    return float(np.linalg.norm(a - b, axis=-1).max())


@dataclass
class SoiSpace:
    """Everything a planner needs to know about valid rims."""

    perimeter: float
    collision: RimCollision
    rng: np.random.Generator
    center_lo: np.ndarray
    center_hi: np.ndarray
    up: np.ndarray
    lambda_4: float = 0.002
    lambda_5: float = 0.021
    perimeter_tol: float = 0.05
    step_m: float = 0.03
    max_tilt_rad: float = 0.6

    def perimeter_ok(self, rims: np.ndarray) -> np.ndarray:
        p = np.linalg.norm(np.roll(rims, -1, axis=-2) - rims, axis=-1).sum(axis=-1)
        return np.abs(p / self.perimeter - 1) <= self.perimeter_tol

    def project(self, rim: np.ndarray) -> np.ndarray:
        """Onto the perimeter constraint, when it is broken."""
        return rim if self.perimeter_ok(rim) else scale_to_perimeter(rim, self.perimeter)

    def valid(self, rim: np.ndarray) -> bool:
        return bool(self.perimeter_ok(rim) and not self.collision.rims_hit(rim[None])[0])

    def sample(self, n: int) -> np.ndarray:
        """A random regularised SOI: a random ellipse of about the bag's perimeter, with a tilt,
        centred in the task region, perturbed point by point, then regularised to an ellipse."""
        rng = self.rng
        c = rng.uniform(self.center_lo, self.center_hi)
        tilt = rng.uniform(0, self.max_tilt_rad)
        az = rng.uniform(0, 2 * np.pi)
        normal = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
        normal = normal if self.up @ normal > 0 else -normal
        e1 = np.cross(normal, [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(normal, e1)
        ang = rng.uniform(0, np.pi)
        u, v = np.cos(ang) * e1 + np.sin(ang) * e2, -np.sin(ang) * e1 + np.cos(ang) * e2
        q = rng.uniform(1.0, 2.5)
        scale = self.perimeter * rng.uniform(0.98, 1.02) / ramanujan_perimeter(1.0, 1.0 / q)
        A = np.column_stack([u * scale, v * scale / q])
        x_rand = ellipse_rim(c, A, n, rng.uniform(0, 2 * np.pi)) + rng.normal(0, 0.003, (n, 3))
        return regularize(x_rand, self.lambda_4, self.lambda_5)

    def sample_regularized(self, n: int, tries: int = SAMPLE_TRIES) -> np.ndarray:
        """`sample`, drawing again when the regularisation fails numerically on a degenerate draw."""
        last: Exception | None = None
        for _ in range(tries):
            try:
                return self.sample(n)
            except NumericalFailure as e:
                last = e
        raise NumericalFailure(f"{tries} samples in a row could not be regularised: {last}")

    def steer(self, frm: np.ndarray, to: np.ndarray, step: float | None = None) -> np.ndarray:
        """From `frm` towards `to` (aligned first) by at most `step` of any point's motion, projected."""
        to = align_cyclic(to, frm)
        d = max_step(frm, to)
        s = step or self.step_m
        x = to if d <= s else frm + (to - frm) * (s / d)
        return self.project(x)

    def edge_ok(self, a: np.ndarray, b: np.ndarray) -> bool:
        """The straight SOI motion a -> b stays valid: every interpolated rim checked at 1 cm resolution."""
        d = max_step(a, b)
        k = max(int(np.ceil(d / EDGE_RESOLUTION_M)), 1)
        s = np.linspace(0.0, 1.0, k + 1)[1:, None, None]
        rims = a[None] + s * (b - a)[None]
        bad = ~self.perimeter_ok(rims)
        if bad.any():
            rims[bad] = np.stack([scale_to_perimeter(r, self.perimeter) for r in rims[bad]])
        return not self.collision.rims_hit(rims).any()
