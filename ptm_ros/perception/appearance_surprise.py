"""Appearance surprise: landmarks where a panorama is surprising (thesis Ch. 4.7, Fig. 59; Fourier Ch. 2.5).

:class:`AppearanceSurpriseDetector` turns each panorama into a measurement and declares a landmark where
its Bayesian surprise rises above the predicted-surprise band: ``"words"`` (:data:`APPEARANCE_MODELS`), a
SIFT bag-of-words histogram (needs a :class:`~ptm_ros.model.vocabulary.Vocabulary`) under Elkan's EDCM
approximation of the Pólya model (eq. 60–66), or ``"fourier"``, log Fourier magnitudes under independent
Normal–Gamma components. The models, their closed-form KL divergences, the forgetting (``memory`` per
panorama, ``memory_distance`` per metre) and the band trigger are :mod:`ptm_ros.perception.surprise`'s
(Ch. 4.6); :class:`AppearanceSurpriseConfig` holds the parameters.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import ConfigError
from ptm_ros.model.appearance import fourier_signature
from ptm_ros.model.geometry import FloatArray
from ptm_ros.model.vocabulary import Vocabulary
from ptm_ros.perception.surprise import (
    EdcmPrior,
    EdcmStats,
    GaussianStats,
    NormalGamma,
    _SurpriseDetector,
    _vector,
    edcm_surprise_step,
    gaussian_surprise_step,
)
from ptm_ros.settings import Settings, setting

__all__ = [
    "APPEARANCE_MODELS",
    "AppearanceSurpriseConfig",
    "AppearanceSurpriseDetector",
]


#: The measurement models of :class:`AppearanceSurpriseDetector`.
APPEARANCE_MODELS = ("words", "fourier")


@dataclass(frozen=True)
class AppearanceSurpriseConfig(Settings):
    """Appearance surprise detector (thesis Ch. 4.7; Fourier variant Ch. 2.5)."""

    model: str = setting(
        "words",
        choices=APPEARANCE_MODELS,
        doc=(
            '``"words"`` (SIFT bag of words, EDCM; needs a vocabulary) or ``"fourier"`` (log Fourier '
            "magnitudes, independent Normal–Gamma components)."
        ),
    )
    memory: float = setting(
        5.0, gt=0, doc="forgetting per panorama, in panoramas (see the module docstring)."
    )
    memory_distance: float = setting(
        float("inf"),
        gt=0,
        finite=False,
        doc="forgetting per metre of odometry travel, in m (``inf`` = none).",
    )
    band_sigmas: float = setting(
        5.0, gt=0, doc="``k`` of the band ``mean + k·std`` of the predicted surprise."
    )
    samples: int = setting(
        200, ge=2, doc="measurements drawn from the predictive for the predicted surprise."
    )
    warmup: int = setting(3, ge=1, doc="panoramas absorbed before a landmark may be declared.")
    min_travel: float = setting(
        2.0,
        ge=0,
        doc="least odometry travel (m) between two landmarks (applies once odometry is fed).",
    )
    seed: int = setting(0, ge=0, doc="seed of the detector's random generator when none is passed in.")
    edcm_strength: float = setting(
        10.0, gt=0, doc="EDCM prior weight in word occurrences (:class:`EdcmPrior`)."
    )
    edcm_precision: float = setting(10.0, gt=0, doc="EDCM prior ``s = Σβ`` (its mode).")
    max_features: int = setting(0, ge=0, doc="strongest SIFT keypoints kept per panorama (0 = all).")
    contrast_threshold: float = setting(0.04, gt=0, doc="OpenCV SIFT contrast threshold.")
    n_coeffs: int = setting(8, ge=1, doc='Fourier coefficients (``"fourier"``).')
    log_floor: float = setting(
        1e-4, gt=0, doc='Fourier magnitudes are floored here before the log (``"fourier"``).'
    )
    prior_std: float = setting(
        0.5, gt=0, doc='within-place standard deviation of a log magnitude (``"fourier"``).'
    )
    prior_strength: float = setting(
        2.0,
        gt=0,
        doc='weight of the ``prior_std`` expectation in panoramas (Normal–Gamma prior; ``"fourier"``).',
    )
    prior_kappa: float = setting(
        0.1,
        gt=0,
        doc='prior pseudo-count of the place mean (centred on the first panorama; ``"fourier"``).',
    )


class AppearanceSurpriseDetector(_SurpriseDetector):
    """Declares landmarks where a panorama is surprising (thesis Ch. 4.7, Fig. 59).

    ``model="words"`` needs a :class:`~ptm_ros.model.vocabulary.Vocabulary` built beforehand (e.g. from
    another
    run). :meth:`on_image` returns True when a landmark is declared (at :attr:`last_landmark_stamp`).
    """

    def __init__(
        self,
        config: AppearanceSurpriseConfig | None = None,
        vocabulary: Vocabulary | None = None,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.config = config or AppearanceSurpriseConfig()
        cfg = self.config
        super().__init__(cfg.band_sigmas, cfg.warmup, cfg.min_travel)
        self._rng = rng if rng is not None else np.random.default_rng(cfg.seed)
        self._vocabulary = vocabulary
        self._edcm_prior: EdcmPrior | None = None
        self._edcm_stats = EdcmStats.empty(1)
        self._ng_prior: NormalGamma | None = None
        self._stats = GaussianStats.empty(cfg.n_coeffs)
        if cfg.model == "words":
            if vocabulary is None:
                msg = "the 'words' appearance surprise needs a Vocabulary"
                raise ConfigError(msg)
            self._edcm_prior = EdcmPrior(vocabulary.size, cfg.edcm_strength, cfg.edcm_precision)
            self._edcm_stats = EdcmStats.empty(vocabulary.size)

    def measurement(self, image: ArrayLike) -> FloatArray | NDArray[np.int64]:
        """The measurement of a panorama: word histogram ``(V,)`` or log Fourier magnitudes ``(K,)``."""
        cfg = self.config
        if self._vocabulary is not None and cfg.model == "words":
            return self._vocabulary.panorama_words(
                image, max_features=cfg.max_features, contrast_threshold=cfg.contrast_threshold
            )
        return np.log(np.maximum(fourier_signature(image, cfg.n_coeffs), cfg.log_floor))

    def on_image(self, stamp: float, image: ArrayLike) -> bool:
        """Feed one panorama (stamp in s); True when a landmark is declared."""
        self._check_stamp(stamp)
        return self._on_measurement(stamp, self.measurement(image))

    def on_measurement(self, stamp: float, measurement: ArrayLike) -> bool:
        """Feed a precomputed :meth:`measurement` (histogram or log magnitudes)."""
        self._check_stamp(stamp)
        return self._on_measurement(stamp, measurement)

    def _on_measurement(self, stamp: float, measurement: ArrayLike) -> bool:
        cfg = self.config
        factor = self._forgetting(cfg.memory, cfg.memory_distance)
        if self._edcm_prior is not None:
            before = self._edcm_stats.decay(factor)
            step = edcm_surprise_step(self._edcm_prior, before, measurement, self._rng, cfg.samples)
            self._edcm_stats = before.add(measurement)
            return self._record(stamp, step)
        v = _vector(measurement, cfg.n_coeffs)
        if self._ng_prior is None:
            shape = 1.0 + 0.5 * cfg.prior_strength
            rate = 0.5 * cfg.prior_strength * cfg.prior_std**2
            self._ng_prior = NormalGamma(
                v, np.full_like(v, cfg.prior_kappa), np.full_like(v, shape), np.full_like(v, rate)
            )
        before_g = self._stats.decay(factor)
        step = gaussian_surprise_step(self._ng_prior, before_g, v, self._rng, cfg.samples)
        self._stats = before_g.add(v)
        return self._record(stamp, step)
