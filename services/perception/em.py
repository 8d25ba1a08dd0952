"""EM for the paper's eq. (48): n Gaussians on the rim plus a uniform outlier term, with a bending prior.

Model: a point p is an outlier with probability w (uniform over the cloud's bounding box, volume V)
or else drawn from one of k isotropic Gaussians N(mu_j, sigma^2 I) with equal weights (1 - w) / k.
The shared variance keeps a starved component from collapsing or ballooning; equal weights keep it
alive so that it can be carried along.

Chain prior (our addition): the means form a closed chain, and the M-step maximises the expected
log-likelihood minus (lambda / 2) * sum_j |mu_{j-1} - 2 mu_j + mu_{j+1}|^2, a discrete bending
energy, as in coherent point drift's smoothness term but along a closed curve. Why bending and not
a spring between neighbours: springs pull every mean towards the chord of its neighbours (the rim
shrinks at its tight ends, and a hidden stretch is bridged by a straight line far inside the rim);
bending only resists changes of direction, so supported means stay on the data (the pull on a
circle scales with (spacing / radius)^4, well under 1 mm here), the means stay in order and evenly
spaced, and means with no data (behind a gripper) follow a smooth cubic-like continuation of the
rim from both sides. The M-step is then one small linear solve: (diag(S) + lambda' P) mu = R^T X.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

MIN_SIGMA_M = 0.0015  # floor on the components' spread: the rim band is a few mm wide
MIN_VOLUME_M3 = 1e-6  # floor on the uniform term's volume (a cloud that is nearly flat)


@dataclass(frozen=True)
class ChainFit:
    """The fitted chain. mu: (k, 3) means in chain order (with the prior); data_mu: (k, 3) each
    component's mean of its points alone (NaN where it has none); support: (k,) summed
    responsibilities."""

    mu: np.ndarray
    data_mu: np.ndarray
    support: np.ndarray
    sigma: float
    outlier_weight: float
    iterations: int


@lru_cache(maxsize=32)
def bending_matrix(k: int) -> np.ndarray:
    """P = D^T D `(k, k)` for the closed chain's second-difference operator D (read-only)."""
    d = np.zeros((k, k))
    idx = np.arange(k)
    d[idx, (idx - 1) % k] += 1.0
    d[idx, idx] -= 2.0
    d[idx, (idx + 1) % k] += 1.0
    p = d.T @ d
    p.setflags(write=False)
    return p


def chain_em(
    cloud: np.ndarray,
    mu0: np.ndarray,
    *,
    iterations: int,
    bending: float,
    sigma0: float,
    outlier_weight0: float = 0.2,
    tol: float = 1e-4,
) -> ChainFit:
    """Fit the chain of means `mu0 (k, 3)` to `cloud (n, 3)` by at most `iterations` EM steps.

    bending: lambda' in units of a component's mean support (so it does not depend on n).
    Stops early when no mean moves more than `tol` metres.
    """
    origin = cloud.mean(axis=0)  # centred: smaller numbers, so float32 distances stay exact to microns
    x = np.ascontiguousarray(cloud - origin, dtype=float)
    x32 = x.astype(np.float32)
    mu = np.array(mu0, dtype=float) - origin
    k = len(mu)
    n = len(x)
    extent = np.maximum(x.max(axis=0) - x.min(axis=0), 0.01)
    p_uniform = 1.0 / max(float(np.prod(extent)), MIN_VOLUME_M3)
    xx = np.einsum("ij,ij->i", x, x)
    xx32 = xx.astype(np.float32)[None]
    x32T = np.ascontiguousarray(x32.T)
    g = np.empty((len(mu0), n), dtype=np.float32)
    P = bending_matrix(k)
    var = max(sigma0, MIN_SIGMA_M) ** 2
    w = float(np.clip(outlier_weight0, 0.01, 0.9))
    support = np.zeros(k)
    b = np.zeros((k, 3))
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 - the count is read after the loop
        # E-step in float32 densities, laid out (k, n) so the sums run along contiguous rows and
        # every (k, n) step is in place: far points' Gaussian terms underflow to 0 and the uniform
        # term keeps every denominator positive, so no log-sum-exp is needed.
        mu32 = mu.astype(np.float32)
        np.matmul(mu32, x32T, out=g)
        g *= np.float32(-2.0)
        g += xx32
        g += np.einsum("ij,ij->i", mu32, mu32)[:, None]
        np.maximum(g, 0.0, out=g)
        g *= np.float32(-0.5 / var)
        np.exp(g, out=g)
        out = w * p_uniform
        scale = (1.0 - w) / k * (2.0 * np.pi * var) ** -1.5
        denom = g.sum(axis=0, dtype=np.float64) * scale + out  # (n,)
        g *= (scale / denom).astype(np.float32)[None]  # responsibilities (k, n)
        support = g.sum(axis=1, dtype=np.float64)
        inlier_mass = float(support.sum())
        w = float(np.clip(out * np.sum(1.0 / denom) / n, 0.01, 0.9))
        if inlier_mass < 1e-6:  # nothing near the chain at all
            break
        # M-step: the means under the bending prior; a tiny ridge towards the old means keeps the
        # system regular even if every component lost its points.
        b = (g @ x32).astype(np.float64)  # (k, 3)
        lam = bending * inlier_mass / k
        ridge = 1e-6 * inlier_mass / k
        A = P * lam
        A[np.diag_indices(k)] += support + ridge
        new_mu = np.linalg.solve(A, b + ridge * mu)
        shift = float(np.abs(new_mu - mu).max())
        mu = new_mu
        # Shared variance from the residuals to the new means, without re-forming (n, k) distances:
        # sum_ij r_ij |x_i - mu_j|^2 = sum_i r_i |x_i|^2 - 2 sum_j mu_j . b_j + sum_j S_j |mu_j|^2.
        r_i = g.sum(axis=0, dtype=np.float64)
        resid = float(r_i @ xx - 2.0 * np.einsum("ij,ij->", mu, b) + support @ np.einsum("ij,ij->i", mu, mu))
        var = max(resid / (3.0 * inlier_mass), MIN_SIGMA_M**2)
        if shift < tol:
            break
    with np.errstate(invalid="ignore", divide="ignore"):
        data_mu = np.where(support[:, None] > 1e-9, b / support[:, None], np.nan) + origin
    return ChainFit(
        mu=mu + origin, data_mu=data_mu, support=support, sigma=float(np.sqrt(var)), outlier_weight=w, iterations=it
    )


def bridge(mu: np.ndarray, keep: np.ndarray, bending: float = 1.0) -> np.ndarray:
    """`mu (k, 3)` with the rows not in `keep` replaced by the bending-energy interpolation of the kept ones.

    The minimiser of the bending energy with the kept means fixed: a smooth, cubic-like bridge
    over a hidden stretch, and the repair for a mean that strayed off the rim.
    """
    k = len(mu)
    if keep.all():
        return mu
    P = bending_matrix(k)
    free = np.flatnonzero(~keep)
    fixed = np.flatnonzero(keep)
    # Minimise |D mu|^2 over the free rows: P_ff mu_f = -P_fc mu_c.
    A = P[np.ix_(free, free)] * bending
    rhs = -(P[np.ix_(free, fixed)] * bending) @ mu[fixed]
    out = mu.copy()
    out[free] = np.linalg.solve(A + 1e-12 * np.eye(len(free)), rhs)
    return out
