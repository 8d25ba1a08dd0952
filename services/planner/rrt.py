"""Sampling-based SOI planners over `SoiSpace`: the paper's CBiRRT (Algorithm 1) and the two
baselines of its Table II, FFG-RRT (forward RRT with goal bias) and TS-RRT (tangent-space RRT).

Each returns the raw node list from start to goal or None; trimming, densifying and smoothing are
shared (`postprocess`).
"""

from __future__ import annotations

import time

import numpy as np
from scipy.spatial import cKDTree

from bagit.common.geometry import align_cyclic
from bagit.services.planner.space import MAX_NODE_STEP_M, SoiSpace, max_step, scale_to_perimeter

GOAL_BIAS = 0.1
CONNECT_STEPS = 60  # greedy extension steps when one tree reaches for the other


class Tree:
    """A tree of rims with nearest-neighbour search on a KD-tree (rebuilt as it doubles) plus a brute-force tail."""

    def __init__(self, root: np.ndarray):
        self.nodes: list[np.ndarray] = [root]
        self.parent: list[int] = [-1]
        self._kd: cKDTree | None = None
        self._kd_n = 0

    def add(self, node: np.ndarray, parent: int) -> int:
        self.nodes.append(node)
        self.parent.append(parent)
        if len(self.nodes) >= 2 * max(self._kd_n, 8):
            self._kd = cKDTree(np.stack([n.ravel() for n in self.nodes]))
            self._kd_n = len(self.nodes)
        return len(self.nodes) - 1

    def nearest(self, x: np.ndarray) -> int:
        q = x.ravel()
        best_i, best_d = -1, np.inf
        if self._kd is not None:
            best_d, best_i = self._kd.query(q)
        tail = np.stack([n.ravel() for n in self.nodes[self._kd_n :]]) if len(self.nodes) > self._kd_n else None
        if tail is not None:
            d = np.linalg.norm(tail - q, axis=1)
            j = int(np.argmin(d))
            if d[j] < best_d:
                best_i, best_d = self._kd_n + j, d[j]
        return int(best_i)

    def branch(self, i: int) -> list[np.ndarray]:
        """Nodes from the root to node i."""
        out = []
        while i >= 0:
            out.append(self.nodes[i])
            i = self.parent[i]
        return out[::-1]


def _extend(space: SoiSpace, tree: Tree, target: np.ndarray) -> int | None:
    i = tree.nearest(target)
    x_new = space.steer(tree.nodes[i], target)
    if max_step(x_new, tree.nodes[i]) < 1e-6 or not space.edge_ok(tree.nodes[i], x_new):
        return None
    return tree.add(x_new, i)


def _connect(space: SoiSpace, tree: Tree, target: np.ndarray, eps: float) -> int | None:
    """Grow `tree` greedily towards `target`; the index of a node within eps of it, or None if blocked."""
    i = tree.nearest(target)
    for _ in range(CONNECT_STEPS):
        if max_step(tree.nodes[i], align_cyclic(target, tree.nodes[i])) <= eps:
            return i
        x_new = space.steer(tree.nodes[i], target)
        if not space.edge_ok(tree.nodes[i], x_new):
            return None
        i = tree.add(x_new, i)
    return None


def cbirrt(space: SoiSpace, start: np.ndarray, goal: np.ndarray, eps: float, max_iter: int, deadline: float) -> tuple[list[np.ndarray] | None, int]:
    """Algorithm 1: two trees, each extended toward a regularised random SOI and then toward the other."""
    trees = (Tree(start), Tree(goal))
    n = len(start)
    for it in range(1, max_iter + 1):
        if time.perf_counter() > deadline:
            return None, it
        x_rand = space.sample_regularized(n)
        a, b = trees if it % 2 else trees[::-1]
        ia = _extend(space, a, x_rand)
        if ia is None:
            continue
        ib = _connect(space, b, a.nodes[ia], eps)
        if ib is not None and space.edge_ok(a.nodes[ia], align_cyclic(b.nodes[ib], a.nodes[ia])):
            pa, pb = a.branch(ia), b.branch(ib)
            path = pa + pb[::-1] if a is trees[0] else pb + pa[::-1]
            return path, it
    return None, max_iter


def _forward_search(
    space: SoiSpace, start: np.ndarray, goal: np.ndarray, eps: float, max_iter: int, deadline: float, extend
) -> tuple[list[np.ndarray] | None, int]:
    """One tree from the start, grown by `extend(tree, target)` toward the goal (with probability
    GOAL_BIAS) or a regularised random SOI, until a node can be joined to the goal."""
    tree = Tree(start)
    n = len(start)
    for it in range(1, max_iter + 1):
        if time.perf_counter() > deadline:
            return None, it
        target = goal if space.rng.random() < GOAL_BIAS else space.sample_regularized(n)
        i = extend(space, tree, target)
        if i is not None and max_step(tree.nodes[i], goal) <= eps and space.edge_ok(tree.nodes[i], goal):
            return tree.branch(i) + [goal], it
    return None, max_iter


def ffg_rrt(space: SoiSpace, start: np.ndarray, goal: np.ndarray, eps: float, max_iter: int, deadline: float) -> tuple[list[np.ndarray] | None, int]:
    """Forward-growing RRT from the start, steered to the goal with probability GOAL_BIAS."""
    return _forward_search(space, start, goal, eps, max_iter, deadline, _extend)


def _tangent_extend(space: SoiSpace, tree: Tree, target: np.ndarray) -> int | None:
    """A step from the nearest node in the tangent space of the perimeter constraint (the direction's
    component along the perimeter gradient removed), projected back onto the constraint."""
    i = tree.nearest(target)
    x = tree.nodes[i]
    d = align_cyclic(target, x) - x
    grad = _perimeter_gradient(x)
    d = d - (np.sum(d * grad) / max(np.sum(grad * grad), 1e-12)) * grad
    m = np.linalg.norm(d, axis=1).max()
    if m < 1e-9:
        return None
    x_new = scale_to_perimeter(x + d * min(1.0, space.step_m / m), space.perimeter)
    if not space.edge_ok(x, x_new):
        return None
    return tree.add(x_new, i)


def ts_rrt(space: SoiSpace, start: np.ndarray, goal: np.ndarray, eps: float, max_iter: int, deadline: float) -> tuple[list[np.ndarray] | None, int]:
    """Tangent-space RRT: every extension is a tangent step projected back (`_tangent_extend`)."""
    return _forward_search(space, start, goal, eps, max_iter, deadline, _tangent_extend)


def _perimeter_gradient(rim: np.ndarray) -> np.ndarray:
    """d(perimeter)/d(points) `(n, 3)`: the unit vectors from each point's neighbours towards it."""
    fwd = rim - np.roll(rim, -1, axis=0)
    bwd = rim - np.roll(rim, 1, axis=0)
    return fwd / np.linalg.norm(fwd, axis=1, keepdims=True) + bwd / np.linalg.norm(bwd, axis=1, keepdims=True)


PLANNERS = {"cbirrt": cbirrt, "ffg-rrt": ffg_rrt, "ts-rrt": ts_rrt}


def postprocess(space: SoiSpace, path: list[np.ndarray], shortcuts: int = 40, smooth_passes: int = 3) -> list[np.ndarray]:
    """Trim (random shortcuts), smooth (local averaging kept only where valid) and densify so no
    point moves more than the step bound between consecutive nodes. Ends are kept as they are."""
    path = [align_cyclic(p, path[0]) if k else p for k, p in enumerate(path)]
    rng = space.rng
    for _ in range(shortcuts):
        if len(path) < 3:
            break
        i, j = sorted(rng.choice(len(path), 2, replace=False))
        if j - i > 1 and space.edge_ok(path[i], path[j]):
            path = path[: i + 1] + path[j:]
    path = densify(space, path, space.step_m)
    for _ in range(smooth_passes):
        for k in range(1, len(path) - 1):
            cand = space.project(0.5 * path[k] + 0.25 * (path[k - 1] + path[k + 1]))
            if space.valid(cand) and space.edge_ok(path[k - 1], cand) and space.edge_ok(cand, path[k + 1]):
                path[k] = cand
    return densify(space, path, min(space.step_m, MAX_NODE_STEP_M))


def densify(space: SoiSpace, path: list[np.ndarray], step: float) -> list[np.ndarray]:
    """Insert projected intermediate rims so consecutive nodes differ by at most `step` per point."""
    out = [path[0]]
    for a, b in zip(path[:-1], path[1:], strict=False):
        k = int(np.ceil(max_step(a, b) / step - 1e-9))
        for s in np.linspace(0.0, 1.0, max(k, 1) + 1)[1:-1]:
            out.append(space.project(a + s * (b - a)))
        out.append(b)
    return out
