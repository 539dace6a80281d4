"""Helpers of the benchmarks whose mistakes would go unnoticed in their figures: the sensors
``bench/bench_calibration.py`` simulates, the cache of exact enumerations ``bench/bench_exact.py``
reuses, how ``bench/bench_missed_pairs.py`` classes passages and registrations, the logs
``bench/bench_perturbed_runs.py`` makes unlike themselves, how ``bench/bench_laser_odometry.py`` scores
the laser odometry, how ``bench/bench_filter_vs_batch.py`` finds a posterior's surest wrong merge and how
``bench/bench_heading_noise.py`` scores the registrations against the truth and how
``bench/bench_wrong_merges.py`` splits a wrong merge into its groups in truth."""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from bench_calibration import NOISE_LEVELS, Case, Sensors, sim_config
from bench_exact import _current
from bench_filter_vs_batch import worst_wrong_pair
from bench_heading_noise import CHI2_3_99, REVISIT_GAP, registration_errors, revisit_ratio
from bench_laser_odometry import LogInput, ScanPass, against_truth, laser_odometry_pass
from bench_missed_pairs import heading_class, outcome
from bench_perturbed_runs import drifted, every_nth_scan, laser_odometry_ate, pair_calibration_lines
from bench_wrong_merges import (
    FAR_M,
    closest,
    fitness_by_truth,
    outcomes_between,
    slides_by_truth,
    split_labels,
    truth_groups,
)

from ptm_ros.config import load_config, save_config
from ptm_ros.io.simulator import SimConfig, simulate
from ptm_ros.io.worlds import get_world
from ptm_ros.model.geometry import NoMatch, RelativePose, between
from ptm_ros.model.odometry import OdometryConfig, path_heading_variances
from ptm_ros.model.visits import Visit
from ptm_ros.perception.laser import FLAT_OPTIMUM, Registration

CASE = Case("loop", "aliased", "aliased-loop", "model", 0)


def test_calibration_cases_simulate_the_sensors_asked_for():
    """Without ``--scan-rate``/``--panorama-spacing`` the simulator's own sensors; with them, scans at
    that rate and a panorama every that many metres, all else the same."""
    plain = sim_config(CASE)
    assert plain == SimConfig(odometry=NOISE_LEVELS["model"])
    other = sim_config(CASE, Sensors(scan_rate=5.0, panorama_spacing=0.5))
    assert (other.laser.rate, other.camera.spacing) == (5.0, 0.5)
    assert replace(other, laser=plain.laser, camera=plain.camera) == plain
    world, rng = get_world(CASE.world), np.random.default_rng
    default_run, held_out = simulate(world, plain, rng(0)), simulate(world, other, rng(0))
    assert np.median(np.diff(held_out.scan_stamps)) == pytest.approx(0.2)
    assert np.median(np.diff(default_run.scan_stamps)) == pytest.approx(0.1)
    assert len(held_out.image_stamps) > 1.8 * len(default_run.image_stamps)
    assert Sensors(5.0, 0.5).tag == "scan5-pano0.5"


def test_a_cached_enumeration_is_reused_only_under_todays_parameters(tmp_path):
    """``bench_exact`` kept enumerations made under other defaults (the area model's, after the step prior
    became the default): a cached ``config.yaml`` must equal today's but for ``inference``."""
    params = tmp_path / "params.yaml"
    params.write_text("inference:\n  top: 500\n")
    saved = tmp_path / "exact" / "config.yaml"
    assert not _current(saved, params)  # nothing cached
    save_config(load_config(params, {"inference": {"method": "exact"}}), saved)
    assert _current(saved, params)  # the method differs, the model does not
    doc = yaml.safe_load(saved.read_text())
    other = "area" if doc["model"]["odometry"]["place_prior"] == "steps" else "steps"
    doc["model"]["odometry"]["place_prior"] = other
    saved.write_text(yaml.safe_dump(doc))
    assert not _current(saved, params)


def test_missed_pairs_classes_headings_both_ways_round():
    """Passages less than π/4 apart in heading go the same direction, more than 3π/4 opposite, whichever
    way round and across ±π."""
    assert [heading_class(d) for d in (0.1, -0.7, 2 * np.pi - 0.1)] == ["same direction"] * 3
    assert [heading_class(d) for d in (np.pi, -3.0, 3.0 + 2 * np.pi)] == ["opposite"] * 3
    assert [heading_class(d) for d in (np.pi / 2, -1.2, 2.3)] == ["across"] * 3


def test_missed_pairs_names_a_registration_by_its_reason():
    def reg(valid, reason):
        return Registration(np.zeros(3), np.eye(3), 0.5, 0.5, 0.5, 0.1, 50, 100, valid, reason)

    assert outcome(None) == "unregistrable"
    assert outcome(reg(True, "")) == "valid"
    assert outcome(reg(False, "inlier fraction 0.300 < 0.4 (source 0.3, target 0.5)")) == "inlier fraction"
    assert outcome(reg(False, f"{FLAT_OPTIMUM}: moving 0.5 m keeps ...")) == FLAT_OPTIMUM
    assert outcome(reg(False, "12 inliers < 30")) == "too few inliers"
    assert outcome(reg(False, "ambiguous: distinct solution [1, 2, 3] has ...")) == "ambiguous"


def _flaser(x, y, th, t):
    return f"FLASER 3 1.0 2.0 3.0 {x} {y} {th} {x} {y} {th} {t} host {t}"


def _odometry(line):
    tokens = line.split()
    return [float(v) for v in tokens[8:11]], [float(v) for v in tokens[5:8]]


def test_perturbed_logs_drop_every_other_scan_and_nothing_else():
    lines = ["# header", *(_flaser(k, 0, 0, k) for k in range(5)), "PARAM x 1"]
    kept = every_nth_scan(lines, 2)
    assert kept == ["# header", lines[1], lines[3], lines[5], "PARAM x 1"]


def test_pair_calibration_tables_pool_over_seeds_runs_and_logs():
    from ptm_ros.scoring.evaluation import PairReliability

    a = PairReliability.of([0.0, 0.5, 0.6, 1.0], [False, True, False, True])
    b = PairReliability.of([0.05, 0.55, 0.99], [True, True, False])
    rows = [
        {"run": "intel", "log": "as logged", "seed": 0, "pair_calibration": a.as_dict()},
        {"run": "aces", "log": "as logged", "seed": 0, "pair_calibration": b.as_dict()},
        {"run": "aces", "log": "drift", "seed": 0, "error": "failed"},
    ]
    lines = pair_calibration_lines(rows)
    table = {line.split(" | ")[0].lstrip("| "): line.split(" | ") for line in lines if line.startswith("| ")}
    # all: 7 pairs, 4 one place, 4 doubtful; one confident false merge (0.99), no confident miss.
    assert table["all"][1:7] == ["7", "4", "4", f"{(a + b).doubtful_gap:.2f}", "1", "0"]
    assert (
        table["log: as logged"][1] == "7" and table["run: intel"][1] == "4" and table["run: aces"][1] == "3"
    )
    assert table["all"][10] == "0.67 / 0.55 (3)"  # the 0.5-0.7 bin: 0.5, 0.6, 0.55, two of them one place
    assert pair_calibration_lines([{"run": "x", "log": "y", "error": "failed"}]) == []


def test_perturbed_logs_drift_by_the_bias_per_metre_and_the_scale():
    """An L-shaped path (3 m east, a left turn, 2 m north): without bias and scale the poses come back;
    with them the heading gains the bias per metre travelled and the travel its scale, the laser pose
    following the odometry's."""
    path = [(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, math.pi / 2), (3, 1, math.pi / 2), (3, 2, math.pi / 2)]
    lines = [_flaser(x, y, th, k) for k, (x, y, th) in enumerate(path)]
    for line, (x, y, th) in zip(drifted(lines, 0.0, 1.0), path, strict=True):
        odom, laser = _odometry(line)
        assert odom == pytest.approx([x, y, th], abs=1e-6) and laser == odom
    bias, scale = 0.01, 1.02
    out = [_odometry(line)[0] for line in drifted(lines, bias, scale)]
    # two 1 m steps east: the second taken already turned by the first's bias
    assert out[2] == pytest.approx([scale * (1 + math.cos(bias)), scale * math.sin(bias), 2 * bias], abs=1e-6)
    assert out[3][2] == pytest.approx(math.pi / 2 + 3 * bias, abs=1e-6)  # the turn itself adds no travel
    last = np.array(out[-1][:2]) - np.array(out[3][:2])  # two 1 m steps, the second turned by bias
    assert np.hypot(*last) == pytest.approx(2 * scale * math.cos(bias / 2), abs=1e-6)
    assert out[-1][2] == pytest.approx(math.pi / 2 + 5 * bias, abs=1e-6)


def test_the_laser_odometry_score_puts_each_heading_error_on_its_steps_status():
    """A straight 10-step path; the laser odometry turns 0.1 rad too far on a rejected step and 0.02 rad
    too little on a matched one, the wheels 0.05 rad too far on every step: the drift splits by status,
    the wheels' is theirs, and the ATE is that of the bent path."""
    from ptm_ros.model.geometry import compose

    truth = np.array([[float(k), 0.0, 0.0] for k in range(11)])
    stamps = np.arange(11.0)
    status = ("kept", *("matched",) * 4, "rejected", *("matched",) * 5)
    corrected, wheel = [truth[0]], [truth[0]]
    for k in range(1, 11):
        turn = {5: 0.1, 7: -0.02}.get(k, 0.0)
        corrected.append(compose(corrected[-1], [1.0, 0.0, turn]))
        wheel.append(compose(wheel[-1], [1.0, 0.0, 0.05]))
    scan = ScanPass(stamps, np.array(wheel), np.array(corrected), status, 0.0)
    got = against_truth(scan, stamps, truth)
    assert (got["scans"], got["steps_matched"], got["steps_rejected"], got["steps_kept"]) == (11, 9, 1, 0)
    assert got["heading_sum_rejected_rad"] == pytest.approx(0.1)
    assert got["heading_sum_matched_rad"] == pytest.approx(-0.02)
    assert got["heading_sum_rad"] == pytest.approx(0.08)
    assert got["wheel_heading_sum_rad"] == pytest.approx(0.5)
    assert 0.05 < got["ate_m"] < 0.5
    exact = against_truth(ScanPass(stamps, truth, truth, status, 0.0), stamps, truth)
    assert exact["ate_m"] == pytest.approx(0.0, abs=1e-9) and exact["heading_rms_rad"] == 0.0


def test_a_pass_of_the_family_shifts_the_offset_skips_scans_and_takes_the_overrides():
    """``laser_odometry_pass``: the learned offset plus the shift, held within [-1, 0]; the first ``skip``
    scans left out; the overrides reach the laser odometry. The wheels are the truth along a room, so the
    pass at the defaults is the truth."""
    from test_laser_odometry import room_scan

    stamps = np.arange(0.0, 12.0, 0.5)
    poses = np.column_stack([1.0 + 0.1 * stamps, np.full_like(stamps, 2.0), np.zeros_like(stamps)])
    scan_stamps = np.arange(1.0, 10.0)
    points = [room_scan([1.0 + 0.1 * t, 2.0, 0.0]) for t in scan_stamps]
    log = LogInput(stamps, poses, scan_stamps, points, learned_offset=-0.1)
    plain = laser_odometry_pass(log)
    assert plain.time_offset == -0.1 and len(plain.stamps) == 9
    assert np.allclose(plain.corrected[:, 0], 1.0 + 0.1 * (scan_stamps - 0.1), atol=0.02)
    shifted = laser_odometry_pass(log, 0.5, skip=3, overrides={"min_points": 10_000})
    assert shifted.time_offset == 0.0 and np.array_equal(shifted.stamps, scan_stamps[3:])
    assert set(shifted.status) == {"kept"}  # no scan has 10 000 points: none is matched
    assert laser_odometry_pass(log, -2.0).time_offset == -1.0
    with pytest.raises(TypeError):
        laser_odometry_pass(log, overrides={"no_such_field": 1})


def test_the_laser_odometry_ate_at_the_visits_aligns_rigidly_and_skips_visits_outside_the_truth(tmp_path):
    """Visits whose corrected poses are the truth turned and shifted score 0; one visit 0.4 m off scores
    its share of the RMS; a visit outside the ground truth's time span is left out."""
    from ptm_ros.io.groundtruth import GroundTruthTrajectory, save_sim_gt
    from ptm_ros.model.geometry import compose

    stamps = np.arange(0.0, 21.0)
    poses = np.array([[0.5 * t, 0.1 * t * t / 20.0, 0.0] for t in stamps])
    truth = save_sim_gt(GroundTruthTrajectory(stamps=stamps, poses_corrected=poses), tmp_path / "gt.json")
    moved = [compose([3.0, -2.0, 0.5], p) for p in poses]
    visits = [{"stamp": float(t), "corrected_pose": list(m)} for t, m in zip(stamps, moved, strict=True)]
    assert laser_odometry_ate(visits, truth) == pytest.approx(0.0, abs=1e-9)
    outside = [*visits, {"stamp": 99.0, "corrected_pose": [50.0, 50.0, 0.0]}]
    assert laser_odometry_ate(outside, truth) == pytest.approx(0.0, abs=1e-9)
    off = [dict(v) for v in visits]
    off[10]["corrected_pose"] = list(compose(moved[10], [0.4, 0.0, 0.0]))
    assert 0.05 < laser_odometry_ate(off, truth) < 0.4


def test_the_worst_wrong_pair_is_the_surest_merge_of_visits_far_apart_in_truth():
    """Visits at 0, 1 and 10 m (and one outside the ground truth's span): merging 0 and 10 m is wrong,
    merging 0 and 1 m is not, and the visit outside the span is not scored."""
    from ptm_ros.io.groundtruth import GroundTruthTrajectory
    from ptm_ros.model.ptm import Landmark, make_ptm

    stamps = np.arange(0.0, 11.0)
    poses = np.column_stack([stamps, np.zeros_like(stamps), np.zeros_like(stamps)])
    truth = GroundTruthTrajectory(stamps=stamps, poses_corrected=poses)
    landmarks = [Landmark(k, t, (0.0, 0.0, 0.0)) for k, t in enumerate((0.0, 1.0, 10.0, 99.0))]
    ptm = make_ptm(
        landmarks,
        {
            (0, 0, 1, 0): 0.6,  # right, but for the unscored visit
            (0, 1, 0, 2): 0.3,  # 0 m and 10 m merged
            (0, 0, 0, 0): 0.1,  # all merged
        },
    )
    assert worst_wrong_pair(ptm, truth) == pytest.approx(0.4)
    assert worst_wrong_pair(make_ptm(landmarks, {(0, 0, 1, 1): 1.0}), truth) == 0.0


def test_registrations_are_scored_against_the_true_relative_pose_with_aliases_and_far_pairs_apart():
    """An exact registration has no error and lies inside its ellipsoid; one 0.3 m and 0.1 rad off, with
    the floor covariance, lies outside; one a radian off is an alias; pairs 4 m apart or more in truth and
    visits outside the truth's span are not scored."""
    truth = SimpleNamespace(
        stamps=np.array([0.0, 1.0, 2.0, 3.0]),
        poses_corrected=np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.5], [1.0, 1.0, 1.0], [9.0, 0.0, 0.0]]),
    )
    stamps = np.array([0.0, 1.0, 2.0, 3.0, 5.0])  # visit 4 lies beyond the truth
    g = truth.poses_corrected
    cov = np.diag([0.05**2, 0.05**2, 0.02**2])
    exact = RelativePose(0, 1, between(g[0], g[1]), cov)
    off = RelativePose(0, 2, between(g[0], g[2]) + np.array([0.3, 0.0, 0.1]), cov)
    alias = RelativePose(1, 2, between(g[1], g[2]) + np.array([0.0, 0.0, 1.0]), cov)
    far = RelativePose(0, 3, between(g[0], g[3]), cov)
    outside = RelativePose(2, 4, np.zeros(3), cov)
    out = registration_errors(stamps, [exact, off, alias, far, outside], truth, (0.05, 0.02))
    assert (out["scored"], out["aliases"]) == (2, 1)
    assert out["xy_rms"] == pytest.approx(math.sqrt(0.3**2 / 2))
    assert out["th_median"] == pytest.approx(0.05)
    assert out["th_p90"] == pytest.approx(0.09)
    assert out["beyond_chi2_99"] == pytest.approx(0.5)
    assert CHI2_3_99 < (0.3 / 0.05) ** 2
    assert registration_errors(stamps, [far, outside], truth, (0.05, 0.02)) == {
        "scored": 0,
        "aliases": 0,
        "floor_xy": 0.05,
        "floor_th": 0.02,
    }


def test_a_wrong_merge_splits_into_its_groups_in_truth_keeping_chains_of_one_place_whole():
    """Visits 1.2 m apart stay together even when the chain they form reaches past 4 m of a third visit
    that a plain complete linkage would have grouped first; a group takes a chain only if no pair of
    them is more than 4 m apart."""
    xy = np.array([[0.0, 0.0], [0.7, 0.0], [3.0, 0.0], [4.2, 0.0], [5.4, 0.0], [20.0, 0.0], [0.2, 0.3]])
    assert truth_groups([0, 1, 2, 3, 4, 5, 6], xy) == [[0, 1, 6], [2, 3, 4], [5]]
    assert truth_groups([0, 1, 6], xy) == [[0, 1, 6]]
    assert truth_groups([], xy) == []
    labels = (0, 0, 0, 0, 0, 1, 0)
    assert split_labels(labels, [[0, 1, 6], [2, 3, 4], [5]]) == (0, 0, 1, 1, 1, 2, 0)
    # the closest pair across groups, whichever two groups hold it
    assert closest([[5], [0, 1, 6], [2, 3, 4]], xy) == pytest.approx(2.3)


def test_the_outcomes_between_groups_leave_out_pairs_inside_a_group_and_visits_outside():
    cov = np.eye(3)
    pairs = {
        (0, 1): RelativePose(0, 1, np.zeros(3), cov),  # inside a group
        (0, 2): RelativePose(0, 2, np.zeros(3), cov),
        (1, 2): NoMatch(1, 2, log_bayes=-2.0),
        (1, 3): NoMatch(1, 3, log_bayes=-1.0),
        (2, 9): NoMatch(2, 9, log_bayes=5.0),  # visit 9 in no group
        (0, 3): None,
    }
    assert outcomes_between([[0, 1], [2, 3]], pairs) == {"valid": 1, "failed": 2, "failed_log_bayes": -1.5}
    out = outcomes_between([[0, 1]], pairs)
    assert (out["valid"], out["failed"], math.isnan(out["failed_log_bayes"])) == (0, 0, True)


def test_the_heading_ratio_over_revisits_is_the_odometrys_error_between_visits_of_one_place():
    """Three laps of a 4 m square, a visit at each corner: the corrected odometry's heading drifts 0.1 rad
    per lap. Revisits are the same corner at least REVISIT_GAP (5) visits apart: (0, 8) and (1, 9), two laps
    apart (0.2 rad), not the visits one lap apart; the ratio is their error squared over the model's heading
    variance of the path between them, averaged, and a constant drift per metre explains it all. Without a
    revisit, none."""
    assert REVISIT_GAP == 5
    n = 10
    corners = np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])[np.arange(n) % 4]
    true_yaw = np.arange(n) * (math.pi / 2)
    truth = SimpleNamespace(
        stamps=np.arange(n, dtype=float), poses_corrected=np.column_stack([corners, true_yaw])
    )
    drift = 0.1 * (np.arange(n) // 4)
    visits = [
        Visit(
            k,
            float(k),
            (*corners[k], float(true_yaw[k] + drift[k])),
            travel=4.0 * (k > 0),
            rotation=math.pi / 2 * (k > 0),
        )
        for k in range(n)
    ]
    cum = path_heading_variances(visits, OdometryConfig())
    expected = np.mean([0.2**2 / (cum[8] - cum[0]), 0.2**2 / (cum[9] - cum[1])])
    out = revisit_ratio(visits, truth)
    assert (out["revisits"], out["revisit_ratio"]) == (2, pytest.approx(expected))
    # both revisits are 32 m of travel apart with 0.2 rad of error: a drift of 0.2 / 32 rad/m explains all
    assert out["drift_rad_per_m"] == pytest.approx(0.2 / 32.0)
    assert out["ratio_without_drift"] == pytest.approx(0.0, abs=1e-20)
    assert revisit_ratio(visits[:8], truth) == {"revisits": 0}


def test_the_fitness_by_truth_class_asks_only_far_pairs_and_near_pairs_visits_apart():
    """Visits on a line: pairs beyond FAR_M are "different", pairs within 1.5 m at least REVISIT_GAP visits
    apart are "same"; nothing else is registered, visits outside the truth never are, and the figures are
    those of the registrar's outcomes (None left out)."""
    xy = np.array([[0.0, 0], [1, 0], [2, 0], [3, 0], [4, 0], [0.5, 0], [20, 0], [30, 0]])
    inside = np.array([True] * 7 + [False])
    asked = []

    def registrar(i, j):
        asked.append((i, j))
        if (i, j) == (4, 6):
            return None
        far = np.hypot(*(xy[i] - xy[j])) > FAR_M
        return (
            NoMatch(i, j, log_bayes=-2.0 if far else 1.0)
            if (i, j) != (0, 6)
            else NoMatch(i, j, log_bayes=1.0)
        )

    out = fitness_by_truth(registrar, xy, inside, np.random.default_rng(0))
    far = {(i, 6) for i in range(6)}
    assert set(asked) == far | {(0, 5)}  # (0, 5): 0.5 m apart, 5 visits apart; (1, 5) is only 4 apart
    assert REVISIT_GAP == 5
    assert out["different"] == {
        "pairs": 5,
        "mean_log_bayes": pytest.approx((4 * -2.0 + 1.0) / 5),
        "share_positive": 0.2,
    }
    assert out["same"] == {"pairs": 1, "mean_log_bayes": 1.0, "share_positive": 1.0}


def test_slides_are_counted_per_truth_class_among_the_pairs_asked(monkeypatch):
    """Each asked pair scored by ptm-eval's radii is registered again; a flat optimum counts as a slide with
    the fitness evidence it would carry, other failures and valid matches do not; unscored pairs, visits
    outside the truth and pairs without a patch are left out."""
    import ptm_ros.perception.laser as laser
    from ptm_ros.perception.laser import LaserConfig, fitness_log_bayes

    xy = np.array([[0.0, 0], [1, 0], [10, 0], [2.5, 0], [20, 0], [0.5, 0]])
    inside = np.array([True, True, True, True, False, True])
    visits = [SimpleNamespace(patch=None if k == 5 else np.zeros((1, 2)) + k) for k in range(6)]
    verdicts = {
        (0, 1): FLAT_OPTIMUM + ": slides",
        (0, 2): FLAT_OPTIMUM + ": slides",
        (1, 2): "inlier fraction",
    }
    registered = []

    def register(a, b, cfg):
        i, j = int(a[0, 0]), int(b[0, 0])
        registered.append((i, j))
        reason = verdicts.get((i, j), "")
        return SimpleNamespace(valid=not reason, reason=reason, inlier_fraction=0.6)

    monkeypatch.setattr(laser, "register_patch_pair", register)
    asked = [(0, 1), (0, 2), (1, 2), (0, 3), (0, 4), (0, 5), (2, 3)]
    out = slides_by_truth(visits, asked, xy, inside, LaserConfig())
    # (0, 3): 2.5 m, unscored; (0, 4): outside the truth; (0, 5): no patch
    assert registered == [(0, 1), (0, 2), (1, 2), (2, 3)]
    lb = fitness_log_bayes(0.6)
    assert out["same"] == {"pairs": 1, "slides": 1, "slides_log_bayes": pytest.approx(lb)}
    assert out["different"] == {"pairs": 3, "slides": 1, "slides_log_bayes": pytest.approx(lb)}
