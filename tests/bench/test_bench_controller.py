"""The controller benchmark (`bagit bench stages --only controller`) runs on the MPC's real QPs.

It replays the QPs recorded from synthetic closed loops through PIQP (dense and sparse) and OSQP;
when MpcSolver.solve grew an argument (u_prev, for move suppression) the replay broke without a test
noticing. Here the benchmark runs (quick) and its solvers must agree on the same QPs.
"""

import numpy as np
import pytest

from bagit.bench import controller


@pytest.mark.slow
def test_the_controller_benchmark_replays_the_recorded_qps_and_its_solvers_agree():
    r = controller.run(quick=True)
    assert r["horizon"] == 10 and r["n_x"] == 32 and r["qps"] > 50
    assert r["piqp_sparse"]["n"] == r["osqp_warm"]["n"] == r["qps"]
    assert r["piqp_sparse"]["max_rel_difference"] < 1e-6  # the same QP, the same solver family
    assert r["osqp_cold"]["max_rel_difference"] < 0.05 and r["osqp_warm"]["max_rel_difference"] < 0.05
    assert np.isfinite(r["piqp_dense"]["median_ms"]) and r["piqp_dense"]["median_ms"] > 0
    assert r["synthetic_mpc"]["done"] and r["synthetic_mpc"]["true_error_mm"] < 15.0
