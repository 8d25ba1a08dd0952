"""SOI extraction speed and accuracy, cold and warm, beside scikit-learn's GaussianMixture.

    python -m bagit.bench.perception [--quick]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

from bagit.bench.common import stats_ms, timeit
from bagit.common.geometry import points_to_polyline_distance
from bagit.services.perception import extract_soi
from bagit.services.perception.cleanup import clean_cloud
from bagit.services.perception.synthetic import rim_cloud, true_rim

N_X = 32


def _accuracy(soi: np.ndarray, rim: np.ndarray) -> dict[str, float]:
    d = points_to_polyline_distance(soi, rim)
    return {"mean_mm": float(d.mean() * 1e3), "p95_mm": float(np.percentile(d, 95) * 1e3)}


def _sklearn(cloud: np.ndarray, rim: np.ndarray, repeat: int) -> dict:
    from sklearn.mixture import GaussianMixture

    cleaned = clean_cloud(cloud)  # the same cleaned cloud our EM sees; sklearn has no outlier term
    gm = GaussianMixture(n_components=N_X, covariance_type="spherical", max_iter=100, random_state=0)
    t = timeit(lambda: gm.fit(cleaned), repeat=repeat, warmup=0)
    return {"time": t, "accuracy": _accuracy(gm.means_, rim), "points": int(len(cleaned))}


def run(quick: bool = False) -> dict:
    repeat = 10 if quick else 50
    out: dict = {"n_x": N_X}
    for n_points in (12_000, 50_000):
        rim = true_rim("ellipse", rpy=(0.2, 0.1, 0.5))
        cloud, _ = rim_cloud(rim, n_points=n_points, outlier_fraction=0.2, occlusion=0.07, seed=1)
        cold = timeit(lambda: extract_soi(cloud, N_X), repeat=repeat)
        soi = extract_soi(cloud, N_X)
        # Warm: the next frame, the rim moved by 3 mm.
        cloud2, _ = rim_cloud(rim + [0.003, 0.0, 0.0], n_points=n_points, outlier_fraction=0.2, occlusion=0.07, seed=2)
        warm = timeit(lambda: extract_soi(cloud2, N_X, init=soi), repeat=repeat)
        row = {
            "cold": cold,
            "warm": warm,
            "accuracy_cold": _accuracy(soi, rim),
            "accuracy_warm": _accuracy(extract_soi(cloud2, N_X, init=soi), rim + [0.003, 0.0, 0.0]),
        }
        if n_points == 12_000:
            sk = _sklearn(cloud, rim, repeat=3 if quick else 10)
            row["sklearn_gmm"] = sk
            row["sklearn_over_ours_time"] = sk["time"]["median_ms"] / cold["median_ms"]
        out[f"points_{n_points}"] = row
    # Accuracy over the test conditions: rim kinds x tilts x seeds.
    errs = []
    for kind in ("ellipse", "lens", "wavy", "sagging"):
        for seed in range(2 if quick else 5):
            rim = true_rim(kind, rpy=(0.3 * seed, 0.1, seed))
            cloud, _ = rim_cloud(rim, outlier_fraction=0.3, occlusion=0.07, occlusion_at=0.2 * seed, seed=seed)
            errs.append(points_to_polyline_distance(extract_soi(cloud, N_X), rim))
    e = np.concatenate(errs) * 1e3
    out["accuracy_all"] = {"mean_mm": float(e.mean()), "p95_mm": float(np.percentile(e, 95)), "max_mm": float(e.max())}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args()
    t0 = time.perf_counter()
    res = run(args.quick)
    for key in ("points_12000", "points_50000"):
        r = res[key]
        print(
            f"{key}: cold median {r['cold']['median_ms']:.1f} ms (p95 {r['cold']['p95_ms']:.1f}), "
            f"warm median {r['warm']['median_ms']:.1f} ms (p95 {r['warm']['p95_ms']:.1f}); "
            f"error cold {r['accuracy_cold']['mean_mm']:.2f}/{r['accuracy_cold']['p95_mm']:.2f} mm (mean/p95)"
        )
        if "sklearn_gmm" in r:
            sk = r["sklearn_gmm"]
            print(
                f"  sklearn GaussianMixture on the same cleaned cloud ({sk['points']} pts): median "
                f"{sk['time']['median_ms']:.1f} ms ({r['sklearn_over_ours_time']:.1f}x ours), error "
                f"{sk['accuracy']['mean_mm']:.2f}/{sk['accuracy']['p95_mm']:.2f} mm"
            )
    a = res["accuracy_all"]
    print(f"all rim kinds: mean {a['mean_mm']:.2f} mm, p95 {a['p95_mm']:.2f} mm, max {a['max_mm']:.2f} mm")
    print(f"({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    main()
