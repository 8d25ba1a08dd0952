"""The rim as a smooth closed curve through the fitted means, and equally spaced points on it.

A periodic cubic spline through the chain of means (parametrised by chord length) is sampled
densely; arc length along the samples places the SOI points at equal spacing from any phase.
Hidden stretches are bridged first (polar_fill), and a warm start's phase follows the last SOI
(following_phase).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline, CubicSpline, splrep

from bagit.services.perception.ring import plane_basis

SAMPLES_PER_MEAN = 16


@dataclass(frozen=True)
class ClosedCurve:
    """Dense samples of a closed curve. points: (m, 3); arc: (m + 1,) arc length at each sample and
    back at the start (arc[-1] is the curve's length)."""

    points: np.ndarray
    arc: np.ndarray

    @property
    def length(self) -> float:
        return float(self.arc[-1])

    @classmethod
    def through(cls, mu: np.ndarray, keep: np.ndarray | None = None) -> ClosedCurve:
        """The periodic cubic spline through the closed chain `mu (k, 3)`, in chain order.

        With `keep (k,)`, only the kept means are knots; each run of dropped ones (a hidden
        stretch) becomes one spline interval whose parameter length is the length of the circular
        arc that leaves and enters the gap along the rim's tangents there. Chord length would be
        too short across a curved gap, and the spline would cut across it.
        """
        k = len(mu)
        idx = np.arange(k) if keep is None or keep.all() else np.flatnonzero(keep)
        knots = mu[idx]
        closed = np.vstack([knots, knots[:1]])
        seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
        if len(idx) < k:
            nxt = np.roll(idx, -1)
            for g in np.flatnonzero((nxt - idx) % k > 1):
                seg[g] = _gap_arc_length(knots, int(g), seg[g])
        t = np.concatenate([[0.0], np.cumsum(np.maximum(seg, 1e-9))])
        spline = CubicSpline(t, closed, bc_type="periodic")
        pts = spline(np.linspace(0.0, t[-1], k * SAMPLES_PER_MEAN, endpoint=False))
        step = np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1)
        return cls(points=pts, arc=np.concatenate([[0.0], np.cumsum(step)]))

    def at(self, s: np.ndarray) -> np.ndarray:
        """Points `(len(s), 3)` at arc lengths `s (m,)` (taken modulo the length), linear between samples."""
        s = np.mod(np.asarray(s, dtype=float), self.length)
        i = np.clip(np.searchsorted(self.arc, s, side="right") - 1, 0, len(self.points) - 1)
        step = self.arc[i + 1] - self.arc[i]
        frac = (s - self.arc[i]) / np.where(step > 0, step, 1.0)
        nxt = self.points[(i + 1) % len(self.points)]
        return self.points[i] + frac[:, None] * (nxt - self.points[i])

    def arc_of(self, q: np.ndarray) -> np.ndarray:
        """Arc length `(n,)` of the curve sample nearest each of `q (n, 3)`."""
        d2 = np.einsum("ij,ij->i", self.points, self.points)[None] - 2.0 * (q @ self.points.T)  # + |q|^2, same per row
        return self.arc[np.argmin(d2, axis=1)]

    def even(self, n: int, phase: float = 0.0) -> np.ndarray:
        """n points `(n, 3)` at equal arc length along the curve, the first at arc length `phase`."""
        return self.at(phase + np.arange(n) * (self.length / n))


def _gap_arc_length(knots: np.ndarray, g: int, chord: float) -> float:
    """Estimated rim length across the gap from knot g to knot g + 1 of the closed `knots (m, 3)`.

    The rim's directions on entering and leaving the gap (from two knots either side) make angles
    a and b with the chord; a circular arc turning by a + b over the chord c has length
    c * h / sin(h), h = (a + b) / 2.
    """
    m = len(knots)
    chord_v = knots[(g + 1) % m] - knots[g]
    t_in = knots[g] - knots[(g - 1) % m]
    t_out = knots[(g + 2) % m] - knots[(g + 1) % m]

    def angle(u: np.ndarray, v: np.ndarray) -> float:
        nu, nv = np.linalg.norm(u), np.linalg.norm(v)
        if nu <= 0 or nv <= 0:
            return 0.0
        return float(np.arccos(np.clip(u @ v / (nu * nv), -1.0, 1.0)))

    h = min(0.5 * (angle(t_in, chord_v) + angle(chord_v, t_out)), 1.3)
    return chord * (h / np.sin(h) if h > 1e-6 else 1.0)


HARMONICS = 3  # Fourier order of 1 / r^2 in the polar rim model that bridges hidden stretches
HEIGHT_NOISE_M = 3e-4  # the knots' height noise (a component averages ~40 points of 2 mm depth noise)
RIDGE = 1e-4  # smoothing of the polar model, growing as order^4 (a periodic smoothing spline in effect)


def _fourier(angle: np.ndarray, order: int) -> np.ndarray:
    """Design matrix `(n, 2 * order + 1)`: 1, cos(j a), sin(j a) for j = 1..order."""
    j = np.arange(1, order + 1)
    return np.hstack([np.ones((len(angle), 1)), np.cos(np.outer(angle, j)), np.sin(np.outer(angle, j))])


def _fit_fourier(angle: np.ndarray, values: np.ndarray, order: int) -> np.ndarray:
    """Coefficients `(2 * order + 1, d)` of the smoothed Fourier fit of `values (n, d)` against `angle (n,)`."""
    A = _fourier(angle, order)
    j = np.arange(1, order + 1, dtype=float)
    penalty = np.concatenate([[0.0], j**4, j**4]) * RIDGE * len(angle)
    return np.linalg.solve(A.T @ A + np.diag(penalty), A.T @ values)


def polar_fill(mu: np.ndarray, keep: np.ndarray, normal: np.ndarray, per_gap_mean: int = 3) -> np.ndarray | None:
    """Knots `(m, 3)` in chain order: the kept means of `mu (k, 3)`, with each run of dropped ones (a
    hidden stretch) replaced by points of a polar model of the rim fitted to the kept ones.

    The model, about the rim centre in the plane of `normal`: 1 / r^2 as a low-order Fourier series
    of the angle, and the height as a (periodic) smoothing spline of the angle. 1 / r^2 of an
    ellipse is exactly a second-order series, whatever its aspect, orientation or small centre
    error, so a hidden tip of a long ellipse is restored where any spline across the gap would cut
    across or overshoot it; pinched rims are close to it. The height of sagging and wavy rims is
    not low-order in the angle (a global fit overshoots across a gap by centimetres); the local
    spline follows the heights on either side, and its light smoothing keeps the knots' noise from
    tilting the bridge. The model's misfit at the gap's two ends is blended linearly across the
    gap, so the bridge leaves and rejoins the seen rim without a step. Returns None when the kept
    means do not turn once monotonically about the centre (not star-shaped) or the model is not a
    closed curve there (the caller then bridges with the arc-length spline).
    """
    idx = np.flatnonzero(keep)
    if len(idx) < 2 * HARMONICS + 2:
        return None
    c = mu.mean(axis=0)
    ex, ey = plane_basis(normal)
    rel = mu[idx] - c
    u, v, h = rel @ ex, rel @ ey, rel @ normal
    phi = np.arctan2(v, u)
    r = np.hypot(u, v)
    step = np.angle(np.exp(1j * np.diff(np.concatenate([phi, phi[:1]]))))
    sign = 1.0 if step.sum() > 0 else -1.0
    if np.any(step * sign <= 0) or abs(abs(step.sum()) - 2 * np.pi) > 1e-6 or np.any(r <= 0):
        return None
    a = sign * phi[0] + np.concatenate([[0.0], np.cumsum(sign * step)[:-1]])  # sign * unwrapped angle: increasing
    coef = _fit_fourier(a, (1.0 / r**2)[:, None], HARMONICS)
    # FITPACK's periodic smoothing spline, smoothed down to the knots' noise level.
    with warnings.catch_warnings():  # FITPACK warns when it cannot reach s exactly (rims far off bag size)
        warnings.simplefilter("ignore", RuntimeWarning)
        a_closed, h_closed = np.concatenate([a, [a[0] + 2 * np.pi]]), np.concatenate([h, h[:1]])
        tck = splrep(a_closed, h_closed, s=len(a) * HEIGHT_NOISE_M**2, per=True)
    height = BSpline(*tck, extrapolate="periodic")

    def model(angle: np.ndarray) -> np.ndarray | None:  # (n,) -> (n, 2): radius, height
        f = _fourier(angle, HARMONICS) @ coef
        return None if np.any(f[:, 0] <= 0) else np.column_stack([1.0 / np.sqrt(f[:, 0]), height(angle)])

    at_knots = model(a)
    if at_knots is None:
        return None
    misfit = np.column_stack([r, h]) - at_knots
    k, m = len(mu), len(idx)
    runs = (np.roll(idx, -1) - idx) % k - 1  # dropped means after each kept one
    gaps = np.flatnonzero(runs > 0)
    pieces = np.split(mu[idx], gaps + 1)  # kept knots up to and including each gap's start
    out = [pieces[0]]
    for g, after in zip(gaps, pieces[1:], strict=False):
        g1 = (g + 1) % m
        a1 = a[g1] + (2 * np.pi if g1 == 0 else 0.0)
        frac = np.linspace(0.0, 1.0, per_gap_mean * runs[g] + 4)[1:-1]
        ang = a[g] + frac * (a1 - a[g])
        val = model(ang)
        if val is None:
            return None
        val += (1 - frac)[:, None] * misfit[g] + frac[:, None] * misfit[g1]
        p = sign * ang
        out += [c + val[:, :1] * (np.cos(p)[:, None] * ex + np.sin(p)[:, None] * ey) + val[:, 1:] * normal, after]
    return np.vstack(out)


def following_phase(curve: ClosedCurve, previous: np.ndarray) -> float:
    """The phase of len(previous) evenly spaced points on `curve` that keeps each near its previous self.

    previous: (n, 3) the last SOI, in the curve's direction. Tangential motion of a rim is not
    observable in a cloud, so each point should move as little as it can: point i's wanted arc
    position is where previous[i] projects onto the curve, and point 0's phase is the circular
    mean of those minus i * L / n (no creeping round the rim frame after frame).
    """
    n = len(previous)
    L = curve.length
    offset = 2.0 * np.pi * (curve.arc_of(previous) - np.arange(n) * (L / n)) / L
    return float(np.mod(np.angle(np.mean(np.exp(1j * offset))) / (2.0 * np.pi) * L, L))
