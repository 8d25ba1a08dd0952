"""SOI extraction: the bag rim as n_x ordered points, by EM on a Gaussian mixture with a uniform outlier term.

The paper (section IV, eq. 48) treats the rim cloud as samples from n_x Gaussians whose means are
the SOI points, plus a uniform component for outliers. The steps here:

1. clean-up (cleanup.py): thin huge clouds, drop scattered outliers (grid-cell counts), voxel
   down-sample so uneven density does not pull the mixture;
2. a cold start orders the cloud around the rim (ring.py) and spaces the components evenly along
   it; a warm start begins from the previous SOI and only looks near it;
3. EM (em.py) with a uniform outlier term and a bending prior on the closed chain of means, which
   keeps the components in order and evenly spaced and carries the ones behind a gripper along a
   smooth continuation of the rim;
4. starved components (no points: a hidden stretch) and strays (off the smooth curve through their
   neighbours, e.g. caught by an outlier clump) are replaced by the bending interpolation of the
   good ones, so no SOI point sits on an outlier or inside a gap;
5. the SOI is n_x points at equal arc length along a periodic spline through the means (curve.py);
   a hidden stretch is bridged in polar form (restores a hidden tip of an ellipse) or by the spline
   alone, and a warm start takes the bridge that keeps the last rim's length.

At least `min_components` Gaussians are fitted even when n_x is smaller, because the mean of a
Gaussian that covers a long arc lies inside the rim; the SOI points are then taken on the curve.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.errors import BadCloud, NumericalFailure
from bagit.common.geometry import align_cyclic, closed_polyline_length, pca, resample_closed
from bagit.services.perception.cleanup import GATE_M, MAX_COORDINATE_M, clean_cloud, crop_near, gate_near, subsample, validate_cloud
from bagit.services.perception.curve import ClosedCurve, following_phase, polar_fill
from bagit.services.perception.em import ChainFit, bending_matrix, bridge, chain_em
from bagit.services.perception.ring import is_counter_clockwise, plane_angles, rim_plane, ring_init


class SoiParams(BaseModel):
    """Knobs of the SOI extractor; the defaults are tuned on the synthetic rims of synthetic.py."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    min_components: int = Field(24, ge=4, le=512, description="fit at least this many Gaussians")
    cold_iterations: int = Field(15, ge=1, le=500)
    warm_iterations: int = Field(4, ge=1, le=500)
    bending: float = Field(0.3, ge=0.0, le=100.0, description="bending prior, per unit of a component's mean support")
    tol_m: float = Field(1e-4, gt=0.0, description="EM stops when no mean moves more than this")
    starved_fraction: float = Field(0.2, ge=0.0, lt=1.0, description="support below this share of the median: starved")
    stray_spacing: float = Field(0.5, gt=0.0, description="off the neighbours' curve by this many spacings: a stray")
    min_supported: float = Field(0.5, gt=0.0, le=1.0, description="share of components that must hold points")
    max_length_change: float = Field(
        0.3, gt=0.0, description="warm start: a rim whose length changed by more than this share is refitted cold"
    )
    gate_m: float = Field(GATE_M, gt=0.0, le=1.0, description="warm start: ignore points this far from the last SOI")


DEFAULT_PARAMS = SoiParams()


def extract_soi(
    points: np.ndarray,
    n_x: int,
    *,
    init: np.ndarray | None = None,
    start_hint: np.ndarray | None = None,
    params: SoiParams = DEFAULT_PARAMS,
) -> np.ndarray:
    """The rim `(n_x, 3)` (the SOI) from a rim cloud `points (n, 3)` (world frame, metres).

    Order convention: the points run counter-clockwise seen from above, i.e. about world +z, or for
    a tilted rim about its plane's normal taken with positive z. Point 0 is the one nearest
    `start_hint` (a world point `(3,)`, e.g. the left handle) when given, else the one at the
    smallest angle from the +x axis (projected into the rim plane) around the rim's centroid.
    The points are equally spaced along the rim.

    With `init` (the previous SOI, `(n_x, 3)`) EM is warm-started from it and init's order is kept
    exactly: point i stays point i (same direction, and each point keeps its place along the rim
    as well as it can); `start_hint` is then ignored. If the rim is no longer near init, the
    extraction starts cold and the result is re-indexed to match init as closely as possible.

    Raises BadCloud for an empty, non-finite, wrongly shaped, too small or degenerate cloud, for
    n_x < 4, a bad init or start_hint, or a cloud in which no rim can be found.
    """
    raw = validate_cloud(points, n_x)
    try:
        soi = _extract(raw, n_x, init, start_hint, params)
    except (NumericalFailure, np.linalg.LinAlgError, FloatingPointError) as e:
        raise BadCloud(f"SOI extraction failed numerically on this cloud: {e}") from None
    if not np.all(np.isfinite(soi)):  # never hand on a rim the fit could not place
        raise BadCloud("SOI extraction gave non-finite points on this cloud")
    return soi


def _extract(raw: np.ndarray, n_x: int, init: object, start_hint: object, params: SoiParams) -> np.ndarray:
    """extract_soi on a validated cloud `raw (n, 3)`."""
    k = max(int(n_x), params.min_components)
    prev = _checked(init, (n_x, 3), "init")
    hint = _checked(start_hint, (3,), "start_hint")
    if prev is not None:
        curve = _warm(raw, prev, k, params)
        if curve is not None:
            return curve.even(n_x, following_phase(curve, prev))
        curve, _ = _cold(raw, k, params)
        return align_cyclic(curve.even(n_x), prev)
    curve, normal = _cold(raw, k, params)
    return _start_at(curve.even(n_x, _start_phase(curve, normal, hint, n_x)), normal, hint)


def _checked(a: object, shape: tuple[int, ...], what: str) -> np.ndarray | None:
    if a is None:
        return None
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise BadCloud(f"{what} is not numeric") from None
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise BadCloud(f"{what} must be a finite array of shape {shape}, got shape {arr.shape}")
    if np.abs(arr).max() > MAX_COORDINATE_M:
        raise BadCloud(f"{what} has coordinates beyond {MAX_COORDINATE_M:.0f} m")
    if what == "init" and closed_polyline_length(arr) <= 0:
        raise BadCloud("init has all its points at one place")
    return arr


def _cold(raw: np.ndarray, k: int, p: SoiParams) -> tuple[ClosedCurve, np.ndarray]:
    """The rim curve (counter-clockwise about the normal) and its plane's normal `(3,)`, from scratch."""
    cloud = clean_cloud(raw, min_points=k)
    centroid, normal = rim_plane(cloud)  # BadCloud if degenerate
    if len(cloud) < k:
        raise BadCloud(f"only {len(cloud)} points left after clean-up, fewer than the {k} components to fit")
    mu0 = ring_init(cloud, k, centroid, normal)
    spacing = closed_polyline_length(mu0) / k
    fit = chain_em(cloud, mu0, iterations=p.cold_iterations, bending=p.bending, sigma0=spacing / 2, tol=p.tol_m)
    mu, keep = _repair(fit, p)
    normal = _normal_of(mu, normal)
    if not is_counter_clockwise(mu, normal):
        mu, keep = mu[::-1], keep[::-1]
    return _curve(mu, keep, normal), normal


def _warm(raw: np.ndarray, prev: np.ndarray, k: int, p: SoiParams) -> ClosedCurve | None:
    """The rim curve in prev's direction, EM started from `prev (n_x, 3)`; None if the rim left it."""
    # Only the neighbourhood of the last rim is cleaned (a box crop first: cheaper on raw points);
    # the few outliers left near the rim are the uniform term's job.
    cloud = gate_near(clean_cloud(crop_near(subsample(raw), prev, p.gate_m), strict=True), prev, p.gate_m)
    if len(cloud) < 2 * k:
        return None
    mu0 = prev if len(prev) == k else resample_closed(prev, k)
    spacing = closed_polyline_length(mu0) / k
    fit = chain_em(cloud, mu0, iterations=p.warm_iterations, bending=p.bending, sigma0=spacing / 2, tol=p.tol_m)
    # A warm start is for the small motion between frames; a rim that jumped by half the gate or
    # more is only partly inside it, and EM would fit the part it sees: start cold instead.
    if np.median(np.linalg.norm(fit.mu - mu0, axis=1)) > 0.5 * p.gate_m:
        return None
    try:
        mu, keep = _repair(fit, p)
    except BadCloud:
        return None
    # A rim's length barely changes between frames (the paper's premise), so of the two bridges over
    # a hidden stretch the one that keeps it is taken: the polar bridge restores a hidden tip the
    # spline would cut across, but bulges far out when the seen rim is not near an ellipse (a
    # kidney-shaped, pinched rim). If neither keeps the length, EM latched onto something else near
    # the old rim: start cold instead.
    length = closed_polyline_length(prev)
    curve = min(_curves(mu, keep, _normal_of(mu, np.array([0.0, 0.0, 1.0]))), key=lambda c: abs(c.length / length - 1.0))
    return curve if abs(curve.length / length - 1.0) <= p.max_length_change else None


def _repair(fit: ChainFit, p: SoiParams) -> tuple[np.ndarray, np.ndarray]:
    """The means `(k, 3)` with starved and stray ones replaced by the bending bridge over the good
    ones, and the mask `(k,)` of the good ones.

    The prior has done its job (order, even spacing, carrying components through gaps); a fed
    component is placed at the mean of its own points, so the ones at the edge of a hidden stretch
    are not pulled off the rim into it.
    """
    k = len(fit.mu)
    support, sigma = fit.support, fit.sigma
    # Fed: a fair share of the median support, and points of its own (EM leaves data_mu NaN below
    # its own floor, which a median of ~0 on a half-hidden rim would otherwise let through).
    fed = (support >= p.starved_fraction * max(float(np.median(support)), 1e-9)) & np.isfinite(fit.data_mu).all(axis=1)
    if fed.sum() < max(4, p.min_supported * k):
        raise BadCloud(
            f"only {int(fed.sum())} of {k} rim components are supported by points: "
            "the cloud does not show enough of a rim"
        )
    mu = bridge(np.where(fed[:, None], fit.data_mu, fit.mu), fed)
    # A stray sits off the smooth curve through its neighbours: the leave-one-out bending
    # prediction of mean j is mu_j - (P mu)_j / P_jj.
    spacing = closed_polyline_length(mu) / k
    off = np.linalg.norm(bending_matrix(k) @ mu, axis=1) / 6.0
    stray = off > max(p.stray_spacing * spacing, 4.0 * sigma)
    keep = fed & ~stray
    if not stray.any() or keep.sum() < max(4, p.min_supported * k):
        return mu, fed
    return bridge(mu, keep), keep


def _curve(mu: np.ndarray, keep: np.ndarray, normal: np.ndarray) -> ClosedCurve:
    """The rim curve through the kept means, hidden stretches bridged in polar form when the rim is
    star-shaped about its centre (else by the arc-length spline alone)."""
    return next(_curves(mu, keep, normal))


def _curves(mu: np.ndarray, keep: np.ndarray, normal: np.ndarray) -> Iterator[ClosedCurve]:
    """The rim curves through the kept means `mu (k, 3)`: with every mean kept, the one curve; else
    the polar bridge over the hidden stretches (when the rim is star-shaped about its centre), then
    the arc-length spline's."""
    if keep.all():
        yield ClosedCurve.through(mu)
        return
    knots = polar_fill(mu, keep, normal)
    if knots is not None:
        yield ClosedCurve.through(knots)
    yield ClosedCurve.through(mu, keep)


def _normal_of(mu: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Unit normal `(3,)` (z >= 0) of the plane through the means `mu (k, 3)`."""
    _, var, axes = pca(mu)
    n = axes[2] if var[1] > 0 else fallback
    return -n if n[2] < 0 else n


def _start_phase(curve: ClosedCurve, normal: np.ndarray, hint: np.ndarray | None, n: int) -> float:
    """Arc length of point 0: the curve's point nearest `hint`, else half a spacing past the +x ray
    (so the smallest-angle point is unambiguous) -- the SOI's place along the rim does not depend on
    where EM's chain happened to start."""
    if hint is not None:
        return float(curve.arc_of(hint[None])[0])
    ang = np.mod(plane_angles(curve.points, curve.points.mean(axis=0), normal), 2.0 * np.pi)
    return float(curve.arc[int(np.argmin(ang))]) + 0.5 * curve.length / n


def _start_at(rim: np.ndarray, normal: np.ndarray, hint: np.ndarray | None) -> np.ndarray:
    """`rim (n, 3)` rolled so point 0 is the one nearest `hint`, else the one at the smallest angle
    from +x around the SOI's own centroid (the convention, exactly as stated)."""
    if hint is not None:
        start = int(np.argmin(np.linalg.norm(rim - hint, axis=1)))
    else:
        start = int(np.argmin(np.mod(plane_angles(rim, rim.mean(axis=0), normal), 2.0 * np.pi)))
    return np.roll(rim, -start, axis=0)
