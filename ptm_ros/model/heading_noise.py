r"""The heading noise of the odometry, learned from the run's own laser registrations (issue #23).

The thesis fixes the odometry noise by hand (eq. 17) and leaves learning it as future work (Ch. 6.3,
"learning the parameters"). Its default (:class:`ptm_ros.model.odometry.OdometryConfig`: ``a_th``, ``b_th``,
``c_th``) describes wheel odometry, but the visits' poses come from the laser-corrected odometry
(:mod:`ptm_ros.perception.laser_odometry`), whose heading drifts far less, by how much depending on the
building, the laser and the simulator (``bench/heading_noise.md`` measures it against the ground truth). A
heading model several times too wide lets the metric likelihood bend a loop far enough to merge places tens of
metres apart; one too narrow refuses true loops. So the scale is learned from each run.

Model
-----
A valid registration ``z`` of visits ``i < j`` (:class:`~ptm_ros.model.geometry.RelativePose`) measures
``between(x_i, x_j)``. Its heading compares with the odometry's heading change without any topology:
headings compose additively, so for a true match

.. math::
    e_{ij} = \mathrm{wrap}\big(z_\theta - (u_j^\theta - u_i^\theta)\big)
           \sim \mathcal N\big(0,\ k\,V_{ij} + R_{ij}\big), \qquad
    V_{ij} = \sum_{m=i+1}^{j} a_\theta \rho_m + c_\theta \ell_m + b_\theta,

exactly (no linearisation): ``V`` is the model's heading variance of the path from ``i`` to ``j``
(:func:`ptm_ros.model.odometry.odometry_covariances`), ``R`` the registration's heading variance and ``k`` the
scale to learn. The registrar is asked only about pairs some topology calls one place, and some of those
are different places whose scans still matched (aliases, uniform heading error), so the likelihood is
the mixture :math:`(1-\varepsilon)\,\mathcal N(e; 0, kV + R) + \varepsilon / 2\pi` with ``ε`` learned too.
With a log-normal prior :math:`\log k \sim \mathcal N(0, s^2)` (``heading_prior_sd``: the default model is
the prior guess), the estimate is the posterior mode over the lattice :math:`k = 2^{m/2}` (a step of
:math:`\sqrt 2` in the variance; :func:`heading_scale`), profiled over ``ε``. Without registrations it is
the prior's mode, the default model.

Approximation: the residuals are taken as independent, but two registrations whose paths share segments
share those segments' heading noise, so a run holds less information about ``k`` than their number says
(the estimate of one run scatters by about a factor 2 around the truth on simulated grid walks); the prior
and the lattice's hysteresis in :class:`ptm_ros.session.FilterSession` keep it from chasing that noise.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ptm_ros.model.geometry import FloatArray, RelativePose
from ptm_ros.model.odometry import OdometryConfig, heading_residuals_of
from ptm_ros.model.visits import Visit

#: The lattice of scales: ``k = 2^(m/2)`` for ``m`` in this range (0.001 … 16).
SCALE_STEPS = range(-20, 9)
#: The outlier fractions over which the likelihood is profiled.
OUTLIER_FRACTIONS = (0.02, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 0.9)


@dataclass(frozen=True)
class HeadingResiduals:
    """The heading discrepancies of a run's valid registrations (module docstring).

    Attributes:
        error: ``(R,)`` :math:`e_{ij}` [rad].
        path_variance: ``(R,)`` :math:`V_{ij}` at the unscaled model [rad²].
        registration_variance: ``(R,)`` :math:`R_{ij}` [rad²].
    """

    error: FloatArray
    path_variance: FloatArray
    registration_variance: FloatArray

    def __len__(self) -> int:
        return len(self.error)


@dataclass(frozen=True)
class NoiseScale:
    """A learned noise scale: the heading's here, the translation's in
    :mod:`ptm_ros.model.translation_noise`.

    Attributes:
        scale: ``k``, the factor on the noise's variances (here ``a_th``, ``b_th`` and ``c_th``).
        step: ``m`` of the lattice, ``k = 2^(m/2)``.
        outlier_fraction: the profiled ``ε`` at ``k``.
        registrations: how many registrations it was learned from.
    """

    scale: float
    step: int
    outlier_fraction: float
    registrations: int

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> NoiseScale:
        """Inverse of :meth:`as_dict`."""
        return cls(float(d["scale"]), int(d["step"]), float(d["outlier_fraction"]), int(d["registrations"]))

    def as_dict(self) -> dict[str, float | int]:
        """Plain values (ptm.json's ``inference.heading_noise``)."""
        return {
            "scale": self.scale,
            "step": self.step,
            "outlier_fraction": self.outlier_fraction,
            "registrations": self.registrations,
        }


#: The estimate without residuals: the prior's mode (the model as configured), at the smallest fraction.
PRIOR_MODE = NoiseScale(1.0, 0, OUTLIER_FRACTIONS[0], 0)


def heading_residuals(
    visits: Sequence[Visit], registrations: Iterable[RelativePose], config: OdometryConfig
) -> HeadingResiduals:
    """The heading discrepancy of each registration against the visits' odometry (module docstring);
    registrations of visits beyond ``visits`` are left out."""
    n = len(visits)
    kept = [z for z in registrations if z.j < n and z.i < z.j]
    return HeadingResiduals(*heading_residuals_of(visits, kept, config))


def scale_log_likelihoods(residuals: HeadingResiduals, scales: FloatArray, outlier: float) -> FloatArray:
    """``log p(e | k, ε)`` of the residuals for each of ``scales`` (the mixture of the module docstring)."""
    var = scales[:, None] * residuals.path_variance[None, :] + residuals.registration_variance[None, :]
    log_in = -0.5 * (residuals.error[None, :] ** 2 / var + np.log(2.0 * math.pi * var))
    log_out = math.log(outlier / (2.0 * math.pi))
    mix = np.logaddexp(math.log1p(-outlier) + log_in, log_out)
    return np.asarray(mix.sum(axis=1), dtype=float)


def heading_scale(residuals: HeadingResiduals, prior_sd: float) -> NoiseScale:
    """The posterior mode of ``k`` over the lattice :data:`SCALE_STEPS`, profiled over ``ε`` in
    :data:`OUTLIER_FRACTIONS`, with the prior :math:`\\log k \\sim N(0, s^2)`, ``s = prior_sd`` (module
    docstring); the prior's mode (``k = 1``) without residuals."""
    if len(residuals) == 0:
        return PRIOR_MODE
    return lattice_mode(_outlier_table(residuals, lattice_scales()), len(residuals), prior_sd)


def lattice_scales() -> FloatArray:
    """The scales of :data:`SCALE_STEPS`, ``k = 2^(m/2)``."""
    return np.asarray(2.0 ** (np.array(SCALE_STEPS, dtype=float) / 2.0), dtype=float)


def lattice_mode(table: FloatArray, registrations: int, prior_sd: float) -> NoiseScale:
    r"""The posterior mode over :func:`lattice_scales` of a ``(len(OUTLIER_FRACTIONS), len(SCALE_STEPS))``
    table of log likelihoods, profiled over the outlier fraction (rows), with the prior
    :math:`\log k \sim N(0, s^2)`, ``s = prior_sd``."""
    steps = np.array(SCALE_STEPS)
    log_prior = -0.5 * (np.log(lattice_scales()) / prior_sd) ** 2
    best_eps = np.argmax(table, axis=0)
    k = int(np.argmax(table[best_eps, np.arange(len(steps))] + log_prior))
    step = int(steps[k])
    return NoiseScale(2.0 ** (step / 2.0), step, OUTLIER_FRACTIONS[int(best_eps[k])], registrations)


def profiled_outlier(residuals: HeadingResiduals, step: int) -> float:
    """The ``ε`` of :data:`OUTLIER_FRACTIONS` that best explains the residuals at the scale of lattice step
    ``step`` (``k = 2^(step/2)``): the share of the registrations the heading model takes for aliases at the
    scale in use; the smallest fraction without residuals."""
    if len(residuals) == 0:
        return OUTLIER_FRACTIONS[0]
    table = _outlier_table(residuals, np.array([2.0 ** (step / 2.0)]))
    return OUTLIER_FRACTIONS[int(np.argmax(table[:, 0]))]


def _outlier_table(residuals: HeadingResiduals, scales: FloatArray) -> FloatArray:
    """``(len(OUTLIER_FRACTIONS), len(scales))`` log likelihoods of the residuals, one row per ``ε``."""
    return np.stack([scale_log_likelihoods(residuals, scales, eps) for eps in OUTLIER_FRACTIONS])


def scaled_heading_noise(config: OdometryConfig, scale: float) -> OdometryConfig:
    """``config`` with its heading noise (``a_th``, ``b_th``, ``c_th``) multiplied by ``scale``."""
    if scale == 1.0:
        return config
    return replace(config, a_th=config.a_th * scale, b_th=config.b_th * scale, c_th=config.c_th * scale)
