"""PNG figures of `bagit bench paper` (matplotlib, Agg): planning-time distributions, our times against
the paper's with error bars, rendered SOI paths like the paper's Fig. 7(c), c1 statistics, manipulation."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from bagit.bench import paper_data as P  # noqa: E402

DPI = 72
COLORS = {"cbirrt": "tab:green", "ffg-rrt": "tab:orange", "ts-rrt": "tab:purple"}
PATH_SCENARIOS = ["exp01", "exp04", "exp06", "exp11", "obstacles-a", "obstacles-b"]


def _save(fig: plt.Figure, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=DPI)
    plt.close(fig)
    return path


def _short(stem: str) -> str:
    return stem[:5] if stem.startswith("exp") else stem.split("-")[0] + "-" + stem.split("-")[1]


def planning_times(r: dict[str, Any], path: Path) -> Path:
    """Box plots of every successful plan's time, per scenario and planner (log scale)."""
    stems = list(r["planning"])
    fig, ax = plt.subplots(figsize=(max(6, 0.7 * len(stems) + 2), 3.6))
    w = 0.25
    for j, planner in enumerate(P.PLANNERS):
        data = [[x["time_s"] for x in r["planning_runs"] if x["scenario"] == s and x["planner"] == planner and x["success"]] or [np.nan] for s in stems]
        pos = np.arange(len(stems)) + (j - 1) * w
        bp = ax.boxplot(data, positions=pos, widths=w * 0.9, patch_artist=True, showfliers=True, flierprops={"markersize": 2})
        for b in bp["boxes"]:
            b.set_facecolor(COLORS[planner])
            b.set_alpha(0.6)
        ax.plot([], [], "s", color=COLORS[planner], label=planner)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(stems)), [_short(s) for s in stems], rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("planning time per path (s)")
    ax.set_title(f"Planning time over {r['seeds']} seeds (successful plans)", fontsize=10)
    ax.legend(fontsize=8, ncol=3)
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def planning_vs_paper(r: dict[str, Any], path: Path) -> Path:
    """Mean ± std planning time and success rate per Table II experiment: ours against the paper's."""
    exps = [e for e in P.TABLE2_EXPERIMENTS if any(s.startswith(e) for s in r["planning"])]
    stem = {e: next(s for s in r["planning"] if s.startswith(e)) for e in exps}
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.6))
    x = np.arange(len(exps))
    w = 0.13
    for j, planner in enumerate(P.PLANNERS):
        ours = [r["planning"][stem[e]].get(planner, {}) for e in exps]
        m = [c.get("time_mean_s") or np.nan for c in ours]
        s = [c.get("time_std_s") or 0.0 for c in ours]
        pm = [P.PLANNING[e][planner][2] for e in exps]
        ps = [P.PLANNING[e][planner][3] for e in exps]
        off = (2 * j - 2.5) * w
        lo = np.minimum(s, 0.9 * np.asarray(m))  # a log axis cannot show mean - std <= 0
        ax.errorbar(x + off, m, yerr=[lo, s], fmt="o", color=COLORS[planner], ms=4, capsize=2, label=f"{planner} (ours)")
        ax.errorbar(x + off + w, pm, yerr=ps, fmt="x", color=COLORS[planner], ms=4, capsize=2, alpha=0.6, label=f"{planner} (paper)")
        ax2.bar(x + (j - 1) * 0.27, [c.get("success", 0) / max(c.get("of", 1), 1) for c in ours], 0.13, color=COLORS[planner], label=f"{planner} (ours)")
        ax2.bar(x + (j - 1) * 0.27 + 0.13, [P.PLANNING[e][planner][0] / P.PLANNING[e][planner][1] for e in exps], 0.13,
                color=COLORS[planner], alpha=0.35, hatch="//", label=f"{planner} (paper)")
    ax.set_yscale("log")
    ax.set_ylabel("planning time (s), mean ± std")
    ax2.set_ylabel("planning success rate")
    ax2.set_ylim(0, 1.05)
    for a in (ax, ax2):
        a.set_xticks(x, exps, rotation=45, fontsize=8)
        a.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=6, ncol=2)
    ax2.legend(fontsize=6, ncol=2, loc="lower right")
    ax.set_title("Table II planning time: ours vs the paper", fontsize=10)
    ax2.set_title("Table II planning success", fontsize=10)
    return _save(fig, path)


def _box_edges(center: np.ndarray, size: np.ndarray, yaw: float) -> list[np.ndarray]:
    c, s = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    corners = np.array([[i, j, k] for i in (-0.5, 0.5) for j in (-0.5, 0.5) for k in (-0.5, 0.5)]) * size @ Rz.T + center
    edges = [(0, 1), (0, 2), (1, 3), (2, 3), (4, 5), (4, 6), (5, 7), (6, 7), (0, 4), (1, 5), (2, 6), (3, 7)]
    return [corners[[a, b]] for a, b in edges]


def rendered_paths(r: dict[str, Any], path: Path) -> Path | None:
    """Six CBiRRT paths (seed 0) in 3-D like Fig. 7(c): pre-bagging orange → blue, bagging blue → red."""
    from bagit.common.scenario import Scenario
    from bagit.scenarios import list_scenarios
    from bagit.services.planner import plan_scenario

    chosen = [p for key in PATH_SCENARIOS for p in list_scenarios() if p.stem.startswith(key)]
    chosen = [p for p in chosen if p.stem in r["planning"]] or chosen[:2]
    if not chosen:
        return None
    cols = 3 if len(chosen) > 2 else len(chosen)
    rows = int(np.ceil(len(chosen) / cols))
    fig = plt.figure(figsize=(3.3 * cols, 3.0 * rows))
    pre_cmap = matplotlib.colors.LinearSegmentedColormap.from_list("pre", ["tab:orange", "tab:blue"])
    bag_cmap = matplotlib.colors.LinearSegmentedColormap.from_list("bag", ["tab:blue", "tab:red"])
    for k, p in enumerate(chosen):
        s = Scenario.from_file(p)
        res = plan_scenario(s, "cbirrt", 0)
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        v = s.object.bottom_vertices()
        vv = np.vstack([v, v[:1]])
        top = vv + s.object.effective_height() * (res.goal.up if res.goal is not None else np.array([0, 0, 1.0]))
        ax.plot(*vv.T, color="k", lw=1.2)
        ax.plot(*top.T, color="0.4", lw=0.8)
        for ob in s.obstacles:
            for e in _box_edges(np.array(ob.center), np.array(ob.size), ob.yaw):
                ax.plot(*e.T, color="k", lw=0.8)
        if res.success:
            n, d = len(res.path), res.dagger_index
            step = max(1, n // 14)
            for i in list(range(0, n, step)) + [d, n - 1]:
                rim = np.vstack([res.path[i], res.path[i][:1]])
                col = pre_cmap(i / max(d, 1)) if i <= d else bag_cmap((i - d) / max(n - 1 - d, 1))
                ax.plot(*rim.T, color=col, lw=0.8)
        ax.set_title(f"{_short(p.stem)}: {f'{len(res.path)} nodes' if res.success else 'no path'}", fontsize=8)
        ax.tick_params(labelsize=5)
        ax.view_init(elev=22, azim=-60)
        pts = res.path.reshape(-1, 3) if res.success else v
        lo, hi = pts.min(0), pts.max(0)
        mid, half = (lo + hi) / 2, (hi - lo).max() / 2 + 0.02
        ax.set_xlim(mid[0] - half, mid[0] + half)
        ax.set_ylim(mid[1] - half, mid[1] + half)
        ax.set_zlim(mid[2] - half, mid[2] + half)
    return _save(fig, path)


def soi_stats(r: dict[str, Any], path: Path) -> Path:
    """c1 over all placements (histogram) and mean c1 per shape, with the paper's mean marked."""
    ok = [x for x in r["placement_runs"] if x["valid"]]
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(9, 3.2))
    ax.hist([x["c1"] for x in ok], bins=30, color="tab:blue", alpha=0.8)
    ax.axvline(P.SOI_STATS["c1"], color="tab:red", ls="--", label=f"paper mean {P.SOI_STATS['c1']}")
    ax.axvline(np.mean([x["c1"] for x in ok]), color="k", ls=":", label="our mean")
    ax.set_xlabel("c1 = max F_e of V in the bagging ellipse")
    ax.set_ylabel("placements")
    ax.legend(fontsize=7)
    shapes = r["placements"]["per_shape"]
    names = list(shapes)
    ax2.bar(np.arange(len(names)), [shapes[n]["c1_mean"] or 0 for n in names], color="tab:blue")
    ax2.errorbar(np.arange(len(names)), [shapes[n]["c1_mean"] or 0 for n in names],
                 yerr=[[0] * len(names), [(shapes[n]["c1_max"] or 0) - (shapes[n]["c1_mean"] or 0) for n in names]], fmt="none", color="k", capsize=2)
    ax2.set_xticks(np.arange(len(names)), names, rotation=60, ha="right", fontsize=7)
    ax2.set_ylabel("mean c1 (bar to max)")
    ax.set_title(f"{len(ok)} placements of {len(names)} shapes", fontsize=10)
    return _save(fig, path)


def manipulation(r: dict[str, Any], path: Path) -> Path | None:
    """Manipulation success rate per experiment and controller, ours (solid) vs the paper (hatched)."""
    if not r["manipulation"]:
        return None
    stems = sorted(r["manipulation"])
    fig, ax = plt.subplots(figsize=(max(6, 0.7 * len(stems) + 2), 3.4))
    x = np.arange(len(stems))
    colors = {"mpc": "tab:green", "ibvs": "tab:blue", "ssvs": "tab:brown"}
    for j, ctrl in enumerate(P.CONTROLLERS):
        ours = [r["manipulation"][s].get(ctrl) for s in stems]
        rate = [np.nan if c is None else c["success"] / c["of"] for c in ours]
        paper = [P.MANIPULATION.get(s[:5], {}).get(ctrl) for s in stems]
        ax.bar(x + (j - 1) * 0.27, rate, 0.13, color=colors[ctrl], label=f"{ctrl} (ours)")
        ax.bar(x + (j - 1) * 0.27 + 0.13, [np.nan if p is None else p[0] / p[1] for p in paper], 0.13, color=colors[ctrl], alpha=0.35, hatch="//",
               label=f"{ctrl} (paper)")
        for xi, c in zip(x + (j - 1) * 0.27, ours, strict=False):
            if c is not None:
                ax.text(xi, 0.02, f"{c['success']}/{c['of']}", rotation=90, fontsize=5, ha="center", va="bottom")
    ax.set_xticks(x, [_short(s) for s in stems], rotation=45, ha="right", fontsize=8)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("manipulation success rate")
    ax.legend(fontsize=6, ncol=3)
    ax.set_title("Manipulation success (missing bars: not run)", fontsize=10)
    return _save(fig, path)


def draw_all(r: dict[str, Any], out_dir: Path) -> list[Path]:
    """Every figure into `out_dir`; returns the files written."""
    out_dir.mkdir(parents=True, exist_ok=True)
    made = [
        planning_times(r, out_dir / "planning_times.png"),
        planning_vs_paper(r, out_dir / "planning_vs_paper.png"),
        rendered_paths(r, out_dir / "paths.png"),
        soi_stats(r, out_dir / "soi_c1.png"),
        manipulation(r, out_dir / "manipulation.png"),
    ]
    stale = out_dir / "manipulation.png"
    if made[-1] is None and stale.exists():
        stale.unlink()  # no closed-loop data now: an old figure would show numbers that are not in the report
    return [p for p in made if p is not None]
