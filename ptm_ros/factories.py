"""Factories: a configuration in, the swappable parts of the pipeline out (kiss-icp's ``get_*`` habit).

The offline run (``ptm-run``), the detector node and the filter session build their detector, visit
extractor and laser registrar here, from the same :class:`~ptm_ros.config.PtmConfig`, so that a visit
reaches the filter by one code path whether it comes from a bag or from live topics.
"""

from __future__ import annotations

import math
from collections.abc import Callable, MutableMapping, Sequence
from dataclasses import replace

from ptm_ros.config import PtmConfig
from ptm_ros.errors import ConfigError
from ptm_ros.model.geometry import NoMatch, RelativePose
from ptm_ros.model.visits import Visit
from ptm_ros.perception.detectors import Detector, EquidistantDetector, ScheduledDetector
from ptm_ros.perception.landmarks import ExtractorConfig, VisitExtractor
from ptm_ros.perception.laser import PatchRegistrar, WorkerPool, patch_registrar

#: What a laser registration of a visit pair gives (None: no information).
Registration = RelativePose | NoMatch | None


def detector_kind(config: PtmConfig, *, has_scans: bool, has_images: bool) -> str:
    """The detector to use: the configured one, else the default for the sensors present: laser
    surprise with scans, equidistant otherwise (appearance surprise needs a vocabulary: ask for it).
    (The detector node decides with its ``use_scans`` / ``use_images`` parameters, ``ptm-run`` with the
    bag's topics, so both pick the same.)"""
    del has_images  # no default detector needs panoramas; kept so callers state what they have
    if config.detector.kind is not None:
        return config.detector.kind
    if has_scans and config.model.use_laser:
        return "laser-surprise"
    return "equidistant"


def with_detector_kind(config: PtmConfig, *, has_scans: bool, has_images: bool) -> PtmConfig:
    """``config`` with ``detector.kind`` set to :func:`detector_kind`'s choice: the configuration a run
    used, as ``ptm-run`` and ``ptm-bringup`` save it (``config.yaml``)."""
    kind = detector_kind(config, has_scans=has_scans, has_images=has_images)
    return replace(config, detector=replace(config.detector, kind=kind))


def make_detector(kind: str, config: PtmConfig, schedule: Sequence[float] | None = None) -> Detector:
    """The streaming detector object of a kind (:mod:`ptm_ros.perception.detectors`,
    :mod:`ptm_ros.perception.laser_surprise`, :mod:`ptm_ros.perception.appearance_surprise`);
    ``ground-truth`` fires at the ``schedule`` stamps (landmarks fixed along the true path) and needs them.

    Raises:
        ConfigError: ``ground-truth`` without a schedule, or ``words`` appearance without a vocabulary.
    """
    det = config.detector
    if kind == "ground-truth":
        if schedule is None:
            msg = (
                "detector 'ground-truth' (landmarks fixed along the true path) needs the run's ground "
                "truth: only ptm-run can use it, with --ground-truth FILE or a simulated bag"
            )
            raise ConfigError(msg)
        return ScheduledDetector(schedule)
    if kind == "laser-surprise":
        from ptm_ros.perception.laser_surprise import LaserSurpriseDetector

        return LaserSurpriseDetector(det.laser_surprise)
    if kind == "appearance-surprise":
        from ptm_ros.model.vocabulary import Vocabulary
        from ptm_ros.perception.appearance_surprise import AppearanceSurpriseDetector

        vocabulary = Vocabulary.load(det.vocabulary) if det.vocabulary else None
        if det.appearance_surprise.model == "words" and vocabulary is None:
            msg = "appearance-surprise with model 'words' needs detector.vocabulary (a .npz vocabulary)"
            raise ConfigError(msg)
        return AppearanceSurpriseDetector(det.appearance_surprise, vocabulary)
    return EquidistantDetector(det.equidistant)


def make_extractor(
    config: PtmConfig,
    kind: str,
    *,
    use_scans: bool,
    use_images: bool,
    record_corrections: bool = False,
    schedule: Sequence[float] | None = None,
    patches: WorkerPool | None = None,
) -> VisitExtractor:
    """The streaming visit extractor shared by ``ptm-run`` and the detector node (``record_corrections``:
    keep the laser-odometry corrections for smoothing the whole trajectory offline; ``schedule``: the
    ``ground-truth`` detector's stamps; ``patches``: where the patches are built)."""
    ext = ExtractorConfig(
        use_scans=use_scans and config.model.use_laser,
        use_images=use_images,
        image_max_dt=config.detector.image_max_dt,
        record_corrections=record_corrections,
        # the mean distance between two visits of one place under the metric model (offsets N(0, 2σ_T² I))
        spread_distance=config.model.odometry.sigma_topology * math.sqrt(math.pi),
    )
    return VisitExtractor(
        make_detector(kind, config, schedule),
        laser=config.laser,
        appearance=config.model.appearance,
        config=ext,
        laser_odometry=config.laser_odometry,
        patches=patches,
    )


def make_registrar(
    visits: Sequence[Visit], config: PtmConfig, diag: MutableMapping[str, int] | None = None
) -> PatchRegistrar:
    """Laser registration of visit j's patch onto visit i's (i < j) under the same-place hypothesis
    (``visits`` may grow after the call: a pair is registered when asked for); ``diag`` receives the
    registration counters."""
    return patch_registrar(visits, config.laser, diag)


def cached(
    registrar: Callable[[int, int], Registration],
    memo: MutableMapping[tuple[int, int], Registration] | None = None,
) -> Callable[[int, int], Registration]:
    """A registrar that registers each pair once (shared by the estimator and the smoothing); ``memo``
    (optional) is the cache itself, pre-filled or read by the caller (a saved session's pairs)."""
    cache: MutableMapping[tuple[int, int], Registration] = {} if memo is None else memo

    def reg(i: int, j: int) -> Registration:
        if (i, j) not in cache:
            cache[(i, j)] = registrar(i, j)
        return cache[(i, j)]

    return reg
