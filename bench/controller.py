"""MPC solve time per tick (T = 10, n_x = 32) with PIQP, beside OSQP on the same QPs, and the
closed loop on the synthetic rim.

    python -m bagit.bench.controller [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import scipy.sparse as sp

from bagit.bench.common import stats_ms
from bagit.common.params import MethodParams
from bagit.services.controller import MpcSolver, ShapeServo
from bagit.services.controller.synthetic import SyntheticRim, apply_increment


def _qps(n: int, rng: np.random.Generator):
    """Realistic QPs: Jacobians and errors from the synthetic rim along a trajectory."""
    m = SyntheticRim(32)
    g = m.home()
    for _ in range(n):
        u0 = rng.normal(size=12) * 0.01
        g = apply_increment(g, u0)
        f = lambda u: m.rim(apply_increment(g, u)).ravel()  # noqa: E731
        x = f(np.zeros(12))
        J = np.stack([(f(e * 1e-5) - x) / 1e-5 for e in np.eye(12)], axis=1)
        target = x + rng.normal(size=x.size) * 0.02
        yield J, x, target, g


def run(quick: bool = False) -> dict:
    rng = np.random.default_rng(0)
    p = MethodParams()
    lin, ang = p.max_linear_speed_mps / p.control_rate_hz, p.max_angular_speed_rps / p.control_rate_hz
    u_max = np.array([lin] * 3 + [ang] * 3 + [lin] * 3 + [ang] * 3)
    solver = MpcSolver(p.horizon, p.q_weight, p.r_weight)
    piqp_ms, osqp_ms, diffs = [], [], []
    import osqp

    for J, x, target, g in _qps(60 if quick else 400, rng):
        pl, pr = g["left"][:3, 3], g["right"][:3, 3]
        sep = float(np.linalg.norm(pr - pl))
        axis = (pr - pl) / sep
        sol = solver.solve(J, x, target, u_max, axis, sep, (0.06, 0.306))
        piqp_ms.append(sol.solve_ms)
        # The same QP for OSQP: bounds and the separation rows as one constraint matrix.
        T = p.horizon
        L = np.tril(np.ones((T, T)))
        H = p.q_weight * np.kron(L.T @ L, J.T @ J) + np.diag(solver._r_diag)  # noqa: SLF001 - same QP
        gvec = p.q_weight * np.kron(L.T @ np.ones(T), J.T @ (x - target))
        a = np.concatenate([-axis, np.zeros(3), axis, np.zeros(3)])
        G = np.kron(L, a[None, :])
        A = sp.vstack([sp.eye(12 * T), sp.csc_matrix(G)]).tocsc()
        lo = np.concatenate([-np.tile(u_max, T), np.minimum(np.full(T, 0.06 - sep), 0)])
        hi = np.concatenate([np.tile(u_max, T), np.maximum(np.full(T, 0.306 - sep), 0)])
        t0 = time.perf_counter()
        prob = osqp.OSQP()
        prob.setup(sp.csc_matrix(np.triu(H)), gvec, A, lo, hi, verbose=False, eps_abs=1e-7, eps_rel=1e-7, max_iter=20000)
        res = prob.solve()
        osqp_ms.append((time.perf_counter() - t0) * 1e3)
        diffs.append(float(np.abs(res.x - sol.u_bar).max()))
    out = {
        "horizon": p.horizon,
        "n_x": 32,
        "piqp": stats_ms(piqp_ms),
        "osqp": stats_ms(osqp_ms),
        "osqp_over_piqp_median": float(np.median(osqp_ms) / np.median(piqp_ms)),
        "max_solution_difference": float(np.max(diffs)),
    }
    # Closed loop on the synthetic rim.
    m = SyntheticRim(32)
    u_goal = np.array([0.05, 0.03, 0.15, 0, 0, 0.2, 0.05, -0.03, 0.15, 0, 0, 0.2])
    path = np.stack([m.rim(apply_increment(m.home(), u_goal * s)) for s in np.linspace(0, 1, 8)])
    for kind in ("mpc", "ibvs", "ssvs"):
        c = ShapeServo(kind, p, path, 5, 0.68)
        g, t, ticks, out_k = m.home(), 0.0, 0, None
        for ticks in range(1, 1200):
            out_k = c.step(m.rim(g), t, g)
            g = apply_increment(g, out_k.u)
            t += 1 / p.control_rate_hz
            if out_k.done:
                break
        out[f"synthetic_{kind}"] = {"done": bool(out_k.done), "ticks": ticks, "error_mm": out_k.error_to_goal * 1e3}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    r = run(ap.parse_args().quick)
    a, b = r["piqp"], r["osqp"]
    print(f"MPC QP (T={r['horizon']}, n_x={r['n_x']}, 120 variables): PIQP median {a['median_ms']:.2f} ms (p95 {a['p95_ms']:.2f}, min {a['min_ms']:.2f})")
    print(f"  OSQP on the same QPs: median {b['median_ms']:.2f} ms (p95 {b['p95_ms']:.2f}); OSQP/PIQP {r['osqp_over_piqp_median']:.1f}x; max |u| difference {r['max_solution_difference']:.2e}")
    for kind in ("mpc", "ibvs", "ssvs"):
        s = r[f"synthetic_{kind}"]
        print(f"synthetic closed loop {kind}: done={s['done']} in {s['ticks']} ticks, error {s['error_mm']:.1f} mm")


if __name__ == "__main__":
    main()
