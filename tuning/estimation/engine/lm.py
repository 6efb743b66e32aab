"""The damped least-squares step every fit of the engine takes (NumPy or JAX arrays).

Levenberg-Marquardt with Marquardt's diagonal scaling: the step solves
(J^T J + lam D) delta = -J^T r, D the diagonal of J^T J (a column the data do not see gets a
tiny floor so the system stays solvable). lam -> 0 is the Gauss-Newton step; a large lam a
short step along the scaled gradient.
"""

from __future__ import annotations

import numpy as np


def marquardt_step(jtj, g, lam, free=None, xp=np):
    """The step delta for damping ``lam`` from J^T J (``jtj``) and J^T r (``g``); ``free``: 1 for
    the entries that move, 0 for those held (their delta is 0)."""
    d = xp.diag(jtj)
    if free is None:
        free = xp.ones_like(d)
    reg = xp.where(free > 0, lam * (d + 1e-9 * xp.max(d)) + 1e-30, 1.0)
    return -xp.linalg.solve(jtj + xp.diag(reg), g) * free


def gauss_newton_step(jac, r):
    """The undamped step: the least-squares solution of J delta = -r, columns scaled to unit
    norm first (the parameters' units differ by orders of magnitude)."""
    scale = np.linalg.norm(jac, axis=0)
    scale[scale == 0] = 1.0
    step, *_ = np.linalg.lstsq(jac / scale, -np.asarray(r), rcond=None)
    return step / scale
