r"""Appearance likelihoods ``P(A | T)`` of a topology (thesis Ch. 2.5, 3.10.3, 4.3–4.4).

A topology ``T`` partitions the visits into blocks (places). Every visit ``i`` of a place ``s`` is an
appearance measurement ``a_i`` of that place's hidden "true appearance" ``y_s``; places are independent
and ``y_s`` is integrated out, so the likelihood is a product partition model (eq. 19–22):

.. math::
    P(A \mid T) = \prod_{s \in T} \int P(y_s) \prod_{i \in s} P(a_i \mid y_s)\, dy_s .

Each block factor is a proper marginal density with all its constants, so products over the blocks of
different topologies (with different numbers of places) are comparable. Two measurement models:

**Fourier signatures** (Ch. 2.5): ``a_i`` is a vector of ``K`` rotation-invariant Fourier magnitudes of
the visit's panorama (:func:`fourier_signature`). Components are independent given the place; per block
``s`` and component ``k`` the Normal–Inverse-Gamma model of eq. 25 is

.. math::
    a_{ik} \sim \mathcal N(y_{sk}, \sigma^2_{sk}),\quad y_{sk} \sim \mathcal N(\mu_k, \sigma^2_{sk}/\kappa),
    \quad \sigma^2_{sk} \sim \mathrm{IG}(\alpha_k, \beta_k),

whose block marginal (eq. 26–28, derived here because the printed eq. 28 is wrong, see
:func:`log_marginal_nig`) is, with ``n = |s|``, ``κ_n = κ + n``, ``α_n = α + n/2`` and
``β_n = β + Φ/2``, ``Φ = Σ_i (a_{ik} - ā_k)^2 + κ n (ā_k - μ_k)^2 / κ_n``:

.. math::
    p(a_{1k}, …, a_{nk}) = (2\pi)^{-n/2} \sqrt{\kappa/\kappa_n}\;
        \frac{\Gamma(\alpha_n)}{\Gamma(\alpha)} \frac{\beta^{\alpha}}{\beta_n^{\alpha_n}} .

The one-visit predictive used by particle filters (eq. 46) is a Student t with ``2α_n`` degrees of
freedom, location ``μ_n = (κμ + Σ a_i)/κ_n`` and squared scale ``β_n (κ_n + 1) / (α_n κ_n)``.

**Bag of words** (Ch. 4.3–4.4): ``a_i`` is a histogram ``x_i`` of ``V`` quantised SIFT words
(:mod:`ptm_ros.model.vocabulary`). The visits of one place are multinomial draws sharing
``θ_s ~ Dir(α)``: the multivariate Pólya / Dirichlet-compound-multinomial model (eq. 54–57),

.. math::
    p(x_1, …, x_n) = \prod_i \frac{m_i!}{\prod_w x_{iw}!}\;
        \frac{\Gamma(\alpha_\cdot)}{\Gamma(m_s + \alpha_\cdot)}
        \prod_w \frac{\Gamma(c_{w} + \alpha_w)}{\Gamma(\alpha_w)},

with ``m_i = Σ_w x_{iw}``, ``c_w = Σ_i x_{iw}``, ``m_s = Σ_i m_i``, ``α_· = Σ_w α_w``. The Dirichlet
parameter ``α`` is one empirical-Bayes prior shared by all places, estimated once from all visits by
Minka's fixed point (:func:`estimate_dcm_alpha`, eq. 58 corrected).

Calling contract: build an :class:`AppearanceModel` once per run with :func:`fit_appearance_model`, then
evaluate :func:`appearance_log_likelihood` for any topology (a cache dict shared across calls reuses block
factors, which recur across MCMC moves) or :func:`appearance_log_predictive` for one new visit given the
visits of a place (particle filters).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import digamma, gammaln

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.model.geometry import FloatArray
from ptm_ros.model.partitions import blocks
from ptm_ros.model.visits import Visit
from ptm_ros.settings import Settings, setting

IntArray = NDArray[np.int64]
Block = tuple[int, ...]

#: The appearance models :class:`AppearanceConfig` can combine.
MODELS = ("fourier", "words")

#: ITU-R BT.601 luma weights used to turn an RGB panorama into grey levels.
_LUMA = np.array([0.299, 0.587, 0.114])
_LOG_2PI = float(np.log(2.0 * np.pi))
#: Variance floor of the empirical-Bayes prior (signature units²), for constant components.
_VAR_FLOOR = 1e-12


# ---------------------------------------------------------------------------------------------------
# Fourier signatures (Ch. 2.5)
# ---------------------------------------------------------------------------------------------------


def fourier_signature(
    image: ArrayLike,
    n_coeffs: int = 8,
    bands: int = 1,
    *,
    include_dc: bool = False,
    gain_invariant: bool = False,
) -> FloatArray:
    """Rotation-invariant Fourier signature of a 360° panorama (thesis Ch. 2.5, after Ishiguro [62]).

    The image rows are averaged (per horizontal band when ``bands > 1``, rows split as evenly as
    possible, top band first) into one grey-level profile over azimuth; the signature is the magnitude of
    the profile's discrete Fourier transform at the lowest frequencies, divided by the width ``W``:

    ``s_k = |Σ_c p_c e^{-2πi k c / W}| / W``, ``k = 1 … n_coeffs`` (``k = 0 … n_coeffs-1`` with
    ``include_dc``), concatenated band after band, shape ``(bands * n_coeffs,)``.

    Choices:
      * Magnitudes: a change of heading is a circular column shift, which multiplies the coefficients by
        a unit phase, so the signature is invariant to a whole-column shift (up to rounding) and, for a
        scene whose profile is smooth at these frequencies, nearly invariant to a sub-pixel shift.
      * Division by ``W``: ``s_k`` is half the amplitude of the k-th azimuthal sinusoid, independent of
        the panorama width. Integer images are scaled to [0, 1] by their dtype's maximum (uint8: 255);
        float images are used as given (expected in [0, 1]). RGB uses BT.601 luma.
      * The DC term (mean brightness) is left out by default: it carries no azimuthal structure and is
        the component most affected by exposure and lighting.
      * ``gain_invariant`` divides each band's magnitudes by that band's mean brightness, making the
        signature invariant to a global brightness gain (at the cost of discarding absolute contrast).

    Raises:
        ModelError: on a wrong shape or dtype, non-finite values, ``W < 2 * n_coeffs``, fewer rows than
            bands, or a black band with ``gain_invariant``.
    """
    if n_coeffs < 1 or bands < 1:
        msg = f"fourier_signature needs n_coeffs >= 1 and bands >= 1, got {n_coeffs}, {bands}"
        raise ModelError(msg)
    img = np.asarray(image)
    grey = _grey_levels(img)
    height, width = grey.shape
    if width < 2 * n_coeffs:
        msg = f"panorama width {width} is too small for {n_coeffs} coefficients (need >= {2 * n_coeffs})"
        raise ModelError(msg)
    if height < bands:
        msg = f"panorama height {height} is smaller than the number of bands {bands}"
        raise ModelError(msg)
    profiles = np.stack([rows.mean(axis=0) for rows in np.array_split(grey, bands, axis=0)])
    spectrum = np.abs(np.fft.rfft(profiles, axis=1)) / width
    start = 0 if include_dc else 1
    mags = spectrum[:, start : start + n_coeffs]
    if gain_invariant:
        brightness = spectrum[:, :1]
        if np.any(brightness <= 0.0):
            msg = "gain_invariant signature of a panorama band with zero mean brightness"
            raise ModelError(msg)
        mags = mags / brightness
    return np.ascontiguousarray(mags.reshape(-1), dtype=np.float64)


def _grey_levels(img: NDArray[Any]) -> FloatArray:
    """``(H, W)`` float grey levels of a mono or RGB(A) image; integer dtypes scaled to [0, 1]."""
    if img.ndim not in (2, 3) or (img.ndim == 3 and img.shape[2] not in (1, 3, 4)):
        msg = f"panorama must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {img.shape}"
        raise ModelError(msg)
    if img.dtype == np.bool_ or not (
        np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)
    ):
        msg = f"panorama dtype must be an integer or float type, got {img.dtype}"
        raise ModelError(msg)
    if img.size == 0:
        msg = f"panorama is empty, shape {img.shape}"
        raise ModelError(msg)
    if np.issubdtype(img.dtype, np.integer):
        data = img.astype(np.float64) / float(np.iinfo(img.dtype).max)
    else:
        data = img.astype(np.float64)
        if not np.all(np.isfinite(data)):
            msg = "panorama holds non-finite values"
            raise ModelError(msg)
    if data.ndim == 2:
        return data
    if data.shape[2] == 1:
        return data[:, :, 0]
    return data[:, :, :3] @ _LUMA


# ---------------------------------------------------------------------------------------------------
# Normal–Inverse-Gamma model of Fourier signatures (eq. 25–28, 46)
# ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class NigPrior:
    """Normal–Inverse-Gamma prior of eq. 25, independent per signature component.

    Attributes:
        mu: prior mean of the true appearance, shape ``(K,)``.
        kappa: prior pseudo-count of ``y``: ``y_k ~ N(mu_k, σ_k² / kappa)``.
        alpha: inverse-gamma shape, scalar or ``(K,)`` (stored as ``(K,)``).
        beta: inverse-gamma scale, scalar or ``(K,)`` (stored as ``(K,)``); ``E[σ²] = beta/(alpha-1)``.
    """

    mu: FloatArray
    kappa: float
    alpha: FloatArray
    beta: FloatArray

    def __post_init__(self) -> None:
        mu = np.atleast_1d(np.asarray(self.mu, dtype=float))
        if mu.ndim != 1 or mu.size == 0 or not np.all(np.isfinite(mu)):
            msg = f"NigPrior.mu must be a finite (K,) vector, got shape {mu.shape}"
            raise ConfigError(msg)
        if not (np.isfinite(self.kappa) and self.kappa > 0.0):
            msg = f"NigPrior.kappa must be finite and > 0, got {self.kappa}"
            raise ConfigError(msg)
        object.__setattr__(self, "mu", mu)
        object.__setattr__(self, "kappa", float(self.kappa))
        for name in ("alpha", "beta"):
            value = np.asarray(getattr(self, name), dtype=float)
            try:
                value = np.broadcast_to(value, mu.shape).copy()
            except ValueError as err:
                msg = f"NigPrior.{name} must be a scalar or shape {mu.shape}, got shape {value.shape}"
                raise ConfigError(msg) from err
            if not np.all(np.isfinite(value) & (value > 0.0)):
                msg = f"NigPrior.{name} must be finite and > 0, got {value}"
                raise ConfigError(msg)
            object.__setattr__(self, name, value)

    @property
    def dim(self) -> int:
        """Number of signature components K."""
        return int(self.mu.size)


@dataclass(frozen=True, eq=False)
class NigStats:
    """Sufficient statistics of the signatures of one block: count, sum and sum of squares per component.

    Immutable: :meth:`add` returns new statistics, so a particle can share its parent's statistics.
    """

    n: int
    total: FloatArray
    total_sq: FloatArray

    @classmethod
    def empty(cls, dim: int) -> NigStats:
        """Statistics of an empty block of ``dim``-component signatures."""
        return cls(0, np.zeros(dim), np.zeros(dim))

    @classmethod
    def from_signatures(cls, signatures: ArrayLike) -> NigStats:
        """Statistics of the rows of an ``(n, K)`` array."""
        a = _signatures(signatures)
        return cls(a.shape[0], a.sum(axis=0), np.square(a).sum(axis=0))

    def add(self, signature: ArrayLike) -> NigStats:
        """The statistics with one more ``(K,)`` signature."""
        a = _signature(signature, self.total.size)
        return NigStats(self.n + 1, self.total + a, self.total_sq + np.square(a))


def _signatures(signatures: ArrayLike) -> FloatArray:
    a = np.asarray(signatures, dtype=float)
    if a.ndim != 2 or not np.all(np.isfinite(a)):
        msg = f"signatures must be a finite (n, K) array, got shape {a.shape}"
        raise ModelError(msg)
    return a


def _signature(signature: ArrayLike, dim: int) -> FloatArray:
    a = np.asarray(signature, dtype=float)
    if a.shape != (dim,) or not np.all(np.isfinite(a)):
        msg = f"signature must be a finite ({dim},) vector, got shape {a.shape}"
        raise ModelError(msg)
    return a


def _check_dim(dim: int, prior: NigPrior) -> None:
    if dim != prior.dim:
        msg = f"signatures have {dim} components but the NIG prior has {prior.dim}"
        raise ModelError(msg)


def _nig_log_marginal_from_scatter(
    n: int, scatter: FloatArray, mean_dev: FloatArray, prior: NigPrior
) -> float:
    """Block marginal from ``n``, the within scatter ``Σ(a-ā)²`` and ``ā - μ`` (all per component)."""
    if n == 0:
        return 0.0
    kappa_n = prior.kappa + n
    alpha_n = prior.alpha + 0.5 * n
    phi = np.maximum(scatter, 0.0) + prior.kappa * n / kappa_n * np.square(mean_dev)
    beta_n = prior.beta + 0.5 * phi
    per_k = (
        -0.5 * n * _LOG_2PI
        + 0.5 * (np.log(prior.kappa) - np.log(kappa_n))
        + gammaln(alpha_n)
        - gammaln(prior.alpha)
        + prior.alpha * np.log(prior.beta)
        - alpha_n * np.log(beta_n)
    )
    return float(per_k.sum())


def log_marginal_nig(signatures: ArrayLike, prior: NigPrior) -> float:
    """``log p(a_1, …, a_n)`` of the ``(n, K)`` signatures of one block under eq. 25, all constants kept.

    The printed eq. 28 is wrong in three ways (derivation in the module docstring): the σ² integral of
    eq. 27 gives ``Γ(γ_s - 1) / (β + Φ/2)^{γ_s - 1}`` with ``γ_s - 1 = α + n/2`` (the Jacobian of
    ``t = σ^{-2}`` is missing, so the printed ``γ_s + 1`` is off by two); the omitted "constants"
    ``κ^{1/2} β^α / Γ(α)`` occur once per block, so they change with the number of places and must be
    kept to compare topologies; ``β`` and ``α`` carry the component index ``k``. An empty block gives 0.
    """
    a = _signatures(signatures)
    _check_dim(a.shape[1], prior)
    n = a.shape[0]
    if n == 0:
        return 0.0
    mean = a.mean(axis=0)
    scatter = np.square(a - mean).sum(axis=0)
    return _nig_log_marginal_from_scatter(n, scatter, mean - prior.mu, prior)


def log_marginal_nig_stats(stats: NigStats, prior: NigPrior) -> float:
    """:func:`log_marginal_nig` from sufficient statistics."""
    _check_dim(stats.total.size, prior)
    if stats.n == 0:
        return 0.0
    mean = stats.total / stats.n
    scatter = stats.total_sq - stats.total * mean
    return _nig_log_marginal_from_scatter(stats.n, scatter, mean - prior.mu, prior)


def log_predictive_nig(signature: ArrayLike, stats: NigStats, prior: NigPrior) -> float:
    """``log p(a_new | block)``: the Student-t posterior predictive of eq. 46, summed over components.

    With the block posterior ``(μ_n, κ_n, α_n, β_n)`` the predictive of each component is a Student t
    with ``ν = 2 α_n`` degrees of freedom, location ``μ_n`` and squared scale ``β_n (κ_n+1)/(α_n κ_n)``.
    An empty block (a new place) gives the prior predictive. Equals the difference of block marginals.
    """
    _check_dim(stats.total.size, prior)
    a = _signature(signature, prior.dim)
    n = stats.n
    kappa_n = prior.kappa + n
    alpha_n = prior.alpha + 0.5 * n
    if n == 0:
        beta_n = prior.beta
    else:
        mean = stats.total / n
        scatter = np.maximum(stats.total_sq - stats.total * mean, 0.0)
        beta_n = prior.beta + 0.5 * (scatter + prior.kappa * n / kappa_n * np.square(mean - prior.mu))
    mu_n = (prior.kappa * prior.mu + stats.total) / kappa_n
    nu = 2.0 * alpha_n
    scale_sq = beta_n * (kappa_n + 1.0) / (alpha_n * kappa_n)
    per_k = (
        gammaln(0.5 * (nu + 1.0))
        - gammaln(0.5 * nu)
        - 0.5 * np.log(nu * np.pi * scale_sq)
        - 0.5 * (nu + 1.0) * np.log1p(np.square(a - mu_n) / (nu * scale_sq))
    )
    return float(per_k.sum())


#: Largest within-place share of a component's variance (keeps ``κ = ρ/(1-ρ)`` finite).
MAX_WITHIN_FRACTION = 0.99


def nig_prior_from_data(
    signatures: ArrayLike,
    *,
    within_fraction: float = 0.1,
    alpha: float = 5.0,
    kappa: float | None = None,
    spreads: ArrayLike | None = None,
    prior_visits: float = 2.0,
) -> NigPrior:
    """Empirical-Bayes NIG prior from the signatures ``(N, K)`` of all visits of a run.

    Rule: ``μ`` = mean signature; ``v_k`` = sample variance of component ``k`` over all visits (floored
    at 1e-12). A fraction ``ρ_k`` of it is expected within a place, the rest between places: the inverse
    gamma is centred on ``E[σ_k²] = β_k/(α-1) = ρ_k v_k``, so ``β_k = (α-1) ρ_k v_k`` (``α`` sets how
    peaked it is: for ``α > 2`` its coefficient of variation is ``1/sqrt(α-2)``); ``κ = ρ̄/(1-ρ̄)`` (``ρ̄``
    the mean of the ``ρ_k``) by default, so the prior spread of the true appearance ``σ²/κ`` is the
    between-place part and the prior predictive of one visit has about the observed variance ``v_k``.

    ``ρ_k``: without ``spreads``, ``within_fraction``. With ``spreads`` ``(n, K)`` (the visits'
    :attr:`~ptm_ros.model.visits.Visit.signature_spread`: ``½ (a - a')²`` for a panorama ``a'`` taken one
    place's width away, whose expectation is the within-place variance ``σ_k²`` of eq. 25), the within-place
    variance is learned from the run: the mean spread, shrunk towards ``within_fraction · v_k`` with the
    weight of ``prior_visits`` visits, ``ρ_k = (Σ spreads + n₀ ρ₀ v_k) / ((n + n₀) v_k)`` capped at
    :data:`MAX_WITHIN_FRACTION`.

    Raises:
        ConfigError: ``within_fraction`` not in (0, 1), ``alpha <= 1``, ``kappa <= 0`` or
            ``prior_visits < 0``.
        ModelError: no signature or a non-finite one; spreads not ``(n, K)``, finite and >= 0.
    """
    if not 0.0 < within_fraction < 1.0:
        msg = f"within_fraction must be in (0, 1), got {within_fraction}"
        raise ConfigError(msg)
    if not alpha > 1.0:
        msg = f"the inverse-gamma shape alpha must be > 1 for a finite prior mean, got {alpha}"
        raise ConfigError(msg)
    a = _signatures(signatures)
    if a.shape[0] == 0:
        msg = "nig_prior_from_data needs at least one signature"
        raise ModelError(msg)
    if not (np.isfinite(prior_visits) and prior_visits >= 0.0):
        msg = f"prior_visits must be finite and >= 0, got {prior_visits}"
        raise ConfigError(msg)
    var = a.var(axis=0, ddof=1) if a.shape[0] > 1 else np.zeros(a.shape[1])
    var = np.maximum(var, _VAR_FLOOR)
    rho = np.full(a.shape[1], within_fraction)
    if spreads is not None:
        sp = np.asarray(spreads, dtype=float)
        if sp.ndim != 2 or sp.shape[1] != a.shape[1] or not np.all(np.isfinite(sp) & (sp >= 0.0)):
            msg = f"spreads must be finite, >= 0 and (n, {a.shape[1]}), got shape {sp.shape}"
            raise ModelError(msg)
        if len(sp) + prior_visits > 0.0:
            within = (sp.sum(axis=0) + prior_visits * within_fraction * var) / (len(sp) + prior_visits)
            rho = np.minimum(within / var, MAX_WITHIN_FRACTION)
    rho_mean = float(rho.mean())
    kappa_value = rho_mean / (1.0 - rho_mean) if kappa is None else kappa
    return NigPrior(
        mu=a.mean(axis=0), kappa=kappa_value, alpha=np.full_like(rho, alpha), beta=(alpha - 1.0) * rho * var
    )


# ---------------------------------------------------------------------------------------------------
# Multivariate Pólya / Dirichlet-compound-multinomial model of word histograms (eq. 54–58)
# ---------------------------------------------------------------------------------------------------


def _counts(counts: ArrayLike, ndim: int) -> IntArray:
    x = np.asarray(counts)
    if x.ndim != ndim:
        msg = f"word counts must be a {ndim}-D array, got shape {x.shape}"
        raise ModelError(msg)
    if x.dtype == np.bool_ or not (np.issubdtype(x.dtype, np.integer) or np.issubdtype(x.dtype, np.floating)):
        msg = f"word counts must be integers, got dtype {x.dtype}"
        raise ModelError(msg)
    if np.issubdtype(x.dtype, np.floating) and not np.all(np.isfinite(x) & (x == np.round(x))):
        msg = "word counts must be whole numbers"
        raise ModelError(msg)
    if np.any(x < 0):
        msg = "word counts must be >= 0"
        raise ModelError(msg)
    return x.astype(np.int64)


def _dirichlet(alpha: ArrayLike, size: int) -> FloatArray:
    a = np.asarray(alpha, dtype=float)
    if a.shape != (size,) or not np.all(np.isfinite(a) & (a > 0.0)):
        msg = f"Dirichlet parameter must be a finite positive ({size},) vector, got shape {a.shape}"
        raise ModelError(msg)
    return a


def _log_multinomial_coefficients(x: IntArray) -> float:
    """``Σ_i log(m_i! / Π_w x_iw!)`` of the rows of ``x``."""
    return float(gammaln(x.sum(axis=-1) + 1.0).sum() - gammaln(x + 1.0).sum())


def _log_polya_ratio(column_sums: IntArray, alpha: FloatArray) -> float:
    """``log Γ(α.)/Γ(m + α.) Π_w Γ(c_w + α_w)/Γ(α_w)`` (the Dirichlet integral of eq. 57)."""
    a_sum = alpha.sum()
    nz = column_sums > 0  # the other words contribute exactly 0
    return float(
        gammaln(a_sum)
        - gammaln(column_sums.sum() + a_sum)
        + (gammaln(column_sums[nz] + alpha[nz]) - gammaln(alpha[nz])).sum()
    )


def log_marginal_dcm(counts: ArrayLike, alpha: ArrayLike) -> float:
    """``log p(x_1, …, x_n)`` of the ``(n, V)`` word histograms of one block sharing ``θ ~ Dir(α)``.

    Eq. 57 corrected: each histogram is its own multinomial draw, so the multinomial coefficients are
    ``Π_i m_i! / Π_w x_iw!`` per histogram (the printed ``n_s! / Π_w n_sw`` pools the block and lacks
    the factorial; pooled coefficients would favour or penalise merging for no reason), and the
    Dirichlet normaliser of eq. 56 has ``Π_w Γ(α_w)``, not a sum. An empty block gives 0.
    """
    x = _counts(counts, 2)
    a = _dirichlet(alpha, x.shape[1])
    if x.shape[0] == 0:
        return 0.0
    return _log_multinomial_coefficients(x) + _log_polya_ratio(x.sum(axis=0), a)


def log_predictive_dcm(counts_new: ArrayLike, block_counts_sum: ArrayLike, alpha: ArrayLike) -> float:
    """``log p(x_new | block)``: the Pólya pmf of one histogram under the posterior ``Dir(α + c)``.

    ``block_counts_sum`` is ``c``, the word counts summed over the block's histograms (zeros for a new
    place). Equals ``log_marginal_dcm(block + new) - log_marginal_dcm(block)``.
    """
    x = _counts(counts_new, 1)
    c = _counts(block_counts_sum, 1)
    if c.shape != x.shape:
        msg = f"block counts have shape {c.shape} but the new histogram has {x.shape}"
        raise ModelError(msg)
    post = _dirichlet(alpha, x.size) + c
    a_sum = post.sum()
    nz = x > 0
    return float(
        gammaln(x.sum() + 1.0)
        - gammaln(x[nz] + 1.0).sum()
        + gammaln(a_sum)
        - gammaln(x.sum() + a_sum)
        + (gammaln(x[nz] + post[nz]) - gammaln(post[nz])).sum()
    )


def estimate_dcm_alpha(
    counts: ArrayLike,
    *,
    min_alpha: float = 1e-8,
    max_precision: float = 1e8,
    tol: float = 1e-10,
    max_iter: int = 100_000,
) -> FloatArray:
    """Maximum-likelihood ``α`` of a Pólya (DCM) model from independent histograms ``(D, V)``.

    Minka's fixed point (Minka 2000, "Estimating a Dirichlet distribution", §3; thesis eq. 58 as it
    should read): with ``m_d = Σ_w n_dw`` and ``α_· = Σ_w α_w``,

    ``α_w ← α_w Σ_d [ψ(n_dw + α_w) - ψ(α_w)] / Σ_d [ψ(m_d + α_·) - ψ(α_·)]``.

    The printed eq. 58 has ``ψ(n_dw + α)`` in the denominator, which should be the histogram total
    ``ψ(m_d + α_·)``. Each step cannot lower the likelihood. Words never observed go to 0 and are held
    at ``min_alpha``. Starts from a moment-matching guess; under-dispersed data (frequency variance at
    most the multinomial one: the likelihood grows towards a plain multinomial as ``α_· → ∞``) starts at
    and is held to ``α_· <= max_precision``. Stops when no ``log α_w`` moves by more than ``tol`` or a
    step gains less than ``tol · D`` nats of log-likelihood (a flat optimum).

    Raises:
        ModelError: bad counts, all histograms empty, or no convergence within ``max_iter`` steps.
    """
    x = _counts(counts, 2)
    totals = x.sum(axis=1)
    x = x[totals > 0]  # empty histograms carry no information
    totals = totals[totals > 0]
    if x.shape[0] == 0:
        msg = "estimate_dcm_alpha needs at least one non-empty histogram"
        raise ModelError(msg)
    docs, words = np.nonzero(x)
    values = x[docs, words].astype(float)
    n_words = x.shape[1]

    def log_lik(a: FloatArray) -> float:  # up to the multinomial coefficients
        a_sum = a.sum()
        return float(
            totals.size * gammaln(a_sum)
            - gammaln(totals + a_sum).sum()
            + (gammaln(values + a[words]) - gammaln(a[words])).sum()
        )

    alpha = _dcm_moment_guess(x, totals, min_alpha, max_precision)
    current = log_lik(alpha)
    step = np.inf
    for _ in range(max_iter):
        a_sum = alpha.sum()
        den = float(np.sum(digamma(totals + a_sum)) - totals.size * digamma(a_sum))
        num = np.bincount(
            words, weights=digamma(values + alpha[words]) - digamma(alpha[words]), minlength=n_words
        )
        new = np.maximum(alpha * num / den, min_alpha)
        if new.sum() > max_precision:
            new = np.maximum(new * (max_precision / new.sum()), min_alpha)
        step = float(np.max(np.abs(np.log(new) - np.log(alpha))))
        updated = log_lik(new)
        gain = updated - current
        alpha, current = new, updated
        if step < tol or abs(gain) < tol * totals.size:
            return alpha
    msg = f"Minka's fixed point did not converge in {max_iter} iterations (last step {step:.3g})"
    raise ModelError(msg)


def _dcm_moment_guess(x: IntArray, totals: IntArray, min_alpha: float, max_precision: float) -> FloatArray:
    """Starting point: mean word frequencies times a precision matched to the frequency variance.

    For a Pólya histogram of ``m`` words, ``Var(x_w/m) = p_w (1-p_w)/m · (m + α_·)/(1 + α_·)``; with the
    ratio ``r`` of the observed variance to ``p_w(1-p_w)`` and the mean total ``m``,
    ``α_· = m (1 - r) / (m r - 1)``; ``max_precision`` when ``m r <= 1`` (no over-dispersion).
    """
    freq = x / totals[:, None]
    p = freq.mean(axis=0)
    m = float(totals.mean())
    binom = p * (1.0 - p)
    ok = binom > 0.0
    precision = 1.0
    if x.shape[0] > 1 and np.any(ok):
        r = float(np.mean(freq.var(axis=0, ddof=1)[ok] / binom[ok]))
        precision = m * (1.0 - r) / (m * r - 1.0) if m * r > 1.0 else max_precision
    precision = float(np.clip(precision, 1e-2, max_precision))
    return np.maximum(p * precision, min_alpha)


# ---------------------------------------------------------------------------------------------------
# Topology likelihood
# ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AppearanceConfig(Settings):
    """Appearance likelihood settings (thesis Ch. 2.5, 4.4)."""

    models: tuple[str, ...] = setting(
        ("fourier",),
        choices=MODELS,
        doc=(
            'which measurement models to multiply: ``"fourier"`` (Fourier signatures, NIG model) and/or '
            '``"words"`` (bag-of-words histograms, Pólya model).'
        ),
    )
    n_coeffs: int = setting(
        8, ge=1, doc="Fourier coefficients per band (the thesis used the first five frequencies)."
    )
    bands: int = setting(
        1, ge=1, doc="horizontal bands of the panorama, each with its own ``n_coeffs`` coefficients."
    )
    include_dc: bool = setting(False, doc="keep the mean brightness as the first coefficient of each band.")
    gain_invariant: bool = setting(False, doc="divide each band's magnitudes by its mean brightness.")
    within_fraction: float = setting(
        0.3,
        gt=0,
        lt=1,
        doc=(
            "empirical Bayes, share of each component's variance over all visits expected within a place (see"
            " :func:`nig_prior_from_data`): the prior guess, used alone when ``within_learned`` is off or no "
            "visit carries a signature spread."
        ),
    )
    within_learned: bool = setting(
        True,
        doc=(
            "learn the within-place variance from the run (the visits' signature spreads, panoramas one "
            "place's width apart) instead of fixing it at ``within_fraction``."
        ),
    )
    within_prior_visits: float = setting(
        2.0, ge=0, doc="weight of ``within_fraction`` against the learned spreads, in visits."
    )
    nig_alpha: float = setting(
        5.0,
        gt=1,
        doc=(
            "inverse-gamma shape (> 1 for a finite prior mean; larger = the within-place variance is known "
            "more surely)."
        ),
    )
    nig_kappa: float | None = setting(
        None, gt=0, doc="prior pseudo-count of the true appearance; None = ``ρ/(1-ρ)`` (empirical Bayes)."
    )
    dcm_alpha: float | None = setting(
        None, gt=0, doc="symmetric Dirichlet parameter per word; None = Minka's ML estimate from all visits."
    )
    dcm_min_alpha: float = setting(
        1e-3, gt=0, doc="floor of the estimated per-word Dirichlet parameters (words rare in the run)."
    )
    dcm_max_iter: int = setting(100_000, ge=1, doc="iteration limit of Minka's fixed point.")
    dcm_tol: float = setting(
        1e-9, gt=0, doc="convergence tolerance of Minka's fixed point (max change of log α)."
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "models", tuple(self.models))  # a list (YAML, callers) becomes a tuple

    def check(self) -> None:
        """At least one model, none named twice."""
        models = tuple(self.models)
        if not models or len(set(models)) != len(models):
            msg = f"AppearanceConfig.models must be distinct names among {MODELS}, got {models}"
            raise ConfigError(msg)


def panorama_signature(image: ArrayLike, config: AppearanceConfig) -> FloatArray:
    """:func:`fourier_signature` of a panorama with the settings of ``config``."""
    return fourier_signature(
        image,
        config.n_coeffs,
        config.bands,
        include_dc=config.include_dc,
        gain_invariant=config.gain_invariant,
    )


@dataclass(frozen=True, eq=False)
class AppearanceModel:
    """The fitted priors of a run: the NIG prior of signatures and/or the Dirichlet of word histograms.

    A model that is None is not used. Build with :func:`fit_appearance_model`.
    """

    nig: NigPrior | None = None
    dcm_alpha: FloatArray | None = None

    def __post_init__(self) -> None:
        if self.nig is None and self.dcm_alpha is None:
            msg = "an AppearanceModel needs a NIG prior, a Dirichlet parameter or both"
            raise ConfigError(msg)
        if self.dcm_alpha is not None:
            a = np.asarray(self.dcm_alpha, dtype=float)
            if a.ndim != 1 or a.size == 0 or not np.all(np.isfinite(a) & (a > 0.0)):
                msg = f"dcm_alpha must be a finite positive (V,) vector, got shape {a.shape}"
                raise ConfigError(msg)
            object.__setattr__(self, "dcm_alpha", a)


_MIN_FIT_VISITS = 2  # visits with the measurement an empirical-Bayes prior needs


def fit_appearance_model(visits: Sequence[Visit], config: AppearanceConfig) -> AppearanceModel:
    """Empirical-Bayes priors from all visits of a run that carry the measurements (signatures and/or
    word histograms as configured). A visit without a measurement is a missing measurement: every
    likelihood of this module leaves it out (its density integrates to 1).

    Raises:
        ModelError: no visits, or fewer than 2 visits carry a measurement a configured model needs.
    """
    if not visits:
        msg = "fit_appearance_model needs at least one visit"
        raise ModelError(msg)
    nig = None
    dcm_alpha = None
    if "fourier" in config.models:
        signatures = _stack_signatures(visits, range(len(visits)))
        if len(signatures) < _MIN_FIT_VISITS:
            msg = f"only {len(signatures)} visits carry a Fourier signature; the appearance prior needs 2"
            raise ModelError(msg)
        spreads = [
            v.signature_spread
            for v in visits
            if v.signature is not None
            and v.signature_spread is not None
            and len(v.signature) == signatures.shape[1]
        ]
        nig = nig_prior_from_data(
            signatures,
            within_fraction=config.within_fraction,
            alpha=config.nig_alpha,
            kappa=config.nig_kappa,
            spreads=np.array(spreads) if config.within_learned and spreads else None,
            prior_visits=config.within_prior_visits,
        )
    if "words" in config.models:
        counts = _stack_words(visits, range(len(visits)), None)
        if len(counts) < _MIN_FIT_VISITS:
            msg = f"only {len(counts)} visits carry a bag-of-words histogram; the appearance prior needs 2"
            raise ModelError(msg)
        if config.dcm_alpha is not None:
            dcm_alpha = np.full(counts.shape[1], config.dcm_alpha)
        else:
            dcm_alpha = estimate_dcm_alpha(
                counts, min_alpha=config.dcm_min_alpha, tol=config.dcm_tol, max_iter=config.dcm_max_iter
            )
    return AppearanceModel(nig=nig, dcm_alpha=dcm_alpha)


def _stack_signatures(
    visits: Sequence[Visit], indices: Sequence[int], dim: int | None = None, *, skip_missing: bool = True
) -> FloatArray:
    """The ``(n, K)`` signatures of the visits ``indices`` that have one (a visit without a panorama is a
    missing measurement: its factor integrates to 1, so it is left out); ``skip_missing=False`` raises."""
    rows = []
    for i in indices:
        sig = visits[i].signature
        if sig is None:
            if skip_missing:
                continue
            msg = f"visit {i} has no Fourier signature but the appearance model needs one"
            raise ModelError(msg)
        rows.append(np.asarray(sig, dtype=float).reshape(-1))
    if len({r.size for r in rows} | ({dim} if dim is not None else set())) > 1:
        msg = "visits have Fourier signatures of different lengths"
        raise ModelError(msg)
    return np.array(rows, dtype=float).reshape(len(rows), -1 if rows else (dim or 0))


def _stack_words(
    visits: Sequence[Visit], indices: Sequence[int], size: int | None, *, skip_missing: bool = True
) -> IntArray:
    """The ``(n, V)`` word histograms of the visits ``indices`` that have one (see
    :func:`_stack_signatures`)."""
    rows = []
    for i in indices:
        words = visits[i].words
        if words is None:
            if skip_missing:
                continue
            msg = f"visit {i} has no bag-of-words histogram but the appearance model needs one"
            raise ModelError(msg)
        rows.append(_counts(words, 1))
    sizes = {r.size for r in rows} | ({size} if size is not None else set())
    if len(sizes) > 1:
        msg = f"bag-of-words histograms of different lengths {sorted(sizes)}"
        raise ModelError(msg)
    if not rows:
        return np.zeros((0, size or 0), dtype=np.int64)
    return np.stack(rows)


def block_log_likelihood(block: Block, visits: Sequence[Visit], model: AppearanceModel) -> float:
    """``log p(a_s)`` of the visits of one block (one place), all configured models multiplied."""
    out = 0.0
    if model.nig is not None:
        out += log_marginal_nig(_stack_signatures(visits, block, model.nig.dim), model.nig)
    if model.dcm_alpha is not None:
        out += log_marginal_dcm(_stack_words(visits, block, model.dcm_alpha.size), model.dcm_alpha)
    return out


def appearance_log_likelihood(
    labels: Sequence[int],
    visits: Sequence[Visit],
    model: AppearanceModel,
    cache: dict[Block, float] | None = None,
) -> float:
    """``log P(A | T) = Σ_blocks log p(a_s)`` of the topology ``labels`` (eq. 22, 24, 54).

    ``cache`` (optional) maps a block (sorted tuple of visit indices) to its log factor; pass the same
    dict across calls with the same visits and model (it is only valid for those) to reuse blocks.
    """
    if len(labels) != len(visits):
        msg = f"labels cover {len(labels)} visits but {len(visits)} visits were given"
        raise ModelError(msg)
    total = 0.0
    for block in blocks(labels):
        if cache is None:
            total += block_log_likelihood(block, visits, model)
            continue
        value = cache.get(block)
        if value is None:
            value = block_log_likelihood(block, visits, model)
            cache[block] = value
        total += value
    return total


def appearance_log_predictive(
    new: int, block: Block, visits: Sequence[Visit], model: AppearanceModel
) -> float:
    """``log p(a_new | a_block)`` (eq. 46): visit ``new`` seen at the place of the visits ``block``.

    An empty ``block`` is a new place (prior predictive). Equals the difference of
    :func:`block_log_likelihood` with and without ``new``.
    """
    n_visits = len(visits)
    if not 0 <= new < n_visits or new in block or any(not 0 <= i < n_visits for i in block):
        msg = f"visit {new} and block {block} are not a new visit and a place among {n_visits} visits"
        raise ModelError(msg)
    out = 0.0
    if model.nig is not None:
        sig = _stack_signatures(visits, [new], model.nig.dim)
        if len(sig):  # else a missing measurement: no appearance evidence
            stats = NigStats.from_signatures(_stack_signatures(visits, block, model.nig.dim))
            out += log_predictive_nig(sig[0], stats, model.nig)
    if model.dcm_alpha is not None:
        size = model.dcm_alpha.size
        x_new = _stack_words(visits, [new], size)
        if len(x_new):
            block_sum = _stack_words(visits, block, size).sum(axis=0)
            out += log_predictive_dcm(x_new[0], block_sum, model.dcm_alpha)
    return out
