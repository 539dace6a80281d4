"""The offline pipeline behind ``ptm-run``: bag → landmark visits → PTM → ptm.json, report, score.

The science is in the core modules; this module only loops over a recorded run, times, and writes
files (kiss-icp's ``pipeline.py`` plays the same role). The detector and filter nodes call the same core
functions on live messages.
"""

from __future__ import annotations

import heapq
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ptm_ros.config import PtmConfig, save_config
from ptm_ros.detectors import EquidistantDetector
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.geometry import Registrar
from ptm_ros.io.bag import RunData, read_run
from ptm_ros.landmarks import IMAGE, ODOM, SCAN, ExtractorConfig, VisitExtractor, diagnostics_dict
from ptm_ros.laser import patch_registrar
from ptm_ros.partitions import Labels
from ptm_ros.posterior import PosteriorModel, exact_posterior, normalize_log, top_k
from ptm_ros.ptm import Landmark, Ptm, make_ptm, save_ptm
from ptm_ros.visits import Visit

Progress = Callable[[Iterable[Any], int], Iterable[Any]]


def detector_kind(config: PtmConfig, *, has_scans: bool, has_images: bool) -> str:
    """The detector to use: the configured one, else the default for the sensors present: laser
    surprise with scans, equidistant otherwise (appearance surprise needs a vocabulary: ask for it).
    (The detector node decides with its ``use_scans`` / ``use_images`` parameters, ``ptm-run`` with the
    bag's topics, so both pick the same.)"""
    if config.detector.kind is not None:
        return config.detector.kind
    if has_scans and config.model.use_laser:
        return "laser-surprise"
    return "equidistant"


def run_sensors(run: RunData) -> dict[str, bool]:
    """Which sensor streams a recorded run has (keyword arguments of :func:`detector_kind`)."""
    return {
        "has_scans": run.scans is not None and len(run.scans.stamps) > 0,
        "has_images": run.images is not None and len(run.images.images) > 0,
    }


def make_detector(kind: str, config: PtmConfig) -> Any:
    """The streaming detector object of a kind (:mod:`ptm_ros.detectors`, :mod:`ptm_ros.surprise`)."""
    det = config.detector
    if kind == "laser-surprise":
        from ptm_ros.surprise import LaserSurpriseDetector

        return LaserSurpriseDetector(det.laser_surprise)
    if kind == "appearance-surprise":
        from ptm_ros.surprise import AppearanceSurpriseDetector
        from ptm_ros.vocabulary import Vocabulary

        vocabulary = Vocabulary.load(det.vocabulary) if det.vocabulary else None
        if det.appearance_surprise.model == "words" and vocabulary is None:
            msg = "appearance-surprise with model 'words' needs detector.vocabulary (a .npz vocabulary)"
            raise ConfigError(msg)
        return AppearanceSurpriseDetector(det.appearance_surprise, vocabulary)
    return EquidistantDetector(det.equidistant)


def make_extractor(config: PtmConfig, kind: str, *, use_scans: bool, use_images: bool) -> VisitExtractor:
    """The streaming visit extractor shared by ``ptm-run`` and the detector node."""
    ext = ExtractorConfig(
        use_scans=use_scans and config.model.use_laser,
        use_images=use_images,
        image_max_dt=config.detector.image_max_dt,
    )
    return VisitExtractor(
        make_detector(kind, config),
        laser=config.laser,
        appearance=config.model.appearance,
        config=ext,
        laser_odometry=config.laser_odometry,
    )


def merged_messages(run: RunData) -> Iterator[tuple[float, int, int]]:
    """(stamp, topic, index) of every message of a run in stamp order (odometry first on ties), the
    order in which a live robot's messages arrive."""
    streams = []
    for topic, data in ((ODOM, run.odometry), (SCAN, run.scans), (IMAGE, run.images)):
        if data is not None and len(data.stamps):
            streams.append([(float(t), topic, k) for k, t in enumerate(data.stamps)])
    return heapq.merge(*streams)


def detect_visits(run: RunData, config: PtmConfig, diagnostics: dict[str, Any] | None = None) -> list[Visit]:
    """Landmark visits of a recorded run, with their appearance signatures and laser patches.

    Feeds the run's messages in stamp order through :class:`ptm_ros.landmarks.VisitExtractor`, the same
    object the detector node uses; ``diagnostics`` (if given) receives the extractor's counters.
    """
    odom = run.odometry
    if odom is None or len(odom.stamps) == 0:
        msg = f"bag {run.path} has no odometry"
        raise DataError(msg)
    sensors = run_sensors(run)
    extractor = make_extractor(
        config,
        detector_kind(config, **sensors),
        use_scans=sensors["has_scans"],
        use_images=sensors["has_images"],
    )
    visits: list[Visit] = []
    for _, topic, k in merged_messages(run):
        if topic == ODOM:
            visits += extractor.on_odometry(odom.stamps[k], odom.poses[k])
        elif topic == SCAN:
            sc = run.scans
            visits += extractor.on_scan(
                sc.stamps[k],
                sc.ranges[k],
                sc.angle_min[k],
                sc.angle_increment[k],
                sc.range_min[k],
                sc.range_max[k],
            )
        else:
            visits += extractor.on_image(run.images.stamps[k], run.images.images[k])
    visits += extractor.flush()
    if diagnostics is not None:
        diagnostics.update(diagnostics_dict(extractor.diagnostics))
        if run.images is not None:
            diagnostics["images_skipped_by_reader"] = dict(run.images.skipped)
    return visits


def make_registrar(
    visits: Sequence[Visit], config: PtmConfig, diag: dict[str, Any] | None = None
) -> Registrar:
    """Laser registration of visit j's patch onto visit i's (i < j) under the same-place hypothesis."""
    return patch_registrar(visits, config.laser, diag)


@dataclass(frozen=True)
class Inference:
    """A PTM's topologies with probabilities, and method-specific details."""

    probabilities: dict[Labels, float]
    positions: dict[Labels, np.ndarray]
    log_posteriors: dict[Labels, float]
    details: dict[str, Any]


def infer(
    visits: Sequence[Visit],
    config: PtmConfig,
    *,
    registrar: Registrar | None = None,
    progress: Progress | None = None,
) -> Inference:
    """Run the configured estimator over a visit sequence."""
    inf = config.inference
    if not visits:
        msg = "no landmark visits were detected: nothing to infer"
        raise DataError(msg)
    model = PosteriorModel(visits, config.model, registrar=registrar, seed=inf.seed)
    if inf.method == "exact":
        if len(visits) > inf.max_exact_visits:
            msg = (
                f"exact enumeration over {len(visits)} visits is too large (max_exact_visits = "
                f"{inf.max_exact_visits}); use --method rbpf"
            )
            raise ConfigError(msg)
        logp = exact_posterior(model, progress=progress)
        probs = normalize_log(logp)
        ranked = dict(top_k(probs, inf.top))
        return Inference(
            probabilities=ranked,
            positions=_metric_positions(model, ranked),
            log_posteriors={lab: logp[lab] for lab in ranked},
            details={"n_topologies_evaluated": len(logp)},
        )
    if inf.method == "rbpf":
        return _infer_rbpf(visits, model, config, registrar, progress)
    if inf.method == "mcmc":
        return _infer_mcmc(model, config)
    msg = f"inference method {inf.method!r} is not available"
    raise ConfigError(msg)


def _metric_positions(model: PosteriorModel, labels: Iterable[Labels]) -> dict[Labels, np.ndarray]:
    """Optimised place positions of some topologies (from the cached metric likelihood)."""
    out = {}
    for lab in labels:
        res = model.terms(lab).metric_result
        if res is not None:
            out[lab] = res.place_positions
    return out


def _infer_mcmc(model: PosteriorModel, config: PtmConfig) -> Inference:
    """Batch MCMC over set partitions (thesis Ch. 2.1, 3.1-3.6), stopping when converged."""
    from ptm_ros.mcmc import run_mcmc

    inf = config.inference
    res = run_mcmc(model, inf.mcmc, inf.seed)
    ranked = dict(top_k(res.probabilities, inf.top))
    d = res.diagnostics
    return Inference(
        probabilities=ranked,
        positions=_metric_positions(model, ranked),
        log_posteriors={lab: res.log_posteriors[lab] for lab in ranked},
        details={
            "estimate": inf.mcmc.estimate,
            "iterations": d.iterations,
            "chains": d.chains,
            "betas": list(d.betas),
            "converged": d.converged,
            "stop_reason": d.stop_reason,
            "doubling_tv": d.doubling_tv,
            "chain_tv": d.chain_tv,
            "n_evaluated": d.n_evaluated,
            "samples": res.samples,
            "acceptance": dict(d.acceptance),
        },
    )


def _infer_rbpf(
    visits: Sequence[Visit],
    model: PosteriorModel,
    config: PtmConfig,
    registrar: Registrar | None,
    progress: Progress | None,
) -> Inference:
    """The Rao-Blackwellized particle filter over the whole run (thesis Algorithm 8)."""
    from ptm_ros.rbpf import RbpfConfig, run_filter

    inf = config.inference
    flt = run_filter(
        visits,
        RbpfConfig(particles=inf.particles, resample=inf.resample),
        model.prior,
        config.model.odometry,
        appearance=model.appearance,
        registrar=registrar,
        seed=inf.seed,
        progress=progress,
    )
    return rbpf_inference(flt, config)


def rbpf_inference(flt: Any, config: PtmConfig, **details: Any) -> Inference:
    """A particle filter's current ensemble as an :class:`Inference` (used by ``ptm-run`` and the node)."""
    inf = config.inference
    probs = flt.ptm_weights()
    logw = flt.log_weights()
    ranked = dict(top_k(probs, inf.top))
    updates = np.array([h.update_s for h in flt.history])
    return Inference(
        probabilities=ranked,
        positions={lab: flt.place_positions(lab) for lab in ranked},
        log_posteriors={lab: logw[lab] for lab in ranked},
        details={
            "resample": inf.resample,
            "n_topologies": flt.n_topologies,
            "ess": flt.history[-1].ess if flt.history else 0.0,
            "log_evidence": flt.log_evidence,
            "update_ms_median": float(np.median(updates) * 1e3) if len(updates) else 0.0,
            "update_ms_p95": float(np.percentile(updates, 95) * 1e3) if len(updates) else 0.0,
            **details,
        },
    )


def build_ptm(
    visits: Sequence[Visit],
    inference: Inference,
    config: PtmConfig,
    *,
    frame_id: str,
    wall_s: float,
    **extra: Any,
) -> Ptm:
    """The ptm.json content of an inference result."""
    landmarks = [Landmark(v.index, v.stamp, v.pose) for v in visits]
    inf = config.inference
    return make_ptm(
        landmarks,
        inference.probabilities,
        positions=inference.positions,
        log_posteriors=inference.log_posteriors,
        frame_id=frame_id,
        inference={"method": inf.method, "particles": inf.particles, "seed": inf.seed, **inference.details},
        timing={"wall_s": wall_s},
        extra=extra,
    )


@dataclass(frozen=True)
class RunResult:
    """What ``run_offline`` wrote."""

    ptm: Ptm
    ptm_path: Path
    report_path: Path | None
    score: Any | None
    diagnostics: dict[str, Any]


def find_ground_truth(bag: Path) -> Path | None:
    """The simulator's ground truth stored beside or inside the bag directory, if any."""
    for cand in (bag / "ground_truth.json", bag.parent / f"{bag.name}.ground_truth.json"):
        if cand.is_file():
            return cand
    return None


def run_offline(
    bag: str | Path,
    out_dir: str | Path,
    config: PtmConfig,
    *,
    ground_truth: str | Path | None = None,
    progress: Progress | None = None,
    write_report: bool = True,
) -> RunResult:
    """Bag in, ``out_dir/ptm.json`` + ``config.yaml`` + report (+ score when a ground truth is known)."""
    t0 = time.perf_counter()
    bag = Path(bag)
    out = Path(out_dir)
    topics = config.topics
    run = read_run(
        bag,
        odom_topic=topics.odom,
        scan_topic=topics.scan,
        image_topic=topics.panorama,
        require=(topics.odom,),
    )
    diag: dict[str, Any] = {}
    visits = detect_visits(run, config, diag)
    registrar = cached(make_registrar(visits, config, diag)) if config.model.use_laser else None
    result = infer(visits, config, registrar=registrar, progress=progress)
    wall = time.perf_counter() - t0
    frame_id = run.odometry.frame_id if run.odometry is not None else "odom"
    used = replace(config, detector=replace(config.detector, kind=detector_kind(config, **run_sensors(run))))
    ptm = build_ptm(
        visits,
        result,
        used,
        frame_id=frame_id or "odom",
        wall_s=wall,
        bag=str(bag),
        detector=used.detector.kind,
        diagnostics=diag,
    )
    ptm_path = save_ptm(ptm, out / "ptm.json")
    save_config(used, out / "config.yaml")
    score = None
    gt = Path(ground_truth) if ground_truth is not None else find_ground_truth(bag)
    if gt is not None:
        score = score_against(ptm, gt)
    report = None
    if write_report:
        from ptm_ros.report import write_report as _write_report

        traj = map_trajectory(run, visits, ptm.map_topology.labels, config, registrar)
        report = _write_report(out, ptm, trajectory=traj, score=score, title=f"PTM of {bag.name}")
    return RunResult(ptm=ptm, ptm_path=ptm_path, report_path=report, score=score, diagnostics=diag)


def cached(registrar: Registrar) -> Registrar:
    """A registrar that registers each pair once (shared by the estimator and the smoothing)."""
    memo: dict[tuple[int, int], Any] = {}

    def reg(i: int, j: int) -> Any:
        if (i, j) not in memo:
            memo[(i, j)] = registrar(i, j)
        return memo[(i, j)]

    return reg


def map_trajectory(
    run: RunData, visits: Sequence[Visit], labels: Labels, config: PtmConfig, registrar: Registrar | None
) -> np.ndarray:
    """The odometry trajectory smoothed for a topology: visit poses optimised under its same-place and
    laser constraints (:func:`ptm_ros.odometry.optimize_poses`), the path between deformed to fit
    (:func:`ptm_ros.smoothing.smoothed_trajectory`)."""
    from ptm_ros.odometry import optimize_poses
    from ptm_ros.smoothing import smoothed_trajectory

    odom = run.odometry
    model = PosteriorModel(visits, config.model, registrar=registrar)
    poses, _, _ = optimize_poses(labels, visits, config.model.odometry, model.loops(labels))
    return smoothed_trajectory(odom.stamps, odom.poses, [v.stamp for v in visits], poses)


def score_against(ptm: Ptm, ground_truth: str | Path) -> Any:
    """Score a PTM against a ground-truth file (simulator JSON or CARMEN ``*-gt-*.txt``)."""
    from ptm_ros.tools.evaluate import score_against_ground_truth

    return score_against_ground_truth(ptm, ground_truth)
