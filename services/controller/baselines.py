"""The paper's comparison controllers (Table II), on the same SOI, guard, exploration and Broyden J.

ibvs: image-based visual servoing, u = -λ Ĵ⁺ e with e the error to the next subgoal on the path,
      one step, no prediction, no constraint but C7.
ssvs: shape servoing with an adaptive (Broyden) Jacobian straight to the final goal g*: the same
      law aimed at g* with no path, so nothing keeps the rim off the object on the way.
"""

from __future__ import annotations

import numpy as np

from bagit.common.errors import NumericalFailure
from bagit.common.params import MethodParams
from bagit.services.controller.servo import ServoBase, scale_into_box

IBVS_GAIN = 0.5  # λ: the share of the (linearised) error removed per tick, before C7
PINV_RCOND = 1e-6


def servo_law(J: np.ndarray, x: np.ndarray, target: np.ndarray, gain: float, u_max: np.ndarray) -> np.ndarray:
    """u = -gain Ĵ⁺ (x - target) `(12,)` for `J (3 n_x, 12)`, shrunk as a whole into C7 `u_max (12,)`
    (keeping its direction: clipping components one by one would turn it)."""
    e = np.asarray(x, dtype=float) - np.asarray(target, dtype=float)
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(e))):
        raise NumericalFailure("servo law: non-finite Jacobian or error")
    try:
        u = -gain * np.linalg.lstsq(J, e, rcond=PINV_RCOND)[0]
    except np.linalg.LinAlgError as err:
        raise NumericalFailure(f"servo law: pseudo-inverse of J failed: {err}") from None
    return scale_into_box(u, u_max)


class IbvsController(ServoBase):
    name = "ibvs"

    def __init__(self, params: MethodParams, n_x: int, gain: float = IBVS_GAIN, **kwargs):
        super().__init__(params, n_x, **kwargs)
        self.gain = gain

    def _law(self, J, x, target, grippers):
        return servo_law(J, x, target, self.gain, self.u_max), 0.0, None


class SsvsController(IbvsController):
    name = "ssvs"
    aims_at_goal = True
