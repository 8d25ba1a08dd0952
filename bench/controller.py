"""The controller's speed: the MPC QP per tick (T = 10, n_x = 32) with PIQP dense and sparse beside
OSQP on the very same QPs, and the three controllers in closed loop on the synthetic rim.

The QPs are the ones the MPC really met, tick after tick, servoing the synthetic rim along a path
(the Jacobian from Broyden's estimate, the target from the subgoal tracker, C6 from the grippers),
replayed into each solver the way a controller would use it: set up once, then updated.

    python -m bagit.bench.controller [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import osqp
import piqp
import scipy.sparse as sp

from bagit.bench.common import stats_ms
from bagit.common.dual_arm import apply_increment
from bagit.common.errors import BadControlInput
from bagit.common.names import SERVO_CONTROLLER_NAMES
from bagit.common.params import MethodParams
from bagit.services.controller import MpcSolver, c7_limits, make_controller
from bagit.services.controller.mpc import MpcController, separation_bounds, separation_gradient, uncondensed_qp
from bagit.services.controller.subgoal import rms_error, slide_to
from bagit.services.controller.synthetic import SyntheticRim

N_X = 32
U_GOAL = np.array([0.05, 0.03, 0.15, 0, 0, 0.2, 0.05, -0.03, 0.15, 0, 0, 0.2])


def _path(m: SyntheticRim, scale: float = 1.0, n_nodes: int = 8) -> np.ndarray:
    return np.stack([m.rim(apply_increment(m.home(), U_GOAL * scale * s)) for s in np.linspace(0, 1, n_nodes)])


def closed_loop(kind: str, p: MethodParams, scale: float = 1.0, noise: float = 0.0, seed: int = 0, record: list | None = None) -> dict:
    """One synthetic run; `record` collects the MPC's QP arguments of every solved tick."""
    m = SyntheticRim(N_X)
    path = _path(m, scale)
    c = make_controller(kind, p, N_X)
    g = m.home()
    c.reset(m.rim(g), path, g, dagger_index=5)
    if record is not None:
        if not isinstance(c, MpcController):
            raise BadControlInput(f"only the mpc controller has a QP to record, not {kind}")
        solve = c.solver.solve

        def spy(*args):
            record.append(tuple(np.copy(a) if isinstance(a, np.ndarray) else a for a in args))
            return solve(*args)

        setattr(c.solver, "solve", spy)  # noqa: B010 - a spy shadowing the method on this instance only
    rng = np.random.default_rng(seed)
    t, out, ms, servo_ms = 0.0, None, [], []
    for k in range(1, 1500):  # noqa: B007 - the count is read after the loop
        x = m.rim(g) + rng.normal(size=(N_X, 3)) * noise
        t0 = time.perf_counter()
        out = c.step(x, t, g)
        dt = (time.perf_counter() - t0) * 1e3
        ms.append(dt)
        if out.mode == "servo":
            servo_ms.append(dt)
        g = apply_increment(g, out.u)
        t += c.dt
        if out.done:
            break
    if out is None:
        raise AssertionError("the loop ran no tick")
    final = m.rim(g)  # the noise-free rim, compared as the tracker does (points may slide along it)
    err_true = rms_error(final, slide_to(path[-1], final))
    return {"done": bool(out.done), "ticks": k, "sim_time_s": k * c.dt, "error_mm": out.error_to_goal * 1e3,
            "true_error_mm": err_true * 1e3, "tick": stats_ms(ms), "servo_tick": stats_ms(servo_ms)}


def _recorded_qps(p: MethodParams, quick: bool) -> list[tuple]:
    rec: list[tuple] = []
    for i, scale in enumerate([1.0, 0.7] if quick else [1.0, 0.7, 1.2, 0.5, 0.9]):
        closed_loop("mpc", p, scale, noise=0.0005, seed=i, record=rec)
    return rec


def _time_solver(solver: MpcSolver, qps: list[tuple]) -> tuple[list[float], list[float], list[np.ndarray], list[int]]:
    """Wall and CPU (this thread's) time per solve: on a shared machine the CPU time is the steadier."""
    ms, cpu, sols, its = [], [], [], []
    for args in qps:
        c0 = time.thread_time()
        sol = solver.solve(*args)
        cpu.append((time.thread_time() - c0) * 1e3)
        ms.append(sol.solve_ms)
        sols.append(sol.u_bar)
        its.append(sol.iterations)
    return ms, cpu, sols, its


def _unpack(args: tuple) -> tuple:
    """A recorded MpcSolver.solve call as (J, x, target, u_max, axis, sep, limits, recover)."""
    full = list(args) + [None] * (8 - len(args))
    J, x, target, u_max, axis, sep, lim, recover = full
    return J, x, target, u_max, axis, 0.0 if sep is None else sep, (0.0, np.inf) if lim is None else lim, recover or 0.0


def _stacked_constraints(ref: MpcSolver, axis: np.ndarray) -> sp.csc_matrix:
    """[I; G] `(12T + T, 12T)` with a pattern that never changes (explicit zeros kept)."""
    n = 12 * ref.T
    vals = separation_gradient(axis)[ref._g_pos]  # noqa: SLF001
    rows = np.concatenate([np.arange(n), n + ref._g_rows])  # noqa: SLF001
    cols = np.concatenate([np.arange(n), ref._g_cols])  # noqa: SLF001
    return sp.csc_matrix((np.concatenate([np.ones(n), vals]), (rows, cols)), shape=(n + ref.T, n))


def _osqp(qps: list[tuple], p: MethodParams, warm: bool, ref: MpcSolver, eps: float = 1e-7) -> tuple[list[float], list[float], list[np.ndarray], list[int]]:
    """OSQP on the same condensed QPs (bounds and C6 rows stacked into one constraint matrix).
    warm: set up once, then update the data and warm start from last tick's plan shifted by one.
    Timed: the solver's calls only (the data are built outside the clock, in PIQP's favour not)."""
    ms, cpu, sols, its = [], [], [], []
    T = p.controller.horizon
    prob, prev = None, None
    for args in qps:
        J, x, target, u_max, axis, sep, lim, recover = _unpack(args)
        H, c = ref.condensed(J, x, target)
        A = _stacked_constraints(ref, axis)
        h_l, h_u = separation_bounds(sep, lim, recover, T)
        lo = np.concatenate([-np.tile(u_max, T), h_l])
        hi = np.concatenate([np.tile(u_max, T), h_u])
        Pu = ref._sparse_p(H)  # noqa: SLF001 - the full upper triangle, explicit zeros kept
        t0, c0 = time.perf_counter(), time.thread_time()
        if prob is None or not warm:
            prob = osqp.OSQP()
            prob.setup(Pu, c, A, lo, hi, verbose=False, eps_abs=eps, eps_rel=eps, max_iter=20000, polish=True)
        else:
            # Same patterns every tick (dense triangle, identity + C6 rows with the axis' entries).
            prob.update(q=c, l=lo, u=hi, Px=Pu.data, Ax=A.data)
            if prev is not None:
                prob.warm_start(x=np.concatenate([prev[12:], prev[-12:]]))
        res = prob.solve(raise_error=False)  # a failed solve shows as a large difference, not an exception
        ms.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.thread_time() - c0) * 1e3)
        prev = res.x
        sols.append(res.x)
        its.append(int(res.info.iter))
    return ms, cpu, sols, its


def _sparse_uncondensed(qps: list[tuple], p: MethodParams, R: np.ndarray) -> tuple[list[float], list[float]]:
    """PIQP's sparse solver on the MPC with the states kept as variables (C8 as equalities): the
    formulation a sparse solver would usually get, 1080 variables at n_x = 32. Solver calls timed."""
    ms, cpu, solver = [], [], None
    for args in qps:
        J, x, target, u_max, axis, sep, lim, recover = _unpack(args)
        qp = uncondensed_qp(J, x, target, u_max, p.controller.horizon, p.controller.q_weight, R, axis, sep, lim, recover)
        t0, c0 = time.perf_counter(), time.thread_time()
        if solver is None:
            solver = piqp.SparseSolver()
            solver.settings.verbose = False
            solver.settings.eps_abs = solver.settings.eps_rel = 1e-7
            solver.setup(qp["P"], qp["c"], qp["A"], qp["b"], qp["G"], qp["h_l"], qp["h_u"], qp["x_l"], qp["x_u"])
        else:
            solver.update(A=qp["A"], b=qp["b"], c=qp["c"], G=qp["G"], h_l=qp["h_l"], h_u=qp["h_u"])
        solver.solve()
        ms.append((time.perf_counter() - t0) * 1e3)
        cpu.append((time.thread_time() - c0) * 1e3)
    return ms, cpu


def run(quick: bool = False) -> dict:
    p = MethodParams()
    qps = _recorded_qps(p, quick)
    u_max = c7_limits(p)
    scale = np.tile(u_max, p.controller.horizon)
    out: dict = {"horizon": p.controller.horizon, "n_x": N_X, "variables": 12 * p.controller.horizon, "qps": len(qps)}
    c = p.controller
    dense_ms, dense_cpu, dense_x, dense_it = _time_solver(MpcSolver(c.horizon, c.q_weight, c.r_weight, "dense", twist=c.experimental.twist_weight), qps)
    sparse_ms, sparse_cpu, sparse_x, _ = _time_solver(MpcSolver(c.horizon, c.q_weight, c.r_weight, "sparse", twist=c.experimental.twist_weight), qps)
    ref = MpcSolver(c.horizon, c.q_weight, c.r_weight, twist=c.experimental.twist_weight)
    cold_ms, cold_cpu, cold_x, cold_it = _osqp(qps, p, warm=False, ref=ref)
    warm_ms, warm_cpu, warm_x, warm_it = _osqp(qps, p, warm=True, ref=ref)
    loose_ms, loose_cpu, loose_x, loose_it = _osqp(qps, p, warm=True, ref=ref, eps=1e-4)
    unc_ms, unc_cpu = _sparse_uncondensed(qps[: 30 if quick else 100], p, ref.R)

    def diff(xs):  # largest difference to PIQP dense, as a share of each input's C7 range
        return float(max(np.max(np.abs(a - b) / scale) for a, b in zip(xs, dense_x, strict=False)))

    med = float(np.median(dense_ms))
    out["piqp_dense"] = stats_ms(dense_ms) | {"iterations_median": float(np.median(dense_it)), "cpu": stats_ms(dense_cpu)}
    out["piqp_sparse"] = stats_ms(sparse_ms) | {"over_dense": float(np.median(sparse_ms)) / med, "max_rel_difference": diff(sparse_x),
                                                "cpu": stats_ms(sparse_cpu)}
    out["piqp_sparse_uncondensed"] = stats_ms(unc_ms) | {"over_dense": float(np.median(unc_ms)) / med, "cpu": stats_ms(unc_cpu)}
    for key, t, tc, xs, it in (("osqp_cold", cold_ms, cold_cpu, cold_x, cold_it), ("osqp_warm", warm_ms, warm_cpu, warm_x, warm_it),
                               ("osqp_warm_eps1e-4", loose_ms, loose_cpu, loose_x, loose_it)):
        out[key] = stats_ms(t) | {"over_dense": float(np.median(t)) / med, "max_rel_difference": diff(xs),
                                  "iterations_median": float(np.median(it)), "cpu": stats_ms(tc)}
    cpu_med = out["piqp_dense"]["cpu"]["median_ms"]
    for key in ("piqp_sparse", "piqp_sparse_uncondensed", "osqp_cold", "osqp_warm", "osqp_warm_eps1e-4"):
        out[key]["cpu_over_dense"] = out[key]["cpu"]["median_ms"] / cpu_med
    for kind in SERVO_CONTROLLER_NAMES:
        out[f"synthetic_{kind}"] = closed_loop(kind, p)
        out[f"synthetic_noisy_{kind}"] = closed_loop(kind, p, noise=0.001, seed=1)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    r = run(ap.parse_args().quick)
    print(f"MPC QP per tick, T = {r['horizon']}, n_x = {r['n_x']} ({r['variables']} variables), {r['qps']} QPs from closed-loop runs:")
    for key, label in (("piqp_dense", "PIQP dense (used)"), ("piqp_sparse", "PIQP sparse, same QP"),
                       ("piqp_sparse_uncondensed", "PIQP sparse, uncondensed"), ("osqp_cold", "OSQP, set up each tick"),
                       ("osqp_warm", "OSQP, updated + warm start"), ("osqp_warm_eps1e-4", "OSQP, warm, eps 1e-4")):
        s = r[key]
        extra = f"  {s['over_dense']:.1f}x dense" if "over_dense" in s else ""
        if "iterations_median" in s:
            extra += f" ({s['iterations_median']:.0f} iterations)"
        if "max_rel_difference" in s:
            extra += f", max |du| {s['max_rel_difference'] * 100:.2f} % of C7"
        print(f"  {label:28s} min {s['min_ms']:.3f}  median {s['median_ms']:.3f}  p95 {s['p95_ms']:.3f} ms{extra}")
        if "cpu" in s:
            c = s["cpu"]
            ratio = f"  {s['cpu_over_dense']:.1f}x dense" if "cpu_over_dense" in s else ""
            print(f"  {'':28s} CPU  min {c['min_ms']:.3f}  median {c['median_ms']:.3f}  p95 {c['p95_ms']:.3f} ms{ratio}")
    print("Closed loop on the synthetic rim (exploration included):")
    for kind in SERVO_CONTROLLER_NAMES:
        for tag in ("", "noisy_"):
            s = r[f"synthetic_{tag}{kind}"]
            print(f"  {kind:4s} {'1 mm noise' if tag else 'no noise  '}: done={s['done']} in {s['ticks']} ticks ({s['sim_time_s']:.1f} s), "
                  f"error {s['error_mm']:.1f} mm (true {s['true_error_mm']:.1f}), tick median {s['tick']['median_ms']:.2f} ms, "
                  f"servo tick p95 {s['servo_tick'].get('p95_ms', 0):.2f} ms")


if __name__ == "__main__":
    main()
