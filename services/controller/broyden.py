"""Online estimate of the deformation Jacobian J (s_t = J u_t, paper eq. 16) by Broyden's rank-one
update, guarded, and the short exploration that initialises it.

The paper's update: J <- J + eps (s - J u) u^T / (u^T u). On real data a tiny u divides noise by
almost zero and a glitch in the SOI can throw J far off, so the update is skipped for tiny or
non-finite steps and J's Frobenius norm is bounded.
"""

from __future__ import annotations

import numpy as np

from bagit.common.errors import NumericalFailure
from bagit.common.params import RigidTurns

MIN_STEP_NORM = 1e-4  # skip updates for ||u|| below this (m / rad per update)
MAX_JACOBIAN_NORM = 50.0  # Frobenius bound on J (SOI metres per input unit)
# rigid_pair_turns "measured": a turn across the grippers' line counts as measured once the applied
# updates' steps along it, in input units (a full C7 step is 1), add up to this in squares (`seen`).
TURN_SEEN = 2.0


class BroydenJacobian:
    """J: (3 n_x, 12), updated from (u, s) pairs.

    input_scale `(12,)` (optional): the natural unit of each input, e.g. its per-tick C7 limit. The
    rank-one update then uses the inner product that unit defines (Broyden's update is the least
    change of J in that norm): J <- J + eps (s - J u) wᵀ / (uᵀ w), w = u / scale². Without it,
    metres and radians are mixed in uᵀu and a step of 0.01 rad outweighs one of 1.7 mm 36 times over,
    so every correction, noise included, lands on the rotation columns. Tiny steps are then judged in
    those units too (`min_step` becomes a share of one full-speed tick).
    """

    def __init__(
        self,
        J0: np.ndarray,
        epsilon: float = 0.3,
        max_norm: float = MAX_JACOBIAN_NORM,
        min_step: float = MIN_STEP_NORM,
        input_scale: np.ndarray | None = None,
    ):
        J0 = np.array(J0, dtype=float)
        if J0.ndim != 2 or not np.all(np.isfinite(J0)):
            raise ValueError(f"J0 must be a finite 2-D matrix, got shape {J0.shape}")
        if not 0.0 < epsilon <= 1.0:
            raise ValueError(f"Broyden rate epsilon must be in (0, 1], got {epsilon}")
        if not max_norm > 0.0:
            raise ValueError(f"max_norm must be positive, got {max_norm}")
        if input_scale is not None:
            input_scale = np.asarray(input_scale, dtype=float).ravel()
            if input_scale.shape != (J0.shape[1],) or not np.all(input_scale > 0) or not np.all(np.isfinite(input_scale)):
                raise ValueError(f"input_scale must be {J0.shape[1]} positive finite units")
        n = np.linalg.norm(J0)
        self.J = J0 * (max_norm / n) if n > max_norm else J0
        self.epsilon = epsilon
        self.max_norm = max_norm
        self.min_step = min_step
        self.input_scale = input_scale
        self.updates = 0
        self.skipped = 0
        self.clamped = 0
        self._seen = np.zeros((J0.shape[1], J0.shape[1]))  # sum of v vᵀ over applied updates, v = u / scale

    def update(self, u: np.ndarray, s: np.ndarray) -> bool:
        """One Broyden step from input `u (12,)` and the SOI change `s (3 n_x,)` it caused. True if applied."""
        u = np.asarray(u, dtype=float).ravel()
        s = np.asarray(s, dtype=float).ravel()
        if u.shape[0] != self.J.shape[1] or s.shape[0] != self.J.shape[0]:
            raise ValueError(f"u {u.shape} and s {s.shape} do not fit J {self.J.shape}")
        w = u if self.input_scale is None else u / self.input_scale**2
        uw = float(u @ w)
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(s))) or not uw >= self.min_step**2:
            self.skipped += 1
            return False
        J = self.J + self.epsilon * np.outer(s - self.J @ u, w) / uw
        n = np.linalg.norm(J)
        if n > self.max_norm:
            J *= self.max_norm / n
            self.clamped += 1
        self.J = J
        self.updates += 1
        v = u if self.input_scale is None else u / self.input_scale
        self._seen += np.outer(v, v)
        return True

    def seen(self, direction: np.ndarray) -> float:
        """How much of input `direction (12,)` the applied updates have measured: the sum of their steps'
        squared components along it, in input units (a full C7 step along it adds 1)."""
        d = np.asarray(direction, dtype=float).ravel()
        d = d if self.input_scale is None else d / self.input_scale
        n = float(np.linalg.norm(d))
        if not n > 0.0:
            raise ValueError("a zero direction")
        d = d / n
        return float(d @ self._seen @ d)

    def pin(self, basis: np.ndarray, response: np.ndarray) -> None:
        """Make J map each input direction of `basis (12, k)` to its known SOI change `response (3 n_x, k)`,
        changing J least (in the input units of the rank-one update): J's action on directions
        orthogonal to the basis in that inner product is kept. Not counted as an update; J's norm
        bound is left to the next update (the pinned part is a model, not a measurement)."""
        B = np.asarray(basis, dtype=float)
        Rsp = np.asarray(response, dtype=float)
        if B.shape[0] != self.J.shape[1] or Rsp.shape != (self.J.shape[0], B.shape[1]):
            raise ValueError(f"basis {B.shape} and response {Rsp.shape} do not fit J {self.J.shape}")
        self.J = pinned(self.J, B, Rsp, self.input_scale)


def pinned(J: np.ndarray, basis: np.ndarray, response: np.ndarray, input_scale: np.ndarray | None = None) -> np.ndarray:
    """`J (m, n)` changed least so that J @ basis = response (`basis (n, k)`, `response (m, k)`): the
    least change in the inner product uᵀ diag(1/scale²) v of `input_scale (n,)` (Euclidean without),
    J' = J + (response - J B)(Bᵀ W B)⁻¹ Bᵀ W. Directions W-orthogonal to the basis keep J's action."""
    B = np.asarray(basis, dtype=float)
    W = np.ones(B.shape[0]) if input_scale is None else 1.0 / np.asarray(input_scale, dtype=float) ** 2
    BW = B.T * W  # (k, n) = Bᵀ W
    try:
        K = np.linalg.solve(BW @ B, BW)
    except np.linalg.LinAlgError as e:
        raise NumericalFailure(f"the pinned directions are degenerate: {e}") from None
    return J + (np.asarray(response, dtype=float) - J @ B) @ K


def turn_axes(p_left: np.ndarray, p_right: np.ndarray, turns: RigidTurns = "all") -> np.ndarray:
    """The unit axes `(3, 3)` of the pair's rigid turns: x, y, z ("all"), or the grippers' line, then the
    horizontal axis across it and the one across both ("measured")."""
    if turns == "all":
        return np.eye(3)
    line = np.asarray(p_right, dtype=float) - np.asarray(p_left, dtype=float)
    n = float(np.linalg.norm(line))
    if not n > 1e-6:
        raise NumericalFailure(f"the grippers are {n:.2g} m apart: no line between them to turn about")
    e = line / n
    a = np.cross(e, [0.0, 0.0, 1.0])
    na = float(np.linalg.norm(a))
    a = a / na if na > 1e-6 else np.array([1.0, 0.0, 0.0])  # a vertical line: any axis across it
    return np.stack([e, a, np.cross(e, a)])


def rigid_pair_motions(p_left: np.ndarray, p_right: np.ndarray, turns: RigidTurns = "all") -> np.ndarray:
    """The inputs `(12, 3 + k)` that move both grippers as one rigid body: a unit translation along x, y,
    z, then a unit turn (rad) about each of the k `turn_axes` through their midpoint (each gripper turns
    and is carried round it). u's layout is `dual_arm`'s: [left dp drot, right dp drot], world frame, each
    gripper turned about its own origin."""
    pl, pr = np.asarray(p_left, dtype=float), np.asarray(p_right, dtype=float)
    m = 0.5 * (pl + pr)
    axes = turn_axes(pl, pr, turns)
    B = np.zeros((12, 3 + len(axes)))
    for k in range(3):
        B[[k, 6 + k], k] = 1.0
    for j, e in enumerate(axes):
        B[3:6, 3 + j] = B[9:12, 3 + j] = e
        B[0:3, 3 + j] = np.cross(e, pl - m)
        B[6:9, 3 + j] = np.cross(e, pr - m)
    return B


def rigid_pair_response(x: np.ndarray, p_left: np.ndarray, p_right: np.ndarray, turns: RigidTurns = "all") -> np.ndarray:
    """The SOI change `(3 n_x, 3 + k)` of each of `rigid_pair_motions`' inputs if the rim `x (n_x, 3)` moves
    with the grippers as one body: a translation moves every point by it, a turn ω about the midpoint
    m moves y by ω × (y - m).

    Why a model here and not a measurement: each gripper clamps a stretch of the rim, so when the
    two move as one body the rim goes with them whatever the fabric, while the exploration's pushes
    measure these directions mostly as the bag's own motion (a hanging bag moves a few mm a point
    between frames, as much as a push moves it). Traced: a turn of both grippers about their line
    turned the rim nearly one to one (docs/experiments.md, "a free arc hangs low"), while the
    measured J had it 3-5x too large and nearly orthogonal."""
    y = np.asarray(x, dtype=float).reshape(-1, 3)
    m = 0.5 * (np.asarray(p_left, dtype=float) + np.asarray(p_right, dtype=float))
    axes = turn_axes(p_left, p_right, turns)
    n = y.shape[0]
    out = np.zeros((3 * n, 3 + len(axes)))
    for k in range(3):
        out[k::3, k] = 1.0
    for j, e in enumerate(axes):
        out[:, 3 + j] = np.cross(e, y - m).ravel()
    return out


def exploration_inputs(step_m: float = 0.004, step_rad: float = 0.04) -> np.ndarray:
    """The exploratory motions `(24, 12)`: each input direction forward then back, bounded in size."""
    scale = np.array([step_m] * 3 + [step_rad] * 3 + [step_m] * 3 + [step_rad] * 3)
    out = []
    for i in range(12):
        e = np.zeros(12)
        e[i] = scale[i]
        out += [e, -e]
    return np.asarray(out)


def jacobian_from_exploration(inputs: np.ndarray, changes: np.ndarray) -> np.ndarray:
    """Finite-difference J `(3 n_x, 12)` from exploratory inputs `(k, 12)` and the SOI changes `(k, 3 n_x)`
    they caused: the least-squares J with changes ~ inputs @ J^T."""
    U, S = np.asarray(inputs, float), np.asarray(changes, float)
    if not (np.all(np.isfinite(U)) and np.all(np.isfinite(S))):
        raise NumericalFailure("the exploration measured non-finite SOI changes: no Jacobian from them")
    try:
        Jt, *_ = np.linalg.lstsq(U, S, rcond=None)
    except np.linalg.LinAlgError as e:
        raise NumericalFailure(f"least squares for the exploration Jacobian failed: {e}") from None
    if not np.all(np.isfinite(Jt)):
        raise NumericalFailure("the exploration Jacobian is not finite")
    return Jt.T


class Exploration:
    """The short, bounded exploratory motion that seeds J at the start of a run.

    Each of the 12 input directions is pushed out at its C7 limit for `push_ticks` ticks, held for
    `settle_ticks`, pushed back the same way and held again: the mounts end where they started and
    every push moves a gripper at most `push_ticks * u_max` (6.7 mm / 0.04 rad at the defaults). The
    SOI change over a whole push (not one tick, which is mostly camera noise) gives one finite
    difference; the 24 of them give J by least squares.

    Use as a state machine: `next_input(x, moved)` with each new SOI `x (3 n_x,)` and the grippers'
    measured motion since the last call returns the input to apply this tick, or None once
    finished; then `jacobian()`. Each push is measured by what the grippers did, not by what was
    asked of them: an arm driver that slowed or dropped a command does not bias J.
    """

    def __init__(self, u_max: np.ndarray, push_ticks: int = 4, settle_ticks: int = 2):
        u_max = np.asarray(u_max, dtype=float).ravel()
        if u_max.shape != (12,) or not np.all(u_max > 0) or not np.all(np.isfinite(u_max)):
            raise ValueError("u_max must be 12 positive finite per-tick limits")
        if push_ticks < 1 or settle_ticks < 0:
            raise ValueError("push_ticks must be >= 1 and settle_ticks >= 0")
        # One segment per push: its per-tick inputs (push then settle).
        self._segments: list[list[np.ndarray]] = []
        for i in range(12):
            e = np.zeros(12)
            e[i] = u_max[i]
            for sign in (1.0, -1.0):
                self._segments.append([sign * e] * push_ticks + [np.zeros(12)] * settle_ticks)
        self._seg = 0
        self._tick = 0
        self._finished = False
        self._x_start: np.ndarray | None = None
        self._u_sum = np.zeros(12)
        self._u_last = np.zeros(12)
        self.inputs: list[np.ndarray] = []  # (12,) summed input of each finished push
        self.changes: list[np.ndarray] = []  # (3 n_x,) SOI change it caused

    @property
    def total_ticks(self) -> int:
        """Ticks with an exploratory input (the call that returns None comes one tick later)."""
        return sum(len(s) for s in self._segments)

    @property
    def done(self) -> bool:
        """Every push made and measured: `jacobian()` is ready."""
        return self._finished

    def progress(self) -> float:
        return len(self.inputs) / len(self._segments)

    def next_input(self, x: np.ndarray, moved: np.ndarray | None = None) -> np.ndarray | None:
        """The exploratory input for this tick given the current SOI `x (3 n_x,)` and `moved (12,)`,
        the grippers' motion since the last call (None: the last input, done exactly); None when finished.

        Ticks on which the caller holds (no valid SOI) simply do not call this: the push pauses with
        the arms still, and its SOI change is still measured between two valid SOIs.
        """
        if self._finished:
            return None
        x = np.asarray(x, dtype=float).ravel()
        if self._x_start is not None:  # the motion since the last call belongs to the push it came from
            self._u_sum += self._u_last if moved is None else np.asarray(moved, dtype=float).ravel()
        if self._tick == 0:
            if self._x_start is not None:  # x is the SOI after the previous push settled: measure it
                self.inputs.append(self._u_sum.copy())
                self.changes.append(x - self._x_start)
            if self._seg == len(self._segments):
                self._finished = True
                return None
            self._x_start, self._u_sum = x.copy(), np.zeros(12)
        u = self._segments[self._seg][self._tick]
        self._u_last = u
        self._tick += 1
        if self._tick == len(self._segments[self._seg]):
            self._seg, self._tick = self._seg + 1, 0
        return u.copy()

    def jacobian(self) -> np.ndarray:
        """J `(3 n_x, 12)` by least squares over the measured pushes."""
        if not self.inputs:
            raise ValueError("no exploratory push measured yet")
        return jacobian_from_exploration(np.asarray(self.inputs), np.asarray(self.changes))
