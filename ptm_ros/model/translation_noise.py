r"""The translation noise of the odometry, measured against the run's own laser registrations (issue #23).

A model check, not a parameter the posterior uses. The visits' poses come from the laser-corrected odometry,
whose error depends on the building and the laser's rate (:mod:`ptm_ros.model.heading_noise` learns its
heading part). Its translation noise (eq. 17's ``a_xy``, ``b_xy``) is checked the same way: how far the
registrations put revisits from where the odometry puts them, against what the model allows. A scale well
above 1 says the metric evidence is weaker than the posterior assumes (the run's geometry is off by more
than its model's noise), so its probabilities of places are less trustworthy. Plugged into the model the
learned scale does not help the MAP on the shared runs: a looser odometry lets the prior merge more
(``bench/real_seeds.md``), so it is reported, not used.

Model
-----
A valid registration ``z`` of visits ``i < j`` measures ``between(x_i, x_j)``; before any topology the
odometry predicts it as ``between(u_i, u_j)``. Linearised in the steps' noise (eq. 17, each step's noise
diagonal in the frame of the visit it leaves), the residual ``e = z ⊖_θ between(u_i, u_j)`` (translation
differenced, heading wrapped) of a true match is :math:`\mathcal N(0,\ k\,A_{ij} + k_\theta H_{ij} + R_{ij})`:

* :math:`A_{ij} = \sum_{m=i+1}^{j} (a_{xy}\ell_m + b_{xy})\,\mathrm{diag}(1, 1, 0)`: each step's translation
  noise is isotropic, so it moves visit ``j`` by the same variance in the frame of visit ``i``;
* :math:`H_{ij} = \sum_{m=i+1}^{j} v^\theta_m\, g_m g_m^\top`, :math:`g_m = (-(y_j - y_m),\ x_j - x_m,\ 1)`
  with ``(x_m, y_m)`` visit ``m``'s position in the frame of visit ``i``: the heading noise of the step into
  visit ``m`` (variance :math:`v^\theta_m`, eq. 17) turns the rest of the path about visit ``m``;
* ``R`` the registration's covariance, ``k_θ`` the heading scale in use and ``k`` the scale to learn.

Aliases are uniform over ``V_reg`` (``registration_volume``): the likelihood is the mixture
:math:`(1-\varepsilon)\,\mathcal N(e; 0, kA + k_\theta H + R) + \varepsilon / V_{reg}`, and ``k`` is the
posterior mode over the heading's lattice with its prior (:func:`ptm_ros.model.heading_noise.lattice_mode`),
profiled over ``ε``. As for the heading, the residuals of registrations whose paths overlap are taken as
independent, and the registrar is asked only about pairs a topology called one place.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ptm_ros.model.geometry import FloatArray, RelativePose, wrap_angle
from ptm_ros.model.heading_noise import (
    OUTLIER_FRACTIONS,
    PRIOR_MODE,
    NoiseScale,
    lattice_mode,
    lattice_scales,
)
from ptm_ros.model.odometry import OdometryConfig, odometry_variances
from ptm_ros.model.visits import Visit, poses_array

#: ``ptm.inference`` key of the scale the registrations suggest (:func:`translation_scale`).
TRANSLATION_KEY = "translation_noise"
#: A learned scale this large or larger means the registrations disagree with the odometry by more than
#: its noise model allows: the variance off by a factor 2 (one lattice step beyond √2).
WEAK_GEOMETRY_SCALE = 2.0


@dataclass(frozen=True)
class TranslationResiduals:
    """The residuals of a run's valid registrations against the odometry (module docstring).

    Attributes:
        error: ``(R, 3)`` :math:`e_{ij}` (translation [m] in the frame of visit ``i``, heading [rad]).
        translation: ``(R,)`` the translation variance of the path at the unscaled model, ``A``'s diagonal.
        heading: ``(R, 3, 3)`` :math:`H_{ij}` at the unscaled heading model.
        registration: ``(R, 3, 3)`` :math:`R_{ij}`.
    """

    error: FloatArray
    translation: FloatArray
    heading: FloatArray
    registration: FloatArray

    def __len__(self) -> int:
        return len(self.error)


def translation_residuals(
    visits: Sequence[Visit], registrations: Iterable[RelativePose], config: OdometryConfig
) -> TranslationResiduals:
    """The residual of each registration of visits ``i < j`` within ``visits`` (module docstring), with
    the terms of its covariance; the others are left out."""
    n = len(visits)
    kept = [z for z in registrations if z.i < z.j < n]
    if not kept:
        return TranslationResiduals(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3, 3)), np.zeros((0, 3, 3)))
    u = poses_array(visits)
    var = np.concatenate([np.zeros((1, 3)), odometry_variances(visits, config)])  # var[m]: step into m
    i = np.array([z.i for z in kept])
    j = np.array([z.j for z in kept])
    sxy = np.cumsum(var[:, 0])
    rot = _to_frame(u[i, 2])
    predicted_xy = np.einsum("rab,rb->ra", rot, u[j, :2] - u[i, :2])
    means = np.array([z.mean for z in kept], dtype=float)
    error = np.column_stack([means[:, :2] - predicted_xy, wrap_angle(means[:, 2] - (u[j, 2] - u[i, 2]))])
    covs = np.array([z.cov for z in kept], dtype=float)
    return TranslationResiduals(
        error, sxy[j] - sxy[i], _path_heading_terms(u[:, :2], var[:, 2], i, j, rot), covs
    )


def _to_frame(yaw: FloatArray) -> FloatArray:
    """``(R, 2, 2)`` rotations from the world into frames of headings ``yaw``."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, s], -1), np.stack([-s, c], -1)], 1)


def _path_heading_terms(
    p: FloatArray, v_th: FloatArray, i: NDArray[np.intp], j: NDArray[np.intp], rot: FloatArray
) -> FloatArray:
    r"""``(R, 3, 3)`` :math:`H_{ij} = \sum_{m=i+1}^{j} v^\theta_m g_m g_m^\top` (module docstring) for visit
    positions ``p`` ``(N, 2)`` and heading variances ``v_th`` ``(N,)`` of the step into each visit (0 for
    the first), ``rot`` the rotations into the frames of visits ``i``: prefix sums of ``v``, ``v p`` and
    ``v p pᵀ`` make each sum over the path two lookups."""
    s0 = np.cumsum(v_th)
    s1 = np.cumsum(v_th[:, None] * p, axis=0)
    s2 = np.cumsum(v_th[:, None, None] * p[:, :, None] * p[:, None, :], axis=0)
    w0, w1, w2 = s0[j] - s0[i], s1[j] - s1[i], s2[j] - s2[i]
    pj = p[j]
    # Σ v d dᵀ and Σ v d with d = p_j − p_m, world frame
    dd = w0[:, None, None] * pj[:, :, None] * pj[:, None, :] - pj[:, :, None] * w1[:, None, :]
    dd = dd - w1[:, :, None] * pj[:, None, :] + w2
    d1 = w0[:, None] * pj - w1
    jr = np.array([[0.0, -1.0], [1.0, 0.0]]) @ rot  # into frame i, then the quarter turn: g = (J d, 1)
    out = np.zeros((len(i), 3, 3))
    out[:, :2, :2] = jr @ dd @ np.swapaxes(jr, 1, 2)
    out[:, :2, 2] = out[:, 2, :2] = np.einsum("rab,rb->ra", jr, d1)
    out[:, 2, 2] = w0
    return out


def inlier_log_densities(
    residuals: TranslationResiduals, scales: FloatArray, heading_scale: float
) -> FloatArray:
    r"""``(len(scales), R)`` :math:`\log \mathcal N(e; 0, kA + k_\theta H + R)` of each residual at each
    scale ``k`` of ``scales``."""
    flat = np.zeros((len(residuals), 3, 3))
    flat[:, 0, 0] = flat[:, 1, 1] = residuals.translation
    fixed = heading_scale * residuals.heading + residuals.registration
    chol = np.linalg.cholesky(scales[:, None, None, None] * flat[None] + fixed[None])  # (K, R, 3, 3)
    e = np.broadcast_to(residuals.error[None, :, :, None], (*chol.shape[:2], 3, 1))
    white = np.linalg.solve(chol, e)[..., 0]
    log_det = np.sum(np.log(np.diagonal(chol, axis1=2, axis2=3)), axis=2)
    return np.asarray(-0.5 * np.sum(white * white, axis=2) - log_det - 1.5 * math.log(2.0 * math.pi))


def translation_scale(
    residuals: TranslationResiduals, heading_scale: float, config: OdometryConfig
) -> NoiseScale:
    """The posterior mode of ``k`` (module docstring) at the heading scale in use, with the heading's prior
    (``heading_prior_sd``) and alias volume (``registration_volume``); ``k = 1`` without residuals."""
    if len(residuals) == 0:
        return PRIOR_MODE
    log_in = inlier_log_densities(residuals, lattice_scales(), heading_scale)
    log_vol = math.log(config.registration_volume)
    table = np.stack(
        [
            np.logaddexp(math.log1p(-eps) + log_in, math.log(eps) - log_vol).sum(axis=1)
            for eps in OUTLIER_FRACTIONS
        ]
    )
    return lattice_mode(table, len(residuals), config.heading_prior_sd)
