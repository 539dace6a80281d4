"""Sparse 2-D pose graphs of relative-pose factors, solved by Levenberg–Marquardt with ``x_0`` fixed.

A factor ``q`` measures ``z_q ≈ x_a ⊖ x_b`` with whitening ``W_q`` (``W_qᵀ W_q = Σ_q⁻¹``); its residual
is ``W_q((x_a ⊖ x_b) ⊟ z_q)`` (heading wrapped) and its Jacobian comes from
:func:`ptm_ros.model.odometry.between_derivatives`. The first pose is the gauge (the batch model's ``x_0 :=
u_0``, thesis App. B). Shared by the robust trajectory smoothing (:mod:`ptm_ros.maps.smoothing`) and the
robust loop-closure baseline (:mod:`ptm_ros.scoring.baselines`), which add their own weighted terms.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray
from scipy.sparse.linalg import spsolve

from ptm_ros.model.geometry import FloatArray, wrap_angle
from ptm_ros.model.odometry import between_derivatives


@dataclass(frozen=True)
class RelativeFactors:
    """Relative-pose factors ``W((x_a ⊖ x_b) ⊟ z)``."""

    a: NDArray[np.intp]
    b: NDArray[np.intp]
    z: FloatArray  # (Q, 3) measurements of between(x_a, x_b)
    w: FloatArray  # (Q, 3, 3) whitening, Wᵀ W = covariance⁻¹


def relative_residuals(x: FloatArray, f: RelativeFactors) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Whitened residuals ``(Q, 3)`` at poses ``x`` ``(N, 3)``, and the translation ``t = x_a ⊖ x_b``
    (``t_x``, ``t_y``, each ``(Q,)``) that :func:`relative_jacobian` needs."""
    pa, pb = x[f.a], x[f.b]
    c, s = np.cos(pa[:, 2]), np.sin(pa[:, 2])
    dx, dy = pb[:, 0] - pa[:, 0], pb[:, 1] - pa[:, 1]
    tx, ty = c * dx + s * dy, -s * dx + c * dy
    e = np.stack([tx - f.z[:, 0], ty - f.z[:, 1], wrap_angle(pb[:, 2] - pa[:, 2] - f.z[:, 2])], axis=1)
    return np.einsum("qij,qj->qi", f.w, e), tx, ty


def relative_jacobian(x: FloatArray, f: RelativeFactors, tx: FloatArray, ty: FloatArray) -> sp.csr_matrix:
    """``∂r/∂(x_1..x_{N-1})``, sparse ``(3Q, 3(N-1))`` (``x_0`` is fixed)."""
    q, n = len(f.a), len(x)
    jab = f.w @ between_derivatives(x, f.a, f.b, tx, ty)
    var = np.concatenate(
        [3 * (f.a - 1)[:, None] + np.arange(3), 3 * (f.b - 1)[:, None] + np.arange(3)], axis=1
    )
    rows = np.broadcast_to((3 * np.arange(q))[:, None, None] + np.arange(3)[None, :, None], jab.shape)
    cols = np.broadcast_to(var[:, None, :], jab.shape)
    keep = cols >= 0  # visit 0 is the gauge
    return sp.csr_matrix((jab[keep], (rows[keep], cols[keep])), shape=(3 * q, 3 * (n - 1)))


def levenberg_marquardt(
    x0: FloatArray,
    cost: Callable[[FloatArray], float],
    normal_equations: Callable[[FloatArray], tuple[sp.csc_matrix, FloatArray]],
    *,
    max_iterations: int,
    tolerance: float,
) -> FloatArray:
    """Minimise ``cost`` over poses ``x`` ``(N, 3)`` from ``x0`` with ``x_0`` fixed.

    ``normal_equations(x)`` returns ``H = Jᵀ J`` (sparse) and ``g = Jᵀ r`` of the residuals whose half
    squared norm is ``cost``. Each iteration solves ``(H + λ diag H) δ = −g`` and raises ``λ`` tenfold
    until the cost does not increase; it stops when no step lowers the cost or the decrease is at most
    ``tolerance · (1 + cost)``.
    """
    x = x0.copy()
    value = cost(x)
    lam = 1e-6
    for _ in range(max_iterations):
        H, g = normal_equations(x)
        while lam < 1e12:
            step = -spsolve((H + sp.diags(lam * H.diagonal())).tocsc(), g)
            x_new = x.copy()
            x_new[1:] += step.reshape(-1, 3)
            new = cost(x_new) if np.all(np.isfinite(step)) else math.inf
            if new <= value:
                break
            lam *= 10.0
        else:
            break  # no step lowers the cost: converged to machine precision
        decrease = value - new
        x, value, lam = x_new, new, max(lam / 10.0, 1e-12)
        if decrease <= tolerance * (1.0 + value):
            break
    return x
