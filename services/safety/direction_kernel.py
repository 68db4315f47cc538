"""Compiled (numba) normal equations of the retargeting by directions (one Levenberg–Marquardt
iteration's linear system, :mod:`services.safety.direction_retarget`).

Same math as :func:`shared.torso_frame.robot_arm_directions` for the robot's torso frame F_T and
its arm segments' directions, with their Jacobians, as scalar loops: ~100 numpy calls of a few
small arrays become one call of a few microseconds inside the control tick.
"""

from __future__ import annotations

import numpy as np

from services.safety.barriers import kernel as _kernel  # noqa: F401  (sets numba's disk cache folder first)
from numba import njit  # noqa: E402


@njit(cache=True, nogil=True)
def direction_normal_equations(endpoints: np.ndarray, jacobians: np.ndarray, frame: np.ndarray, capsules: np.ndarray,
                               targets: np.ndarray, moving: np.ndarray, damping: float, min_segment: float,
                               hessian: np.ndarray, gradient: np.ndarray) -> bool:
    """JᵀJ + λI into ``hessian`` (m, m) and Jᵀ(p − d) into ``gradient`` (m,) over the columns ``moving``
    (m,) of the joints; False (outputs undefined) if the robot's torso frame is degenerate.

    ``endpoints`` (C, 2, 3) and ``jacobians`` (C, 2, 3, n) the robot's capsules; ``frame`` (3,) the
    capsules (torso, left upper arm, right upper arm) whose first endpoints are the pelvis and the
    shoulders of F_T; ``capsules`` (k,) the segments (a → b) compared with ``targets`` (k, 3), unit
    directions p in F_T. d = R û, J = R (I − û ûᵀ)(J_b − J_a)/‖b − a‖ with R's rows e_x, e_y, e_z
    (held fixed: the torso frame moves with the waist, not with the arms).
    """
    pelvis = endpoints[frame[0], 0]
    left = endpoints[frame[1], 0]
    right = endpoints[frame[2], 0]
    up = 0.5 * (left + right) - pelvis
    length = np.sqrt(np.sum(up * up))
    if not length >= min_segment:
        return False
    e_z = up / length
    line = right - left
    line = line - np.sum(line * e_z) * e_z
    width = np.sqrt(np.sum(line * line))
    if not width >= min_segment:
        return False
    e_x = line / width
    rotation = np.empty((3, 3))
    rotation[0] = e_x
    rotation[1, 0] = e_z[1] * e_x[2] - e_z[2] * e_x[1]
    rotation[1, 1] = e_z[2] * e_x[0] - e_z[0] * e_x[2]
    rotation[1, 2] = e_z[0] * e_x[1] - e_z[1] * e_x[0]
    rotation[2] = e_z
    m = moving.shape[0]
    hessian[:, :] = 0.0
    gradient[:] = 0.0
    for i in range(m):
        hessian[i, i] = damping
    jac = np.empty((3, m))
    for s in range(capsules.shape[0]):
        c = capsules[s]
        axis = endpoints[c, 1] - endpoints[c, 0]
        norm = np.sqrt(np.sum(axis * axis))
        unit = axis / norm
        residual = np.empty(3)
        for r in range(3):
            residual[r] = targets[s, r] - np.sum(rotation[r] * unit)
        for j in range(m):
            d_axis = jacobians[c, 1, :, moving[j]] - jacobians[c, 0, :, moving[j]]
            tangential = (d_axis - np.sum(unit * d_axis) * unit) / norm
            for r in range(3):
                jac[r, j] = np.sum(rotation[r] * tangential)
        for i in range(m):
            gradient[i] += jac[0, i] * residual[0] + jac[1, i] * residual[1] + jac[2, i] * residual[2]
            for j in range(m):
                hessian[i, j] += jac[0, i] * jac[0, j] + jac[1, i] * jac[1, j] + jac[2, i] * jac[2, j]
    return True
