"""The offline pipeline behind ``ptm-run``: bag → landmark visits → PTM → ptm.json, report, score.

The science is in the core modules; this module only loops over a recorded run, times, and writes
files (kiss-icp's ``pipeline.py`` plays the same role). The detector and filter nodes call the same core
functions on live messages.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ptm_ros.appearance import panorama_signature
from ptm_ros.config import PtmConfig, save_config
from ptm_ros.configio import to_dict
from ptm_ros.detectors import EquidistantDetector, OdometryTracker
from ptm_ros.errors import ConfigError, DataError, RegistrationError
from ptm_ros.geometry import interpolate_poses, wrap_angle
from ptm_ros.io.bag import RunData, read_run
from ptm_ros.laser import build_patch, passage_slice, register_patches, scan_to_points, to_relative_pose
from ptm_ros.partitions import Labels
from ptm_ros.posterior import PosteriorModel, Registrar, exact_posterior, normalize_log, top_k
from ptm_ros.ptm import Landmark, Ptm, make_ptm, save_ptm
from ptm_ros.visits import Visit

Progress = Callable[[Iterable[Any], int], Iterable[Any]]


@dataclass
class RunDiagnostics:
    """What the pipeline skipped or noticed, reported in ptm.json (``diagnostics``)."""

    odometry_messages: int = 0
    odometry_skipped: dict[str, int] = field(default_factory=dict)
    scans: int = 0
    scan_beams_dropped: int = 0
    images: int = 0
    images_skipped: dict[str, int] = field(default_factory=dict)
    visits_without_panorama: int = 0
    visits_without_patch: int = 0
    registrations: int = 0
    registrations_valid: int = 0

    def skip(self, reason: str) -> None:
        self.odometry_skipped[reason] = self.odometry_skipped.get(reason, 0) + 1


def detector_kind(run: RunData, config: PtmConfig) -> str:
    """The detector to use: the configured one, else the default for the bag's sensors."""
    kind = config.detector.kind or "equidistant"
    if kind != "equidistant":
        msg = f"detector {kind!r} is not available in this version; use 'equidistant'"
        raise ConfigError(msg)
    return kind


def detect_visits(run: RunData, config: PtmConfig, diagnostics: RunDiagnostics | None = None) -> list[Visit]:
    """Landmark visits of a recorded run, with their appearance signatures and laser patches."""
    diag = diagnostics if diagnostics is not None else RunDiagnostics()
    odom = run.odometry
    if odom is None or len(odom.stamps) == 0:
        msg = f"bag {run.path} has no odometry on {config.topics.odom}"
        raise DataError(msg)
    detector_kind(run, config)
    detector = EquidistantDetector(config.detector.equidistant)
    tracker = OdometryTracker()
    picked: list[tuple[int, float, float]] = []  # (odometry index, travel, rotation)
    diag.odometry_messages = len(odom.stamps)
    for k, (stamp, pose) in enumerate(zip(odom.stamps, odom.poses, strict=True)):
        if not (math.isfinite(stamp) and np.all(np.isfinite(pose))):
            diag.skip("non-finite")
            continue
        if tracker.last_stamp is not None and stamp < tracker.last_stamp:
            diag.skip("stamp-backwards")
            continue
        tracker.update(float(stamp), pose)
        if detector.on_odometry(float(stamp), pose):
            travel, rotation = tracker.reset()
            picked.append((k, 0.0 if not picked else travel, 0.0 if not picked else rotation))
    signatures = _signatures(run, [odom.stamps[k] for k, _, _ in picked], config, diag)
    patches = _patches(run, [(odom.stamps[k], odom.poses[k]) for k, _, _ in picked], config, diag)
    visits = []
    for n, (k, travel, rotation) in enumerate(picked):
        visits.append(
            Visit(
                index=n,
                stamp=float(odom.stamps[k]),
                pose=tuple(float(v) for v in odom.poses[k]),  # type: ignore[arg-type]
                travel=travel,
                rotation=rotation,
                signature=signatures[n],
                patch=patches[n],
            )
        )
    return visits


def _signatures(
    run: RunData, stamps: Sequence[float], config: PtmConfig, diag: RunDiagnostics
) -> list[np.ndarray | None]:
    images = run.images
    if images is None or not images.images:
        return [None] * len(stamps)
    diag.images = len(images.images)
    diag.images_skipped = dict(images.skipped)
    t = np.asarray(images.stamps, dtype=float)
    out: list[np.ndarray | None] = []
    for s in stamps:
        k = int(np.argmin(np.abs(t - s)))
        if abs(t[k] - s) > config.detector.image_max_dt:
            diag.visits_without_panorama += 1
            out.append(None)
            continue
        out.append(panorama_signature(images.images[k], config.model.appearance))
    return out


def _patches(
    run: RunData, visits: Sequence[tuple[float, np.ndarray]], config: PtmConfig, diag: RunDiagnostics
) -> list[np.ndarray | None]:
    scans, odom = run.scans, run.odometry
    if scans is None or odom is None or len(scans.stamps) == 0 or not config.model.use_laser:
        return [None] * len(visits)
    diag.scans = len(scans.stamps)
    lc = config.laser
    points = []
    for k in range(len(scans.stamps)):
        res = scan_to_points(
            scans.ranges[k],
            float(scans.angle_min[k]),
            float(scans.angle_increment[k]),
            float(scans.range_min[k]),
            min(float(scans.range_max[k]), lc.max_range),
        )
        diag.scan_beams_dropped += res.dropped
        points.append(res.points)
    scan_poses = interpolate_poses(odom.stamps, odom.poses, scans.stamps)
    out: list[np.ndarray | None] = []
    for stamp, pose in visits:
        sl = passage_slice(scans.stamps, scan_poses, stamp, pose, lc.patch_radius)
        patch = build_patch(points[sl], scan_poses[sl], pose, lc.patch_radius, lc.patch_voxel)
        if len(patch) < lc.min_points:
            diag.visits_without_patch += 1
            out.append(None)
        else:
            out.append(patch)
    return out


def make_registrar(
    visits: Sequence[Visit], config: PtmConfig, diag: RunDiagnostics | None = None
) -> Registrar:
    """Laser registration of visit j's patch onto visit i's (i < j), assuming they are one place."""
    lc = config.laser

    def registrar(i: int, j: int):
        a, b = visits[i], visits[j]
        if a.patch is None or b.patch is None:
            return None
        initial = (0.0, 0.0, float(wrap_angle(b.pose[2] - a.pose[2])))
        try:
            reg = register_patches(b.patch, a.patch, initial, lc)
        except RegistrationError:
            return None
        if diag is not None:
            diag.registrations += 1
            diag.registrations_valid += int(reg.valid)
        return to_relative_pose(reg, i, j)

    return registrar


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
        positions = {}
        for lab in ranked:
            res = model.terms(lab).metric_result
            if res is not None:
                positions[lab] = res.place_positions
        return Inference(
            probabilities=ranked,
            positions=positions,
            log_posteriors={lab: logp[lab] for lab in ranked},
            details={"n_topologies_evaluated": len(logp)},
        )
    if inf.method == "rbpf":
        return _infer_rbpf(visits, model, config, registrar, progress)
    msg = f"inference method {inf.method!r} is not available in this version; use 'exact' or 'rbpf'"
    raise ConfigError(msg)


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
    diagnostics: RunDiagnostics


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
    diag = RunDiagnostics()
    visits = detect_visits(run, config, diag)
    registrar = make_registrar(visits, config, diag) if config.model.use_laser else None
    result = infer(visits, config, registrar=registrar, progress=progress)
    wall = time.perf_counter() - t0
    frame_id = run.odometry.frame_id if run.odometry is not None else "odom"
    used = replace(config, detector=replace(config.detector, kind=detector_kind(run, config)))
    ptm = build_ptm(
        visits,
        result,
        used,
        frame_id=frame_id or "odom",
        wall_s=wall,
        bag=str(bag),
        detector=used.detector.kind,
        diagnostics=to_dict(diag),
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

        traj = run.odometry.poses if run.odometry is not None else None
        report = _write_report(out, ptm, trajectory=traj, score=score, title=f"PTM of {bag.name}")
    return RunResult(ptm=ptm, ptm_path=ptm_path, report_path=report, score=score, diagnostics=diag)


def score_against(ptm: Ptm, ground_truth: str | Path) -> Any:
    """Score a PTM against a ground-truth file (simulator JSON or CARMEN ``*-gt-*.txt``)."""
    from ptm_ros.tools.evaluate import score_against_ground_truth

    return score_against_ground_truth(ptm, ground_truth)
