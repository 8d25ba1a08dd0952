"""SOI extraction: the bag rim as n_x ordered points, by EM on a Gaussian mixture with a uniform outlier term.

The paper (section IV) treats the rim cloud as samples from n_x Gaussians whose means are the SOI
points, plus a uniform component for outliers. Three additions make it hold on real depth data:

* a chain prior on the means (each is pulled weakly towards its two neighbours around the rim), so
  the components keep their order and a component that loses its points (behind a gripper) is
  carried along by its neighbours instead of drifting onto an outlier;
* starved or stray components (little responsibility, or far off the curve through their
  neighbours) are dropped, and the rim is a periodic arc-length spline through the supported ones,
  so no SOI point sits on an outlier and a hidden stretch is bridged smoothly from both sides;
* the final rim is resampled at equal arc length along that spline, so the points are evenly
  spaced whatever the cloud's density.

Order convention: counter-clockwise seen from above (about the rim plane's normal taken with
positive world z). Point 0 is the one nearest `start_hint` (e.g. the left handle) when given, else
the one at the smallest angle from world +x around the rim centroid. With `init` (the previous
SOI) EM is warm-started from it and point i stays point i.
"""

from __future__ import annotations

import numpy as np
from scipy.interpolate import CubicSpline

from bagit.common.errors import BadCloud
from bagit.common.geometry import align_cyclic, pca
from bagit.services.perception.cleanup import clean_cloud, gate_near, validate_cloud, voxel_down

COLD_ITERATIONS = 12
WARM_ITERATIONS = 5
MIN_SIGMA_M = 0.0015  # floor on the component spread: the rim band is a few mm wide
CHAIN_WEIGHT = 0.02  # neighbour pull, as a fraction of a component's typical support
SUPPORT_FRACTION = 0.25  # a component with less than this share of the median support is starved
DENSE_SAMPLES = 24
PHASE_STEPS = 41  # phases tried within one spacing either way when following the previous SOI
CONVERGED_M = 1e-4  # EM stops when no mean moves more than this  # spline samples per SOI point for the arc-length resampling


def extract_soi(
    points: np.ndarray,
    n_x: int,
    *,
    init: np.ndarray | None = None,
    start_hint: np.ndarray | None = None,
) -> np.ndarray:
    """The rim `(n_x, 3)` from a rim cloud `points (n, 3)` (world frame, metres).

    Raises BadCloud for an empty, non-finite, too small or degenerate cloud, or n_x < 4.
    """
    raw = validate_cloud(points, n_x)
    mu0 = None
    if init is not None:
        mu0 = np.asarray(init, dtype=float)
        if mu0.shape != (n_x, 3) or not np.all(np.isfinite(mu0)):
            raise BadCloud(f"init must be a finite ({n_x}, 3) array, got {mu0.shape}")
        cloud = gate_near(voxel_down(raw), mu0)
        if len(cloud) < 4 * n_x:  # the rim moved away from init (or vanished): start cold
            mu0 = None
    if mu0 is None:
        cloud = clean_cloud(raw)
    if len(cloud) < n_x:
        raise BadCloud(f"only {len(cloud)} points left after removing outliers, fewer than n_x = {n_x}")
    centroid, var, axes = pca(cloud)
    normal = axes[2]
    if var[1] < (0.005) ** 2:
        raise BadCloud("cloud is degenerate: its points lie on a line or a point, not around a rim")
    if normal[2] < 0:
        normal = -normal

    warm = mu0 is not None
    if mu0 is None:
        mu0 = _cold_init(cloud, n_x, centroid, normal)
    mu, support = _em(cloud, mu0, WARM_ITERATIONS if warm else COLD_ITERATIONS)
    if init is not None:
        # Keep the phase too: start where init's first point projects, then point i stays point i.
        prev = np.asarray(init, dtype=float)
        return _resample_even(_supported(mu, support), n_x, follow=prev)
    rim = _resample_even(_supported(mu, support), n_x)
    return _canonical_order(rim, normal, start_hint)


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the rim plane, the first as close to world +x as the plane allows."""
    x = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - normal[1] * normal
    x /= np.linalg.norm(x)
    return x, np.cross(normal, x)


def _cold_init(cloud: np.ndarray, n_x: int, centroid: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Means `(n_x, 3)` from angle bins around a robust centre in the rim plane (counter-clockwise)."""
    ex, ey = _plane_basis(normal)
    rel = cloud - centroid
    uv = np.column_stack([rel @ ex, rel @ ey])
    centre = np.median(uv, axis=0)
    ang = np.arctan2(uv[:, 1] - centre[1], uv[:, 0] - centre[0])
    bins = np.floor((ang + np.pi) / (2 * np.pi) * n_x).astype(int) % n_x
    mu = np.full((n_x, 3), np.nan)
    counts = np.bincount(bins, minlength=n_x)
    order = np.argsort(bins, kind="stable")
    splits = np.split(order, np.cumsum(counts)[:-1])
    for j, idx in enumerate(splits):
        if len(idx):
            mu[j] = np.median(cloud[idx], axis=0)
    ok = ~np.isnan(mu[:, 0])
    if ok.sum() < 3:
        raise BadCloud("cloud does not go around a rim: fewer than 3 angular sectors hold points")
    return _fill_periodic(mu, ok)


def _fill_periodic(mu: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Replace rows of `mu (k, 3)` where `ok` is False by a periodic spline (by index) through the others."""
    if ok.all():
        return mu
    k = len(mu)
    idx = np.flatnonzero(ok)
    t = np.concatenate([idx, [idx[0] + k]]).astype(float)
    y = np.vstack([mu[idx], mu[idx[0]]])
    kind = "periodic" if len(idx) >= 4 else "not-a-knot"
    if len(idx) < 4:  # too few for a cubic: go linear
        out = mu.copy()
        for d in range(3):
            out[:, d] = np.interp(np.arange(k), t, y[:, d], period=k)
        return out
    spl = CubicSpline(t, y, bc_type=kind)
    out = mu.copy()
    missing = np.flatnonzero(~ok)
    tm = np.where(missing < idx[0], missing + k, missing).astype(float)
    out[missing] = spl(tm)
    return out


def _em(cloud: np.ndarray, mu: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """EM for the means `(k, 3)` of k isotropic Gaussians (shared variance) plus a uniform outlier term.

    Returns the means and each component's support (summed responsibility).
    """
    k = len(mu)
    mu = mu.copy()
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    volume = float(np.prod(np.maximum(hi - lo, 0.01)))
    log_uniform = -np.log(volume)
    spacing = np.linalg.norm(np.roll(mu, -1, axis=0) - mu, axis=1).mean()
    var = max((spacing / 2) ** 2, MIN_SIGMA_M**2)
    w_out = 0.2
    beta = CHAIN_WEIGHT * len(cloud) / k
    pp = np.einsum("ij,ij->i", cloud, cloud)[:, None]
    support = np.zeros(k)
    rg = np.zeros((len(cloud), k))
    for _ in range(iterations):
        d2 = np.maximum(pp - 2.0 * cloud @ mu.T + np.einsum("ij,ij->i", mu, mu)[None], 0.0)
        # Densities rather than logs: a far point's Gaussian terms underflow to 0, and the uniform
        # term keeps every denominator positive, so no log-sum-exp is needed.
        rg = np.exp(d2 * (-0.5 / var)) * ((1 - w_out) / k * (2 * np.pi * var) ** -1.5)
        p_out = w_out * np.exp(log_uniform)
        denom = rg.sum(axis=1) + p_out
        rg /= denom[:, None]
        support = rg.sum(axis=0)
        w_out = float(np.clip(np.mean(p_out / denom), 0.01, 0.9))
        neighbours = np.roll(mu, 1, axis=0) + np.roll(mu, -1, axis=0)
        new_mu = (rg.T @ cloud + beta * neighbours) / (support + 2 * beta)[:, None]
        shift = float(np.abs(new_mu - mu).max())
        mu = new_mu
        resid = float(np.einsum("ij,ij->", rg, d2))
        var = max(resid / (3.0 * max(support.sum(), 1e-9)), MIN_SIGMA_M**2)
        if shift < CONVERGED_M:
            break
    # The chain prior has done its job (order, gaps); supported means are taken from the data alone,
    # so the components at the edge of a hidden stretch are not pulled off the rim into it.
    data_mu = (rg.T @ cloud) / np.maximum(support, 1e-12)[:, None]
    return np.where((support > 1.0)[:, None], data_mu, mu), support


def _supported(mu: np.ndarray, support: np.ndarray) -> np.ndarray:
    """The components `(m, 3)` that hold the rim: starved ones and strays (off the curve through their
    neighbours) are dropped, so the arc-length spline bridges gaps from the good ones on either side."""
    ok = support >= SUPPORT_FRACTION * np.median(support)
    if ok.sum() < 4:
        raise BadCloud("too few rim components are supported by points: the cloud does not show a rim")
    good = mu[ok]
    spacing = np.linalg.norm(np.roll(good, -1, axis=0) - good, axis=1)
    mid = 0.5 * (np.roll(good, 1, axis=0) + np.roll(good, -1, axis=0))
    stray = np.linalg.norm(good - mid, axis=1) > 0.75 * np.median(spacing) + 0.005
    return good[~stray] if (~stray).sum() >= 4 else good


def _resample_even(mu: np.ndarray, n: int, follow: np.ndarray | None = None) -> np.ndarray:
    """n points at equal arc length along a periodic spline through the closed chain `mu (k, 3)`.

    With `follow (n, 3)` (the previous SOI) the points are indexed like it and their phase along the
    rim is the one that moves them least from it: points do not creep round the rim frame after frame.
    """
    closed = np.vstack([mu, mu[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    t = np.concatenate([[0.0], np.cumsum(np.maximum(seg, 1e-9))])
    spl = CubicSpline(t, closed, bc_type="periodic")
    tt = np.linspace(0.0, t[-1], n * DENSE_SAMPLES, endpoint=False)
    dense = spl(tt)
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(np.vstack([dense, dense[:1]]), axis=0), axis=1))])
    knots = np.concatenate([tt, [t[-1]]])
    spacing = arc[-1] / n

    def at(start: np.ndarray) -> np.ndarray:  # (m,) phases -> (m, n, 3)
        target = (start[:, None] + np.arange(n)[None] * spacing) % arc[-1]
        return spl(np.interp(target, arc, knots))

    if follow is None:
        return at(np.zeros(1))[0]
    base = align_cyclic(at(np.zeros(1))[0], follow)
    # where point 0 of the aligned rim sits, as an arc phase; then search +-1 spacing around it
    k0 = int(np.argmin(np.sum((dense - base[0]) ** 2, axis=1)))
    phases = arc[k0] + np.linspace(-1.0, 1.0, PHASE_STEPS) * spacing
    cands = at(phases)  # (m, n, 3), each in the base rim's direction
    forward = np.sum((np.roll(base, -1, axis=0) - base) * (np.roll(cands[0], -1, axis=0) - cands[0])) > 0
    if not forward:
        cands = np.concatenate([cands[:, :1], cands[:, :0:-1]], axis=1)
    cost = np.sum((cands - follow[None]) ** 2, axis=(1, 2))
    return cands[int(np.argmin(cost))]


def _canonical_order(rim: np.ndarray, normal: np.ndarray, start_hint: np.ndarray | None) -> np.ndarray:
    """Counter-clockwise about `normal` (z > 0), starting nearest `start_hint` or at the smallest angle from +x."""
    c = rim.mean(axis=0)
    signed_area = np.einsum("ij,j->", np.cross(rim - c, np.roll(rim, -1, axis=0) - c), normal)
    if signed_area < 0:
        rim = rim[::-1]
    if start_hint is not None:
        hint = np.asarray(start_hint, dtype=float).reshape(3)
        start = int(np.argmin(np.linalg.norm(rim - hint, axis=1)))
    else:
        ex, ey = _plane_basis(normal)
        ang = np.arctan2((rim - c) @ ey, (rim - c) @ ex)
        start = int(np.argmin(np.mod(ang, 2 * np.pi)))
    return np.roll(rim, -start, axis=0)

