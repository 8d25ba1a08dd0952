"""Colours of the dashboard's scene, chosen to match the paper's figures.

Fig. 2 draws the cloud P_t, the SOI as a red curve, V as yellow dots and the bagging ellipse in
green; Fig. 7(c) fades the path's rims from orange (g0) to blue (g†) in pre-bagging and from blue
to red (g*) in bagging. Colours are uint8 RGB.
"""

from __future__ import annotations

import numpy as np

ORANGE = np.array([245, 140, 30], dtype=float)  # g0, start of the pre-bagging fan
BLUE = np.array([40, 90, 225], dtype=float)  # g†, where bagging starts
RED = np.array([215, 25, 35], dtype=float)  # g*, the end of bagging
SOI = (230, 20, 60)  # the live SOI (a brighter red than g*, drawn thicker)
ELLIPSE = (30, 170, 60)  # the bagging ellipse
VERTICES = (235, 195, 0)  # the object's bottom outline V
OBJECT = (160, 160, 170)
OBSTACLE = (40, 40, 45)
ARM_LINK = (200, 205, 215)
ARM_JOINT = (70, 80, 95)
CAMERA = (20, 20, 20)
SUBGOAL = (255, 0, 200)  # the next subgoal, a colour the fan never uses
BACKGROUND = np.array([255, 255, 255], dtype=float)

# Anchors of a perceptually ordered ramp (viridis) for clouds that come without colours.
_RAMP = np.array([[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]], dtype=float)


def _lerp(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a[None] + (b - a)[None] * t[:, None]


def fan_colors(n_nodes: int, dagger_index: int) -> np.ndarray:
    """`(n_nodes, 3)` uint8: orange -> blue over nodes 0..dagger_index, blue -> red after it (Fig. 7(c))."""
    if n_nodes <= 0:
        return np.zeros((0, 3), dtype=np.uint8)
    d = int(np.clip(dagger_index, 0, n_nodes - 1))
    i = np.arange(n_nodes, dtype=float)
    pre = _lerp(ORANGE, BLUE, i[: d + 1] / max(d, 1)) if d > 0 else BLUE[None].copy()
    post_n = n_nodes - d - 1
    post = _lerp(BLUE, RED, np.arange(1, post_n + 1, dtype=float) / post_n) if post_n > 0 else np.zeros((0, 3))
    return np.round(np.vstack([pre, post])).astype(np.uint8)


def fade(colors: np.ndarray, amount: float) -> np.ndarray:
    """`colors (n, 3)` blended toward the white background by `amount` in [0, 1] (lines carry no alpha)."""
    c = np.asarray(colors, dtype=float)
    return np.round(c + (BACKGROUND - c) * float(np.clip(amount, 0.0, 1.0))).astype(np.uint8)


def height_colors(z: np.ndarray) -> np.ndarray:
    """`(n, 3)` uint8 colours of heights `z (n,)` on the viridis ramp, low to high."""
    z = np.asarray(z, dtype=float)
    if len(z) == 0:
        return np.zeros((0, 3), dtype=np.uint8)
    lo, hi = float(np.min(z)), float(np.max(z))
    t = (z - lo) / (hi - lo) if hi > lo else np.zeros_like(z)
    x = t * (len(_RAMP) - 1)
    k = np.minimum(x.astype(int), len(_RAMP) - 2)
    f = (x - k)[:, None]
    return np.round(_RAMP[k] * (1 - f) + _RAMP[k + 1] * f).astype(np.uint8)
