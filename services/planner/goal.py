"""The bagging SOI g† and the goal SOI g* (paper section V).

Bottom frame F_m: origin at V's centroid, z normal to V's plane (taken upward, the paper's sgn
rule), x along V's principal axis. The bagging ellipse minimises (L - R)^2 under C1 (every vertex
inside with F_e <= lambda_1), C2 (centre within lambda_2 of the centroid) and C3 (major axis
parallel to V's principal axis, |d_e . d_v| >= lambda_3; dropped when V has no principal axis).

The minimum (L = R exactly) is reached in closed form: the smallest centred, axis-aligned ellipse
holding V under C1 is found over its aspect ratio (a 1-D search), then scaled up about its centre
until its Ramanujan perimeter equals R; scaling up only lowers F_e, and the centre and axis stay,
so C1-C3 hold. Only when that ellipse is already longer than R are the centre (C2) and the angle
(C3) let move too, to find the true shortest ellipse; if even that is longer than R the bag is too
small, and InfeasibleGoal names the rim perimeter that would do. The achieved c2 is therefore 0
whenever the centred ellipse fits, which is the safest choice for C1's margin.

That ellipse is one of a whole family of minimisers (every centred ellipse of perimeter R holding V
under C1 has L = R). With the bag's opening g0 known and `dagger_shape: bag` (the default), the
bagging ellipse is instead the member closest in shape to g0's own opening (Frobenius distance of
the shape matrices) that keeps `dagger_margin_share` of the tight ellipse's margin round V, and the
bag's orientation takes C3's place: the paper asks the opening to stay close to Q0's, and a bag
held by two clamps folds when its opening is stretched across them (see `bag_ellipse`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import minimize, minimize_scalar
from scipy.spatial import ConvexHull, QhullError

from bagit.common.errors import BadVertices, InfeasibleGoal
from bagit.common.geometry import (
    align_cyclic,
    as_points,
    ellipse_points_2d,
    farthest_point_sampling,
    make_transform,
    pca,
    ramanujan_perimeter,
    transform_points,
)
from bagit.common.messages import EllipseParams, Goal
from bagit.common.params import DEFAULT_LAMBDA_D_M, MethodParams

N_ELLIPSE = 720  # n_e: dense ellipse samples before farthest point sampling
ISOTROPY_RATIO = 1.08  # principal variances closer than this: no principal axis, C3 is dropped
MAX_ASPECT = 8.0
MAX_BAG_ASPECT = 2.5  # the bag-shaped opening is searched up to this aspect ratio


@dataclass
class BaggingGoal:
    """g† and g* with the ellipse they came from. g_dagger, g_star: (n_x, 3) world; frame: (4, 4) world <- F_m."""

    g_dagger: np.ndarray
    g_star: np.ndarray
    frame: np.ndarray
    ellipse: EllipseParams
    perimeter: float
    c1: float
    c2: float
    c3: float
    c3_applied: bool
    lambda_d: float
    vertices: np.ndarray = field(repr=False)
    dagger_depth: float = 0.0  # g† lies this far below V's plane (m); g* lies lambda_d above it
    # what set the ellipse's orientation: 'axis' (V's principal axis, C3), 'bag' (the bag's own opening,
    # `dagger_shape: bag`) or 'none' (V has no principal axis)
    oriented_by: str = "axis"

    @property
    def up(self) -> np.ndarray:
        """The object's upward axis a_z (after the sgn rule), world frame."""
        return self.frame[:3, 2]

    def to_message(self, run_id: str | None = None, object_height: float = 0.0) -> Goal:
        return Goal(
            run_id=run_id,
            g_dagger=self.g_dagger,
            g_star=self.g_star,
            frame=self.frame,
            ellipse=self.ellipse,
            perimeter=self.perimeter,
            c1=self.c1,
            c2=self.c2,
            c3=self.c3,
            vertices=self.vertices,
            object_height=object_height,
        )


def validate_vertices(vertices: object) -> np.ndarray:
    """V as a finite `(n_v, 3)` float array spanning a plane, or BadVertices."""
    v = as_points(vertices, BadVertices, "vertices")
    if len(v) < 3:
        raise BadVertices(f"need at least 3 vertices for a bottom outline, got {len(v)}")
    if not np.all(np.isfinite(v)):
        raise BadVertices("vertices contain NaN or infinite coordinates")
    _, var, _ = pca(v)
    if var[1] < 1e-8:
        raise BadVertices("vertices are collinear or coincident: they outline no bottom face")
    if np.sqrt(var[2]) > 0.05 * np.sqrt(var[0]) + 1e-3:
        raise BadVertices("vertices are not coplanar: V must be the outline of a flat bottom")
    return v


def bottom_frame(vertices: np.ndarray) -> np.ndarray:
    """4x4 world <- F_m: origin at the centroid, z normal to V (upward), x along V's principal axis."""
    centroid, _, axes = pca(vertices)
    z = axes[2] if axes[2][2] >= 0 else -axes[2]  # sgn(a_z . b_z): the object's side is up
    x = axes[0] - np.dot(axes[0], z) * z
    x /= np.linalg.norm(x)
    return make_transform(np.column_stack([x, np.cross(z, x), z]), centroid)


def _f_e(xy: np.ndarray, center: np.ndarray, a: np.ndarray | float, b: np.ndarray | float, alpha: np.ndarray | float) -> np.ndarray:
    """F_e of points `xy (n, 2)` for the ellipse (centre, a, b, alpha): < 1 inside."""
    c, s = np.cos(alpha), np.sin(alpha)
    d = xy - center
    xr = d[:, 0] * c + d[:, 1] * s
    yr = -d[:, 0] * s + d[:, 1] * c
    return (xr / a) ** 2 + (yr / b) ** 2


def _tight(xy: np.ndarray, q: float, lambda_1: float) -> tuple[float, float]:
    """Semi-axes (a, b = a/q) of the smallest centred, x-aligned ellipse with F_e <= lambda_1 on `xy`."""
    a = np.sqrt(np.max(xy[:, 0] ** 2 + (q * xy[:, 1]) ** 2) / lambda_1)
    return float(a), float(a / q)


def smallest_ellipse(xy: np.ndarray, lambda_1: float) -> tuple[float, float, float]:
    """(a, b, L) of the shortest centred, x-aligned ellipse holding `xy (n, 2)` under C1."""

    def perim(log_q: float) -> float:
        return float(ramanujan_perimeter(*_tight(xy, np.exp(log_q), lambda_1)))

    res = minimize_scalar(perim, bounds=(0.0, np.log(MAX_ASPECT)), method="bounded", options={"xatol": 1e-4})
    best_q = np.exp(res.x) if res.fun <= perim(0.0) else 1.0
    a, b = _tight(xy, best_q, lambda_1)
    if b > a:  # keep a the major semi-axis
        a, b = b, a
    return a, b, float(ramanujan_perimeter(a, b))


def smallest_ellipse_moved(
    xy: np.ndarray, lambda_1: float, lambda_2: float, max_angle: float | None
) -> tuple[np.ndarray, float, float, float, float]:
    """(centre, a, b, alpha, L) of the shortest ellipse holding `xy (n, 2)` under C1 whose centre may move
    within lambda_2 (C2) and whose major axis may turn by up to `max_angle` from x (C3; None: free).

    Only needed when the centred ellipse is too long for the bag: the move can save a few millimetres
    of perimeter, and InfeasibleGoal must name the true smallest perimeter. Nelder-Mead over
    (centre, angle, log aspect), each squashed into its bounds by tanh, so every trial is feasible.
    """
    span = np.pi / 2 if max_angle is None else max_angle * (1 - 1e-9)
    radius = lambda_2 * (1 - 1e-9)  # strictly inside the bounds despite rounding
    log_qmax = np.log(MAX_ASPECT)

    def unpack(z: np.ndarray) -> tuple[np.ndarray, float, float]:
        r = np.hypot(z[0], z[1])
        centre = np.zeros(2) if r < 1e-12 else z[:2] * (radius * np.tanh(r) / r)
        alpha = span * np.tanh(z[2])
        q = np.exp(0.5 * log_qmax * (1 + np.tanh(z[3])))
        return centre, float(alpha), float(q)

    def perim(z: np.ndarray) -> float:
        centre, alpha, q = unpack(z)
        c, s = np.cos(alpha), np.sin(alpha)
        d = xy - centre
        local = np.column_stack([d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c])
        return float(ramanujan_perimeter(*_tight(local, q, lambda_1)))

    a0, b0, _ = smallest_ellipse(xy, lambda_1)
    z_q = np.arctanh(np.clip(2 * np.log(max(a0 / b0, 1.0)) / log_qmax - 1, -0.999, 0.999))
    best = None
    for start in ([0.0, 0.0, 0.0, z_q], [0.3, 0.0, 0.0, z_q], [0.0, 0.3, 0.0, z_q], [0.0, 0.0, 0.3, z_q]):
        res = minimize(perim, np.array(start), method="Nelder-Mead", options={"xatol": 1e-5, "fatol": 1e-7, "maxiter": 800})
        if best is None or res.fun < best.fun:
            best = res
    if best is None:
        raise AssertionError("no Nelder-Mead start was tried")
    centre, alpha, q = unpack(best.x)
    c, s = np.cos(alpha), np.sin(alpha)
    d = xy - centre
    a, b = _tight(np.column_stack([d[:, 0] * c + d[:, 1] * s, -d[:, 0] * s + d[:, 1] * c]), q, lambda_1)
    return centre, a, b, alpha, float(ramanujan_perimeter(a, b))


def shape_matrix(a: np.ndarray | float, b: np.ndarray | float, alpha: np.ndarray | float) -> np.ndarray:
    """M `(..., 2, 2)` = R(alpha) diag(a, b) R(alpha)ᵀ: the centred ellipse is M applied to the unit circle,
    so |M1 - M2| (Frobenius) measures how far apart two ellipses' shapes are."""
    a, b, alpha = np.broadcast_arrays(np.asarray(a, float), np.asarray(b, float), np.asarray(alpha, float))
    c, s = np.cos(alpha), np.sin(alpha)
    m11 = a * c**2 + b * s**2
    m22 = a * s**2 + b * c**2
    m12 = (a - b) * c * s
    return np.stack([np.stack([m11, m12], -1), np.stack([m12, m22], -1)], -2)


def opening_shape(points_xy: np.ndarray) -> np.ndarray:
    """M `(2, 2)` of the ellipse that fits the closed rim `points_xy (n >= 5, 2)` best (OpenCV's direct
    least-squares conic fit, exact for points on an ellipse however they are spaced)."""
    p = np.asarray(points_xy, dtype=float)
    while len(p) < 5:  # the fit needs five points: add the midpoints of the sides
        p = np.stack([p, 0.5 * (p + np.roll(p, -1, axis=0))], axis=1).reshape(-1, 2)
    (_, _), (w, h), angle = cv2.fitEllipse(p.astype(np.float32).reshape(-1, 1, 2))
    return shape_matrix(w / 2, h / 2, np.radians(angle))


def signed_margins(xy: np.ndarray, a: np.ndarray, b: np.ndarray, alpha: np.ndarray, n: int = 256) -> np.ndarray:
    """`(k,)`: for each of k centred ellipses (a, b, alpha: `(k,)`), the smallest signed distance (> 0
    inside) of `xy (m, 2)` to its outline, from n outline samples."""
    th = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    pts = ellipse_points_2d(np.zeros(2), a[:, None], b[:, None], alpha[:, None], th)  # (k, n, 2)
    d = np.linalg.norm(pts[:, :, None, :] - xy[None, None], axis=-1).min(axis=1)  # (k, m)
    inside = _f_e(xy, np.zeros(2), a[:, None], b[:, None], alpha[:, None]) < 1.0
    return np.where(inside, d, -d).min(axis=1)


def bag_ellipse(
    xy: np.ndarray, perimeter: float, lambda_1: float, g0_xy: np.ndarray, reference: tuple[float, float, float], margin_share: float
) -> tuple[float, float, float]:
    """(a, b, alpha) of the centred ellipse of the given perimeter, closest in shape to the bag's own
    opening `g0_xy (n, 2)`, that holds `xy (m, 2)` under C1 and keeps at least `margin_share` of the
    margin round it that the `reference` ellipse (a, b, alpha) has.

    Why: every centred ellipse of perimeter R holding V under C1 minimises the paper's |L - R|², and
    of them the bag takes the one nearest its own opening with the least folding. Its mounts clamp
    stretches of the rim, so an opening stretched across the mounts' axis (the paper's C3 for an
    object lying across them) or squeezed round must bow the free fabric between the clamps outwards,
    and it buckled inwards under the object as often (traced in the simulator)."""
    try:
        opening = opening_shape(g0_xy)
    except cv2.error:  # no ellipse through g0 (all its points on a line): nothing to stay close to
        return reference
    if not np.all(np.isfinite(opening)):
        return reference
    hull = xy
    if len(xy) > 3:
        try:
            hull = xy[ConvexHull(xy).vertices]  # F_e and the margin are extreme at the hull's corners
        except QhullError:
            pass
    alphas = np.radians(np.arange(0.0, 180.0, 1.0))
    qs = np.exp(np.linspace(0.0, np.log(MAX_BAG_ASPECT), 81))
    A, Q = (g.ravel() for g in np.meshgrid(alphas, qs, indexing="ij"))
    b = perimeter / np.asarray(ramanujan_perimeter(Q, 1.0))  # (an array: Q is one)
    a = Q * b
    fits = _f_e(hull, np.zeros(2), a[:, None], b[:, None], A[:, None]).max(axis=1) <= lambda_1
    distance = np.linalg.norm(shape_matrix(a, b, A) - opening, axis=(-2, -1))
    ref_a, ref_b, ref_alpha = reference
    need = margin_share * float(signed_margins(hull, np.array([ref_a]), np.array([ref_b]), np.array([ref_alpha]))[0])
    order = np.flatnonzero(fits)[np.argsort(distance[fits], kind="stable")]
    for start in range(0, len(order), 64):  # nearest first; the first batch nearly always holds one
        k = order[start : start + 64]
        ok = np.flatnonzero(signed_margins(hull, a[k], b[k], A[k]) >= need)
        if len(ok):
            i = k[ok[0]]
            return float(a[i]), float(b[i]), float(A[i])
    return reference


def bagging_soi(
    vertices: np.ndarray,
    rim_perimeter: float,
    n_x: int,
    params: MethodParams | None = None,
    *,
    lambda_d: float | None = None,
    g0: np.ndarray | None = None,
) -> BaggingGoal:
    """g† and g* for an object with bottom outline `vertices (n_v, 3)` and a bag of rim perimeter R.

    `lambda_d` defaults to the parameter, else DEFAULT_LAMBDA_D_M; with `g0 (n_x, 3)` the points of
    g† and g* are indexed like g0's (best cyclic shift and direction).
    """
    p = params or MethodParams()
    v = validate_vertices(vertices)
    if not (np.isfinite(rim_perimeter) and rim_perimeter > 0):
        raise BadVertices(f"rim perimeter must be positive, got {rim_perimeter}")
    if n_x < 4:
        raise BadVertices(f"n_x must be at least 4, got {n_x}")
    T = bottom_frame(v)
    T_inv = np.linalg.inv(T)  # not invert_transform: the closed loop is sensitive at the float level
    xy = transform_points(T_inv, v)[:, :2]
    _, var, _ = pca(xy)
    c3_applied = var[0] > ISOTROPY_RATIO * var[1]
    oriented_by = "axis" if c3_applied else "none"

    centre = np.zeros(2)
    alpha = 0.0
    a, b, L_min = smallest_ellipse(xy, p.goal.lambda_1)
    moved = L_min > rim_perimeter
    if moved:  # the centred, parallel ellipse is too long: use C2's and C3's slack
        max_angle = float(np.arccos(p.goal.lambda_3)) if c3_applied else None
        centre, a, b, alpha, L_min = smallest_ellipse_moved(xy, p.goal.lambda_1, p.goal.lambda_2, max_angle)
    if L_min > rim_perimeter:
        needed = np.ceil(L_min * 1000) / 1000
        raise InfeasibleGoal(
            f"the object is too large for the bag: no ellipse of perimeter {rim_perimeter:.3f} m holds its "
            f"bottom under C1-C3; the rim perimeter would have to be at least {needed:.3f} m"
        )
    k = rim_perimeter / L_min  # scaling about the centre only lowers F_e and keeps C2 and C3
    a, b = a * k, b * k
    if alpha == 0.0 and not c3_applied:
        # no principal axis to follow: turn the ellipse by 90 degrees if that holds V better
        if _f_e(xy, centre, a, b, np.pi / 2).max() < _f_e(xy, centre, a, b, 0.0).max() - 1e-9:
            alpha = np.pi / 2
    if p.goal.experimental.dagger_shape == "bag" and g0 is not None and not moved:
        g0_xy = transform_points(T_inv, np.asarray(g0, dtype=float))[:, :2]
        a, b, alpha = bag_ellipse(xy, rim_perimeter, p.goal.lambda_1, g0_xy, (a, b, alpha), p.goal.experimental.dagger_margin_share)
        c3_applied, oriented_by = False, "bag"  # the bag's own opening sets the orientation, not V's axis
    c1 = float(_f_e(xy, centre, a, b, alpha).max())
    if c1 > p.goal.lambda_1 + 1e-9:
        raise InfeasibleGoal(f"internal: the bagging ellipse breaks C1 (max F_e {c1:.3f} > {p.goal.lambda_1})")
    # d_e: the major axis (a >= b); d_v: V's principal axis, F_m's x by construction
    c3 = float(abs(np.cos(alpha)))  # |d_e . d_v| with d_v = (1, 0)
    if c3_applied and c3 < p.goal.lambda_3 - 1e-12:
        raise InfeasibleGoal(f"internal: the bagging ellipse breaks C3 (|d_e . d_v| = {c3:.4f})")

    theta = np.linspace(0.0, 2 * np.pi, N_ELLIPSE, endpoint=False)
    dense = ellipse_points_2d(centre, a, b, alpha, theta)
    idx = farthest_point_sampling(dense, n_x)
    ring = dense[np.sort(idx)]  # FPS picks the points; sorting by theta orders them counter-clockwise

    g_dagger = transform_points(T, np.column_stack([ring, np.full(n_x, -p.goal.experimental.dagger_depth_m)]))
    if g0 is not None:
        g_dagger = align_cyclic(g_dagger, np.asarray(g0, dtype=float))
    ld = lambda_d if lambda_d is not None else (p.goal.lambda_d if p.goal.lambda_d is not None else DEFAULT_LAMBDA_D_M)
    g_star = g_dagger + (p.goal.experimental.dagger_depth_m + ld) * T[:3, 2]  # eq. (11) with a_z already turned upward
    return BaggingGoal(
        g_dagger=g_dagger,
        g_star=g_star,
        frame=T,
        ellipse=EllipseParams(center=(float(centre[0]), float(centre[1])), a=a, b=b, alpha=alpha),
        perimeter=float(ramanujan_perimeter(a, b)),
        c1=c1,
        c2=float(np.hypot(*centre)),
        c3=c3,
        c3_applied=bool(c3_applied),
        lambda_d=ld,
        oriented_by=oriented_by,
        vertices=v,
        dagger_depth=p.goal.experimental.dagger_depth_m,
    )
