"""BimaManip's learned SOI dynamics (Zhou et al., arXiv 2401.11432): a graph neural network that
predicts how the rim's points move when the two grippers move, and the gradient-based MPC that plans
the grippers' motion through it. JAX and Equinox (the `learn` extra): import this module only where
the model is used (the bimamanip controller's reset, the training bench), never at a package's top:
`bagit up`'s fork server preloads the controller package and must not load JAX (its thread pools).

The graph (as the paper builds it from the SOI's particles and the grippers): one node per SOI point
`x (n_x, 3)` and one per gripper `(2, 3)` (left, right); edges both ways along the rim's ring, and
both ways between each gripper and every rim point (the model learns which points a gripper drags).
Node inputs: the position relative to the rim's centroid (translation invariance), the node's kind,
and for a gripper node its motion this step; edge inputs: the relative position and distance, the
edge's kind. `ROUNDS` rounds of message passing, then a decoder gives each rim point's displacement.
Treating every rim point alike makes the model blind to where the SOI's numbering starts (perception's
points slide along the rim between frames).

One model step is `MODEL_TICKS` control ticks: the grippers move at most C7 per tick, so a single
tick's change is mostly camera noise; the paper's actions are likewise short motions, not servo ticks.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.typing import ArrayLike

MODEL_TICKS = 5  # control ticks per model step (1/6 s at 30 Hz)
POS_SCALE = 10.0  # positions enter the network in decimetres
ACT_SCALE = 100.0  # gripper motions and predicted displacements in centimetres
HIDDEN = 48  # width of every MLP
ROUNDS = 3  # message-passing rounds
NODE_IN = 3 + 2 + 3  # relative position, kind (rim, gripper), gripper motion (0 on rim nodes)
EDGE_IN = 3 + 1 + 2  # relative position, distance, kind (ring, gripper)
WEIGHTS_FILE = Path(__file__).resolve().parent / "data" / "bimamanip.eqx"
RECORD_FILE = WEIGHTS_FILE.with_suffix(".json")


def edges(n_x: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(senders, receivers, kind) `(n_e,)` of the graph over n_x rim nodes and the grippers n_x, n_x + 1;
    kind 0: along the ring, 1: between a gripper and a rim point."""
    i = np.arange(n_x)
    ring_s, ring_r = np.concatenate([i, (i + 1) % n_x]), np.concatenate([(i + 1) % n_x, i])
    g = np.repeat([n_x, n_x + 1], n_x)
    r = np.tile(i, 2)
    s = np.concatenate([ring_s, g, r])
    rcv = np.concatenate([ring_r, r, g])
    kind = np.concatenate([np.zeros(2 * n_x, int), np.ones(4 * n_x, int)])
    return s, rcv, kind


class SoiGnn(eqx.Module):
    """x_{t+1} = x_t + f(x_t, grippers_t, a_t): `x (n_x, 3)`, grippers `(2, 3)`, a `(2, 3)` (m)."""

    enc_node: eqx.nn.MLP
    enc_edge: eqx.nn.MLP
    messages: list[eqx.nn.MLP]
    updates: list[eqx.nn.MLP]
    dec: eqx.nn.MLP

    def __init__(self, key: jax.Array, hidden: int = HIDDEN, rounds: int = ROUNDS):
        keys = jax.random.split(key, 3 + 2 * rounds)
        self.enc_node = eqx.nn.MLP(NODE_IN, hidden, hidden, 1, activation=jax.nn.silu, key=keys[0])
        self.enc_edge = eqx.nn.MLP(EDGE_IN, hidden, hidden, 1, activation=jax.nn.silu, key=keys[1])
        self.messages = [eqx.nn.MLP(3 * hidden, hidden, hidden, 1, activation=jax.nn.silu, key=k) for k in keys[3 : 3 + rounds]]
        self.updates = [eqx.nn.MLP(2 * hidden, hidden, hidden, 1, activation=jax.nn.silu, key=k) for k in keys[3 + rounds :]]
        self.dec = eqx.nn.MLP(hidden, 3, hidden, 1, activation=jax.nn.silu, key=keys[2])

    def __call__(self, x: jax.Array, grippers: jax.Array, a: jax.Array) -> jax.Array:
        """The rim's displacement `(n_x, 3)` (m) over one model step."""
        n_x = x.shape[0]
        s, r, kind = edges(n_x)
        c = jnp.mean(x, axis=0)
        pos = jnp.concatenate([x, grippers]) - c  # (n_x + 2, 3)
        is_grip = jnp.concatenate([jnp.zeros(n_x), jnp.ones(2)])[:, None]
        act = jnp.concatenate([jnp.zeros((n_x, 3)), a * ACT_SCALE])
        nodes = jnp.concatenate([pos * POS_SCALE, 1.0 - is_grip, is_grip, act], axis=1)
        d = (pos[s] - pos[r]) * POS_SCALE
        e_in = jnp.concatenate([d, jnp.linalg.norm(d, axis=1, keepdims=True), jax.nn.one_hot(kind, 2)], axis=1)
        h = jax.vmap(self.enc_node)(nodes)
        e = jax.vmap(self.enc_edge)(e_in)
        for msg, upd in zip(self.messages, self.updates, strict=True):
            m = jax.vmap(msg)(jnp.concatenate([h[s], h[r], e], axis=1))
            agg = jax.ops.segment_sum(m, r, num_segments=n_x + 2)
            h = h + jax.vmap(upd)(jnp.concatenate([h, agg], axis=1))
        return jax.vmap(self.dec)(h[:n_x]) / ACT_SCALE


def rollout(model: SoiGnn, x: jax.Array, grippers: jax.Array, actions: jax.Array) -> jax.Array:
    """The SOIs `(H, n_x, 3)` after each of `actions (H, 2, 3)`, from `x (n_x, 3)` and `grippers (2, 3)`."""

    def one(carry: tuple[jax.Array, jax.Array], a: jax.Array) -> tuple[tuple[jax.Array, jax.Array], jax.Array]:
        xk, gk = carry
        xn = xk + model(xk, gk, a)
        return (xn, gk + a), xn

    _, xs = jax.lax.scan(one, (x, grippers), actions)
    return xs


# ---- training ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Transitions:
    """Simulated transitions: `x (N, n_x, 3)`, `grippers (N, 2, 3)`, `u (N, 12)` (the pose increment over
    one model step, the u layout; only its translations [0:3] and [6:9] move here), `x_next (N, n_x, 3)`."""

    x: np.ndarray
    grippers: np.ndarray
    u: np.ndarray
    x_next: np.ndarray

    @property
    def a(self) -> np.ndarray:
        """The grippers' translations `(N, 2, 3)`."""
        return np.stack([self.u[:, 0:3], self.u[:, 6:9]], axis=1)

    def take(self, idx: np.ndarray) -> Transitions:
        return Transitions(self.x[idx], self.grippers[idx], self.u[idx], self.x_next[idx])


def batch_loss(model: SoiGnn, x: ArrayLike, g: ArrayLike, a: ArrayLike, x_next: ArrayLike) -> jax.Array:
    """Mean square error of the predicted displacement, in centimetres squared."""
    x, x_next = jnp.asarray(x), jnp.asarray(x_next)
    pred = jax.vmap(model)(x, jnp.asarray(g), jnp.asarray(a))
    return jnp.mean(jnp.sum(((pred - (x_next - x)) * ACT_SCALE) ** 2, axis=-1))


def train(data: Transitions, *, seed: int, epochs: int, batch: int = 64, lr: float = 2e-3, noise_m: float = 5e-4,
          hidden: int = HIDDEN, rounds: int = ROUNDS, log: Any = None) -> tuple[SoiGnn, list[float]]:
    """A model of `hidden` width and `rounds` rounds trained on `data` (Adam, cosine-decayed rate, inputs
    jittered by `noise_m` as perception's SOI is); the mean training loss of each epoch."""
    key = jax.random.PRNGKey(seed)
    key, init = jax.random.split(key)
    model = SoiGnn(init, hidden=hidden, rounds=rounds)
    steps_per_epoch = max(len(data.x) // batch, 1)
    opt = optax.adam(optax.cosine_decay_schedule(lr, epochs * steps_per_epoch, alpha=0.05))
    state = opt.init(eqx.filter(model, eqx.is_array))

    @eqx.filter_jit
    def step(model: SoiGnn, state: Any, key: jax.Array, x: ArrayLike, g: ArrayLike, a: ArrayLike, xn: ArrayLike) -> tuple[SoiGnn, Any, jax.Array]:
        noise = noise_m * jax.random.normal(key, jnp.shape(x))
        loss, grads = eqx.filter_value_and_grad(batch_loss)(model, x + noise, g, a, xn + noise)
        updates, state = opt.update(grads, state, eqx.filter(model, eqx.is_array))
        return eqx.apply_updates(model, updates), state, loss

    rng = np.random.default_rng(seed)
    a_all = data.a
    losses = []
    for epoch in range(epochs):
        order = rng.permutation(len(data.x))
        total = 0.0
        for b in range(steps_per_epoch):
            idx = order[b * batch : (b + 1) * batch]
            key, sub = jax.random.split(key)
            model, state, loss = step(model, state, sub, data.x[idx], data.grippers[idx], a_all[idx], data.x_next[idx])
            total += float(loss)
        losses.append(total / steps_per_epoch)
        if log is not None:
            log.info("epoch %d/%d: loss %.4f cm^2", epoch + 1, epochs, losses[-1])
    return model, losses


def prediction_error_mm(model: SoiGnn, data: Transitions) -> dict[str, float]:
    """One-step prediction error on `data`: the RMS point error (mm) of the model, and of two references:
    the rim standing still, and the rim moving with the grippers' mean motion."""
    pred = np.asarray(eqx.filter_jit(jax.vmap(model))(jnp.asarray(data.x), jnp.asarray(data.grippers), jnp.asarray(data.a)))
    truth = data.x_next - data.x
    rms = lambda d: float(np.sqrt(np.mean(np.sum(d**2, axis=-1))) * 1e3)  # noqa: E731
    rigid = np.broadcast_to(data.a.mean(axis=1)[:, None, :], truth.shape)
    return {"model_mm": rms(pred - truth), "still_mm": rms(truth), "with_grippers_mm": rms(rigid - truth)}


# ---- weights on disk (no pickle: Equinox writes each array as .npy bytes) --------------------


def save(model: SoiGnn, record: dict[str, Any], weights: Path = WEIGHTS_FILE, record_file: Path = RECORD_FILE) -> None:
    """The weights and the JSON record of how they were made (with the shape the loader rebuilds)."""
    weights.parent.mkdir(parents=True, exist_ok=True)
    eqx.tree_serialise_leaves(weights, model)
    record_file.write_text(json.dumps({**record, "architecture": {"hidden": model.dec.width_size, "rounds": len(model.messages)}}, indent=2) + "\n")


def load(weights: Path = WEIGHTS_FILE, record_file: Path = RECORD_FILE) -> SoiGnn:
    """The model saved by `save` (its shape from the record)."""
    arch = json.loads(record_file.read_text())["architecture"]
    skeleton = eqx.filter_eval_shape(SoiGnn, jax.random.PRNGKey(0), hidden=int(arch["hidden"]), rounds=int(arch["rounds"]))  # shapes, no init
    return eqx.tree_deserialise_leaves(weights, skeleton)


# ---- MPC through the model --------------------------------------------------------------------


@dataclass(frozen=True)
class MpcWeights:
    """The cost: the SOI's squared distance to the target (cm², every step, the last `terminal` times),
    `effort` on each step's motion (cm²), and `separation` on the grippers leaving the C6 band (cm²)."""

    terminal: float = 3.0
    effort: float = 0.5
    separation: float = 10.0


def make_planner(model: SoiGnn, horizon: int, iterations: int, a_max: float, lr: float = 0.25,
                 weights: MpcWeights = MpcWeights()) -> Any:
    """A jitted `plan(x, grippers, pending, target, a0, sep_lo, sep_hi) -> (actions (H, 2, 3), cost)`: the
    action sequence minimising the cost from where the SOI `x (n_x, 3)` and the grippers `(2, 3)` will be
    once the motion `pending (2, 3)` in flight is made, by `iterations` steps of projected Adam (steps of
    about `lr` a_max, then clipped into the box: each gripper at most a_max per axis and step, C7 over
    MODEL_TICKS ticks) from the warm start `a0 (H, 2, 3)`. Projected rather than squashed (a_max tanh z):
    a squashed action that saturates has no gradient left to come back with, and a warm start keeps it there."""
    opt = optax.adam(lr * a_max)
    step_w = jnp.ones(horizon).at[-1].set(weights.terminal)

    def cost(acts: jax.Array, x: jax.Array, g: jax.Array, target: jax.Array, lo: jax.Array, hi: jax.Array) -> jax.Array:
        xs = rollout(model, x, g, acts)
        err = jnp.mean(jnp.sum(((xs - target) * ACT_SCALE) ** 2, axis=-1), axis=-1)  # (H,)
        gs = g + jnp.cumsum(acts, axis=0)  # (H, 2, 3)
        sep = jnp.linalg.norm(gs[:, 1] - gs[:, 0], axis=-1)
        out = (jax.nn.relu(lo - sep) + jax.nn.relu(sep - hi)) * ACT_SCALE
        return jnp.sum(step_w * err) + weights.effort * jnp.sum((acts * ACT_SCALE) ** 2) + weights.separation * jnp.sum(out**2)

    grad = jax.value_and_grad(cost)

    @jax.jit
    def plan(x: jax.Array, g: jax.Array, pending: jax.Array, target: jax.Array, a0: jax.Array, lo: jax.Array,
             hi: jax.Array) -> tuple[jax.Array, jax.Array]:
        moving = jnp.any(pending != 0.0)
        x = x + jnp.where(moving, model(x, g, pending), 0.0)
        g = g + pending

        def body(carry: tuple[jax.Array, Any], _: None) -> tuple[tuple[jax.Array, Any], jax.Array]:
            a, st = carry
            c, ga = grad(a, x, g, target, lo, hi)
            upd, st = opt.update(ga, st, a)
            return (jnp.clip(optax.apply_updates(a, upd), -a_max, a_max), st), c

        a0 = jnp.clip(a0, -a_max, a_max)
        (a, _), _ = jax.lax.scan(body, (a0, opt.init(a0)), None, length=iterations)
        return a, cost(a, x, g, target, lo, hi)

    return plan
