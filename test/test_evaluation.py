"""Tests of ptm_ros.scoring.evaluation: pairwise scoring of a PTM against true positions."""

from __future__ import annotations

import itertools
import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import one_error_line
from scipy.cluster.hierarchy import fcluster, linkage

from ptm_ros.errors import ConfigError, DataError, ModelError
from ptm_ros.model.partitions import canonical
from ptm_ros.model.ptm import Landmark, Ptm, Topology, load_ptm, make_ptm, save_ptm
from ptm_ros.scoring import evaluation
from ptm_ros.scoring.evaluation import (
    PAIR_BIN_EDGES,
    EvalConfig,
    PairCounts,
    PairReliability,
    place_ids_from_positions,
    score_ptm,
    single_linkage_places,
)
from ptm_ros.tools.evaluate import main as eval_main
from ptm_ros.tools.evaluate import score_against_ground_truth

# Four visits: A, B, C, A again (0.5 m from the first).
XY4 = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [0.5, 0.0]])


def make(xy: np.ndarray, tops: list[tuple[tuple[int, ...], float]]) -> Ptm:
    """A PTM over visits at ``xy`` (odometry = truth) listing ``tops`` in the given order."""
    landmarks = tuple(Landmark(i, float(i), (float(x), float(y), 0.0)) for i, (x, y) in enumerate(xy))
    return Ptm(landmarks=landmarks, topologies=tuple(Topology(lab, p) for lab, p in tops))


def brute_counts(xy: np.ndarray, labels: tuple[int, ...], r_same: float, r_diff: float) -> PairCounts:
    """TP/FP/FN/TN by a plain double loop over pairs."""
    tp = fp = fn = tn = 0
    for i, j in itertools.combinations(range(len(labels)), 2):
        d = math.dist(xy[i], xy[j])
        pred = labels[i] == labels[j]
        if d < r_same:
            tp, fn = tp + pred, fn + (not pred)
        elif d > r_diff:
            fp, tn = fp + pred, tn + (not pred)
    return PairCounts(tp, fp, fn, tn)


def test_perfect_map_scores_one_and_consistent_mass_is_its_mass() -> None:
    ptm = make(XY4, [((0, 1, 2, 0), 0.7), ((0, 1, 2, 3), 0.2), ((0, 0, 1, 0), 0.05)])
    s = score_ptm(ptm, XY4, true_places=[7, 8, 9, 7])
    assert (s.map.counts.precision, s.map.counts.recall, s.map.counts.f1) == (1.0, 1.0, 1.0)
    assert s.map.counts == PairCounts(1, 0, 0, 5)
    assert s.consistent_mass == pytest.approx(0.7)
    assert s.true_topology_mass == pytest.approx(0.7)
    assert (s.n_true_places, s.true_places_from, s.map.num_places) == (3, "place-ids", 3)
    assert (s.n_scored_pairs, s.n_same_pairs, s.n_different_pairs) == (6, 1, 5)


def test_contradictory_chain_is_reported_and_excluded_from_the_attainable_mass() -> None:
    """Visits 0-4 chained by 1.2 m gaps (must share a place) with 0 and 4 4.8 m apart (must differ): no
    topology scores all their pairs right; the far visit 5 is scored normally."""
    xy = np.array([[0.0, 0.0], [1.2, 0.0], [2.4, 0.0], [3.6, 0.0], [4.8, 0.0], [50.0, 0.0]])
    tops = [((0, 0, 0, 0, 0, 1), 0.5), ((0, 0, 0, 1, 1, 2), 0.3), ((0, 0, 0, 0, 0, 0), 0.2)]
    s = score_ptm(make(xy, tops), xy)
    for top, _ in tops:  # every topology gets some scored pair wrong
        assert brute_counts(xy, top, 1.5, 4.0).errors > 0
    assert s.consistent_mass == 0.0
    # scored pairs inside the chain: the 4 neighbours (same) and (0, 4) at 4.8 m (different)
    assert s.n_contradictory_pairs == 5
    # outside the chain only the pairs with visit 5 are scored: the third topology merges it wrongly
    assert s.attainable_consistent_mass == pytest.approx(0.8)
    doc = s.as_dict()
    assert doc["n_contradictory_pairs"] == 5 and doc["attainable_consistent_mass"] == pytest.approx(0.8)
    clean = score_ptm(make(XY4, [((0, 1, 2, 0), 0.7), ((0, 0, 1, 0), 0.3)]), XY4)
    assert clean.n_contradictory_pairs == 0
    assert clean.attainable_consistent_mass == clean.consistent_mass == pytest.approx(0.7)


def test_wrong_merge_precision_by_hand() -> None:
    # MAP merges B into A's place: predicted-same pairs (0,1), (0,3), (1,3); only (0,3) is truly same.
    s = score_ptm(make(XY4, [((0, 0, 1, 0), 1.0)]), XY4)
    assert s.map.counts == PairCounts(tp=1, fp=2, fn=0, tn=3)
    assert s.map.counts.precision == pytest.approx(1 / 3)
    assert s.map.counts.recall == 1.0
    assert s.map.counts.f1 == pytest.approx(2 * (1 / 3) / (1 / 3 + 1))
    assert s.consistent_mass == 0.0
    assert s.true_topology_mass is None
    assert s.n_true_places == 3  # single linkage on the true positions


def test_missed_revisit_has_zero_recall() -> None:
    s = score_ptm(make(XY4, [((0, 1, 2, 3), 1.0)]), XY4)
    assert s.map.counts == PairCounts(0, 0, 1, 5)
    assert (s.map.counts.precision, s.map.counts.recall, s.map.counts.f1) == (1.0, 0.0, 0.0)


def test_unscored_pairs_are_ignored() -> None:
    # Visit 4 is 2.5 m from visit 0 and 2.0 m from visit 3: both pairs are neither same nor different.
    xy = np.vstack([XY4, [[2.5, 0.0]]])
    merged = score_ptm(make(xy, [((0, 1, 2, 0, 0), 1.0)]), xy)
    apart = score_ptm(make(xy, [((0, 1, 2, 0, 3), 1.0)]), xy)
    assert merged.n_scored_pairs == apart.n_scored_pairs == 10 - 2
    assert merged.map.counts == apart.map.counts == PairCounts(1, 0, 0, 7)
    assert merged.consistent_mass == apart.consistent_mass == 1.0


def test_posterior_weighted_by_hand_on_three_topologies() -> None:
    # Listed mass 0.9 -> weights 5/9, 3/9, 1/9.
    tops = [((0, 1, 2, 0), 0.5), ((0, 0, 1, 0), 0.3), ((0, 1, 2, 3), 0.1)]
    s = score_ptm(make(XY4, tops), XY4)
    # per topology (TP, FP, FN, TN): (1,0,0,5), (1,2,0,3), (0,0,1,5)
    w = np.array([5, 3, 1]) / 9
    etp, efp, efn = w @ [1, 1, 0], w @ [0, 2, 0], w @ [0, 0, 1]
    assert s.listed_mass == pytest.approx(0.9)
    assert (s.expected.tp, s.expected.fp, s.expected.fn) == pytest.approx((8 / 9, 6 / 9, 1 / 9))
    assert s.expected.tn == pytest.approx(w @ [5, 3, 5])
    assert s.expected.precision == pytest.approx(etp / (etp + efp)) == pytest.approx(8 / 14)
    assert s.expected.recall == pytest.approx(8 / 9)
    assert s.expected.f1 == pytest.approx(2 * etp / (2 * etp + efp + efn)) == pytest.approx(16 / 23)
    assert s.mean_f1 == pytest.approx(w @ [1.0, 0.5, 0.0])
    assert s.consistent_mass == pytest.approx(0.5)  # not renormalised


def test_random_ptms_match_brute_force_and_pair_marginals() -> None:
    rng = np.random.default_rng(3)
    cfg = EvalConfig(same_radius=1.5, different_radius=4.0)
    for _ in range(20):
        n = int(rng.integers(2, 12))
        xy = rng.uniform(0.0, 8.0, size=(n, 2))
        k = int(rng.integers(1, 6))
        tops = list({canonical(rng.integers(0, 4, size=n).tolist()) for _ in range(k)})
        probs = rng.dirichlet(np.ones(len(tops))) * rng.uniform(0.3, 1.0)
        s = score_ptm(make(xy, list(zip(tops, probs, strict=True))), xy, config=cfg)
        brute = [brute_counts(xy, t, 1.5, 4.0) for t in tops]
        assert [t.counts for t in s.topologies] == brute
        # E[TP] = sum over truly-same pairs of the posterior co-location marginal P(i ~ j).
        w = probs / probs.sum()
        etp = efp = 0.0
        for i, j in itertools.combinations(range(n), 2):
            marginal = sum(wk for wk, t in zip(w, tops, strict=True) if t[i] == t[j])
            d = math.dist(xy[i], xy[j])
            etp += marginal * (d < 1.5)
            efp += marginal * (d > 4.0)
        assert s.expected.tp == pytest.approx(etp)
        assert s.expected.fp == pytest.approx(efp)
        consistent = sum(p for t, p, b in zip(tops, probs, brute, strict=True) if b.fp + b.fn == 0)
        assert s.consistent_mass == pytest.approx(consistent)


def test_chunked_counting_equals_unchunked(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(5)
    xy = rng.uniform(0, 10, size=(30, 2))
    tops = [(canonical(rng.integers(0, 6, size=30).tolist()), 0.01) for _ in range(40)]
    ptm = make(xy, tops)
    whole = score_ptm(ptm, xy)
    monkeypatch.setattr(evaluation, "_CHUNK_ELEMENTS", 7)
    assert score_ptm(ptm, xy).topologies == whole.topologies


def test_no_true_same_pairs_conventions() -> None:
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]])
    apart = score_ptm(make(xy, [((0, 1, 2), 1.0)]), xy)
    c = apart.map.counts
    assert (c.precision, c.recall, c.f1) == (1.0, 1.0, 1.0)
    merged = score_ptm(make(xy, [((0, 1, 0), 1.0)]), xy).map.counts
    assert (merged.precision, merged.recall, merged.f1) == (0.0, 1.0, 0.0)


def test_single_visit_and_empty_ptm_conventions() -> None:
    one = score_ptm(make(np.zeros((1, 2)), [((0,), 0.8)]), [[3.0, 4.0]], true_places=[5])
    assert (one.n_pairs, one.n_scored_pairs, one.n_true_places) == (0, 0, 1)
    assert (one.map.counts.precision, one.map.counts.recall, one.map.counts.f1) == (1.0, 1.0, 1.0)
    assert (one.expected.f1, one.mean_f1) == (1.0, 1.0)
    assert one.consistent_mass == one.true_topology_mass == pytest.approx(0.8)
    empty = score_ptm(make(np.zeros((0, 2)), [((), 1.0)]), np.zeros((0, 2)))
    assert (empty.n_visits, empty.n_true_places, empty.map.counts.f1) == (0, 0, 1.0)


def test_true_places_are_canonicalised_and_unlisted_truth_has_zero_mass() -> None:
    ptm = make(XY4, [((0, 0, 1, 0), 0.6), ((0, 1, 2, 0), 0.3)])
    assert score_ptm(ptm, XY4, true_places=[4, 2, 9, 4]).true_topology_mass == pytest.approx(0.3)
    assert score_ptm(ptm, XY4, true_places=[0, 1, 2, 3]).true_topology_mass == 0.0
    assert score_ptm(ptm, XY4, true_places=[0, 1, 2, 3]).n_true_places == 4


def test_single_linkage_chains_and_matches_scipy_hierarchy() -> None:
    chain = np.array([[0.0, 0.0], [1.4, 0.0], [2.8, 0.0], [4.2, 0.0], [5.8, 0.0]])
    assert single_linkage_places(chain, 1.5).tolist() == [0, 0, 0, 0, 1]
    rng = np.random.default_rng(11)
    for _ in range(10):
        xy = rng.uniform(0, 12, size=(40, 2))
        ref = fcluster(linkage(xy, method="single"), t=1.5, criterion="distance")
        assert single_linkage_places(xy, 1.5).tolist() == list(canonical(ref.tolist()))
    assert single_linkage_places(np.zeros((0, 2)), 1.5).size == 0


def test_as_dict_is_json_with_stable_keys() -> None:
    s = score_ptm(make(XY4, [((0, 1, 2, 0), 0.5), ((0, 0, 1, 0), 0.3)]), XY4, true_places=[0, 1, 2, 0])
    doc = json.loads(json.dumps(s.as_dict()))
    assert doc["schema"] == "ptm_ros.eval/1"
    assert doc["map_precision"] == 1.0 and doc["map_tp"] == 1 and doc["n_scored_pairs"] == 6
    assert doc["posterior_precision"] == pytest.approx(s.expected.precision)
    assert doc["consistent_mass"] == pytest.approx(0.5) and doc["true_topology_mass"] == pytest.approx(0.5)
    assert [t["consistent"] for t in doc["topologies"]] == [True, False]
    assert doc["topologies"][1]["fp"] == 2
    assert "topologies" not in s.as_dict(per_topology=False)


def test_thresholds_come_from_config() -> None:
    # With a 0.4 m same radius the 0.5 m revisit becomes unscored; 12 m different radius drops pairs too.
    s = score_ptm(make(XY4, [((0, 1, 2, 0), 1.0)]), XY4, config=EvalConfig(0.4, 12.0))
    assert (s.n_same_pairs, s.n_different_pairs) == (0, 1)  # only B-C (14.1 m) is scored


def test_errors() -> None:
    ptm = make(XY4, [((0, 1, 2, 0), 1.0)])
    with pytest.raises(ModelError, match=r"shape \(4, 2\)"):
        score_ptm(ptm, XY4[:3])
    with pytest.raises(ModelError, match="visit 2 is not finite"):
        score_ptm(ptm, np.where(np.arange(8).reshape(4, 2) == 4, np.nan, XY4))
    with pytest.raises(ModelError, match="visit 1 is not finite"):
        score_ptm(ptm, np.where(np.arange(4)[:, None] == 1, np.inf, XY4))
    with pytest.raises(ModelError, match="one entry per visit"):
        score_ptm(ptm, XY4, true_places=[0, 1])
    with pytest.raises(DataError, match="no topology"):
        score_ptm(make(XY4, []), XY4)
    with pytest.raises(DataError, match="zero total probability"):
        score_ptm(make(XY4, [((0, 1, 2, 0), 0.0)]), XY4)
    with pytest.raises(ModelError, match="topology 0 labels 3 visits"):
        score_ptm(make(XY4, [((0, 1, 2), 1.0)]), XY4)
    with pytest.raises(ConfigError, match="different_radius"):
        EvalConfig(same_radius=2.0, different_radius=1.0)
    with pytest.raises(ConfigError, match="same_radius must be > 0"):
        EvalConfig(same_radius=0.0)
    with pytest.raises(ConfigError, match="finite"):
        EvalConfig(different_radius=math.inf)


def test_thresholds_are_strict() -> None:
    # Exactly 1.5 m is not "same" and exactly 4.0 m is not "different": both pairs are unscored.
    xy = np.array([[0.0, 0.0], [1.5, 0.0], [-4.0, 0.0]])
    s = score_ptm(make(xy, [((0, 0, 1), 1.0)]), xy)
    assert (s.n_same_pairs, s.n_different_pairs) == (0, 1)  # only visits 1-2 (5.5 m) are scored
    assert s.n_true_places == 3


def test_visits_without_truth_are_left_out() -> None:
    # Visit 4 (NaN row) has no ground truth: its pairs are unscored whatever the topology says.
    xy = np.vstack([XY4, [[np.nan, np.nan]]])
    tops = [((0, 1, 2, 0, 0), 0.5), ((0, 1, 2, 0, 1), 0.5)]
    s = score_ptm(make(xy, tops), xy)
    assert (s.n_visits, s.n_visits_without_truth, s.n_true_places) == (5, 1, 3)
    assert (s.n_scored_pairs, s.n_same_pairs) == (6, 1)
    assert [t.counts for t in s.topologies] == [PairCounts(1, 0, 0, 5)] * 2
    assert s.consistent_mass == pytest.approx(1.0)
    assert s.as_dict()["n_visits_without_truth"] == 1


def test_place_ids_from_positions() -> None:
    places = [[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]
    ids = place_ids_from_positions(XY4 + 0.3, places, 1.5)
    assert ids is not None and ids.tolist() == [0, 1, 2, 0]
    off = XY4.copy()
    off[1, 1] += 2.0  # visit 1 is 2 m from B
    assert place_ids_from_positions(off, places, 1.5) is None
    assert place_ids_from_positions([[0.0, 0.0], [np.nan, np.nan]], places, 1.5) is None
    assert place_ids_from_positions(XY4, np.zeros((0, 2)), 1.5) is None


# ---- ptm-eval end to end ---------------------------------------------------------------------------

GT_HEADER = "# scan raw_scan_index logger_timestamp x_corr y_corr theta_corr x_raw y_raw theta_raw\n"


def write_carmen_gt(path: Path, stamps: list[float], xy: list[tuple[float, float]]) -> Path:
    """A 9-column CARMEN ground truth (raw odometry = truth shifted by 100 m in x)."""
    rows = [
        f"{k} {k} {t} {x} {y} 0.0 {x + 100} {y} 0.0"
        for k, (t, (x, y)) in enumerate(zip(stamps, xy, strict=True))
    ]
    path.write_text(GT_HEADER + "\n".join(rows) + "\n")
    return path


def run_cli(args: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, dict | None, str]:
    code = eval_main(args)
    out, err = capsys.readouterr()
    return code, (json.loads(out) if code == 0 else None), err


def test_cli_scores_carmen_ground_truth(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # Ground truth: the robot drives A(0,0) -> B(10,0) -> A(0,0) over 20 s, straight lines.
    gt = write_carmen_gt(tmp_path / "gt.txt", [0.0, 10.0, 20.0], [(0.0, 0.0), (10.0, 0.0), (0.0, 0.0)])
    # Landmarks at 0 s (A), 5 s (x=5), 19.9 s (x=0.1, A again) and 30 s (no truth: 10 s after the end);
    # their odometry is the log's raw odometry (the ground truth's x_raw = x + 100).
    stamps = [0.0, 5.0, 19.9, 30.0]
    raw_x = [100.0, 105.0, 100.1, 100.0]
    landmarks = [Landmark(i, t, (raw_x[i], 0.0, 0.0)) for i, t in enumerate(stamps)]
    ptm = make_ptm(landmarks, {(0, 1, 0, 2): 0.6, (0, 0, 0, 1): 0.3, (0, 1, 2, 3): 0.1})
    path = save_ptm(ptm, tmp_path / "run" / "ptm.json")
    code, doc, err = run_cli(
        [str(path), "--ground-truth", str(gt), "--report", str(tmp_path / "rep")], capsys
    )
    assert code == 0, err
    assert doc is not None
    # scored pairs: (0,2) same at 0.1 m; (0,1), (1,2) different at 5 m, 4.9 m; pairs with visit 3 unscored
    assert (doc["n_visits"], doc["n_visits_without_truth"], doc["n_scored_pairs"]) == (4, 1, 3)
    assert (doc["n_same_pairs"], doc["n_true_places"], doc["true_places_from"]) == (1, 2, "single-linkage")
    assert (doc["map_tp"], doc["map_fp"], doc["map_fn"], doc["map_f1"]) == (1, 0, 0, 1.0)
    assert doc["topologies"][1]["fp"] == 2 and doc["topologies"][2]["fn"] == 1
    assert doc["posterior_tp"] == pytest.approx(0.9)
    assert doc["posterior_fp"] == pytest.approx(0.6)
    assert doc["posterior_precision"] == pytest.approx(0.9 / 1.5)
    assert doc["consistent_mass"] == pytest.approx(0.6)
    assert doc["true_topology_mass"] is None
    assert (tmp_path / "rep" / "report.html").is_file()
    assert "visits without ground truth (unscored): 1" in (tmp_path / "rep" / "report.md").read_text()
    # --no-topologies drops the per-topology list
    code, doc, _ = run_cli([str(path), "--ground-truth", str(gt), "--no-topologies"], capsys)
    assert code == 0 and doc is not None and "topologies" not in doc


def test_cli_uses_simulator_places(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gt = {
        "schema": "ptm_ros.ground_truth/1",
        "frame_id": "map",
        "poses": {"stamp": [0.0, 10.0, 20.0], "x": [0.0, 10.0, 0.0], "y": [0.0, 0.0, 0.0], "yaw": [0.0] * 3},
        "places": [{"id": "a", "x": 0.0, "y": 0.0, "kind": "junction"}, {"id": "b", "x": 10.0, "y": 0.0}],
        "passages": [
            {"stamp": 0.0, "place": "a"},
            {"stamp": 10.0, "place": "b"},
            {"stamp": 20.0, "place": "a"},
        ],
    }
    (tmp_path / "ground_truth.json").write_text(json.dumps(gt))
    odometry = [(5.05, 3.0, 1.0), (-4.9, 3.0, 1.0), (5.0, 3.0, 1.0)]  # the truth's motion, turned half round
    landmarks = [Landmark(i, t, odometry[i]) for i, t in enumerate([0.05, 10.0, 19.9])]
    path = save_ptm(make_ptm(landmarks, {(0, 1, 0): 0.75, (0, 1, 2): 0.25}), tmp_path / "ptm.json")
    code, doc, err = run_cli([str(path), "--ground-truth", str(tmp_path)], capsys)  # the bag directory
    assert code == 0, err
    assert doc is not None
    assert (doc["true_places_from"], doc["n_true_places"]) == ("place-ids", 2)
    assert doc["true_topology_mass"] == pytest.approx(0.75)
    direct = score_against_ground_truth(load_ptm(path), tmp_path / "ground_truth.json")
    fit = {**doc.pop("odometry_fit")}
    assert {**direct.as_dict(), "map_quality": None} == doc  # no map beside the ptm.json
    assert fit["against"] == "poses" and fit["windows"] == 1 and fit["statistic"] < 1e-9 and fit["fits"]


def test_cli_bad_input_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    gt = write_carmen_gt(tmp_path / "gt.txt", [100.0, 110.0], [(0.0, 0.0), (10.0, 0.0)])
    landmarks = [Landmark(i, t, (0.0, 0.0, 0.0)) for i, t in enumerate([1.0, 2.0])]
    path = save_ptm(make_ptm(landmarks, {(0, 1): 1.0}), tmp_path / "ptm.json")
    (tmp_path / "bad.json").write_text('{"schema": "nope"}')
    (tmp_path / "gt.csv").write_text("1,2,3\n")
    cases = [
        ([str(path), "--ground-truth", str(gt)], "no landmark stamp"),
        ([str(tmp_path / "missing.json"), "--ground-truth", str(gt)], "cannot read"),
        ([str(tmp_path / "bad.json"), "--ground-truth", str(gt)], "invalid ptm.json"),
        ([str(path), "--ground-truth", str(tmp_path / "gt.csv")], "unknown file type"),
        ([str(path), "--ground-truth", str(tmp_path / "nothere.txt")], "does not exist"),
        ([str(path), "--ground-truth", str(gt), "--same-radius", "5", "--different-radius", "4"], "radius"),
        ([str(path), "--ground-truth", str(gt), "--max-extrapolation", "-1"], "max_extrapolation"),
    ]
    for args, message in cases:
        code, _, err = run_cli(args, capsys)
        assert code == 2, args
        assert err.startswith("ptm-eval: error:") and message in err, err
    with pytest.raises(SystemExit) as exc:
        eval_main([str(path)])  # --ground-truth missing: argparse's own exit status 2
    assert exc.value.code == 2


def test_cli_refuses_a_ground_truth_that_covers_few_landmarks(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue #25: another run's ground truth overlapping this one's clock only in part (most landmarks
    without truth) is refused with the figures, unless --force."""
    gt = write_carmen_gt(tmp_path / "gt.txt", [0.0, 10.0], [(0.0, 0.0), (10.0, 0.0)])
    landmarks = [Landmark(i, t, (0.0, 0.0, 0.0)) for i, t in enumerate([1.0, 9.0, 30.0, 40.0, 50.0])]
    path = save_ptm(make_ptm(landmarks, {(0, 1, 2, 3, 4): 1.0}), tmp_path / "ptm.json")
    code, _, err = run_cli([str(path), "--ground-truth", str(gt)], capsys)
    assert code == 2
    assert err.startswith("ptm-eval: error: 3 of 5 landmarks lie outside") and "--force" in err, err
    assert err.count("\n") == 1
    code, doc, err = run_cli([str(path), "--ground-truth", str(gt), "--force"], capsys)
    assert code == 0, err
    assert doc is not None and (doc["n_visits"], doc["n_visits_without_truth"]) == (5, 3)
    half = save_ptm(make_ptm(landmarks[:4], {(0, 1, 2, 3): 1.0}), tmp_path / "half" / "ptm.json")
    assert run_cli([str(half), "--ground-truth", str(gt)], capsys)[0] == 0  # 2 of 4: scored


def test_cli_on_intel_ground_truth(
    datasets_dir: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # Intel's logger stamps step back 4 times; landmarks at every 5th ground-truth scan take its pose.
    from ptm_ros.io.groundtruth import load_ground_truth

    gt_path = datasets_dir / "intel" / "intel-gt-910.txt"
    gt = load_ground_truth(gt_path)
    rows = np.arange(0, len(gt.stamps), 5)
    xy = gt.poses_corrected[rows, :2]
    landmarks = [Landmark(i, float(gt.stamps[r]), tuple(gt.poses_raw[r])) for i, r in enumerate(rows)]
    clusters = tuple(single_linkage_places(xy, 1.5).tolist())
    ptm = make_ptm(landmarks, {clusters: 0.7, tuple(range(len(rows))): 0.3})
    path = save_ptm(ptm, tmp_path / "ptm.json")
    code, doc, err = run_cli([str(path), "--ground-truth", str(gt_path)], capsys)
    assert code == 0, err
    assert doc is not None
    brute = [brute_counts(xy, t.labels, 1.5, 4.0) for t in ptm.topologies]
    assert [(t["tp"], t["fp"], t["fn"], t["tn"]) for t in doc["topologies"]] == [
        (c.tp, c.fp, c.fn, c.tn) for c in brute
    ]
    assert doc["n_visits_without_truth"] == 0
    assert doc["n_true_places"] == len(set(clusters))
    assert doc["map_recall"] == 1.0  # single linkage joins every pair closer than 1.5 m


# ------------------------------------------------------------------------------ odometry fit (issue #25)


def square_route(side: float, laps: int = 2, speed: float = 0.5, dt: float = 0.5) -> np.ndarray:
    """Poses ``(x, y, yaw)`` every ``dt`` s of a robot driving ``laps`` times round a square of ``side`` m
    at ``speed`` m/s (the simulator's worlds are such corridors)."""
    s = np.arange(0.0, 4 * side * laps, speed * dt) % (4 * side)
    side_k = (s // side).astype(int)
    corners = np.array([[0.0, 0.0], [side, 0.0], [side, side], [0.0, side]])
    heading = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]])
    xy = corners[side_k] + (s - side_k * side)[:, None] * heading[side_k]
    return np.column_stack([xy, np.arctan2(heading[side_k, 1], heading[side_k, 0])])


def drifting_odometry(poses: np.ndarray, heading_drift: float, scale: float) -> np.ndarray:
    """Odometry of ``poses``: their increments read ``scale`` too long and turned by ``heading_drift`` rad
    per metre, integrated from another origin (the odometry frame)."""
    from ptm_ros.model.geometry import between, compose

    out = [np.array([3.0, -2.0, 0.7])]
    for step in between(poses[:-1], poses[1:]):
        d = math.hypot(step[0], step[1])
        out.append(
            compose(out[-1], [(1 + scale) * step[0], (1 + scale) * step[1], step[2] + heading_drift * d])
        )
    return np.array(out)


@pytest.mark.slow
def test_fit_windows_and_residuals_match_a_plain_loop() -> None:
    rng = np.random.default_rng(8)
    true = np.cumsum(rng.normal(scale=1.5, size=(40, 2)), axis=0)
    odom = _rigid(true, 0.4, np.array([5.0, -1.0])) + rng.normal(scale=0.3, size=(40, 2))
    step = np.hypot(*np.diff(true, axis=0).T)
    windows = []
    for i in range(len(true)):  # the shortest run of >= 3 visits from i whose true path covers 8 m
        for j in range(i + 2, len(true)):
            if step[i:j].sum() >= 8.0:
                windows.append((i, j))
                break
    assert evaluation.fit_windows(true, 8.0) == windows and len(windows) > 20
    expected = []
    for i, j in windows:
        g = true[i : j + 1]
        spread = math.sqrt(np.mean(np.sum((g - g.mean(axis=0)) ** 2, axis=1)))
        expected.append(_brute_ate(odom[i : j + 1], g) / spread)
    np.testing.assert_allclose(evaluation.window_residuals(odom, true, 8.0), expected, rtol=1e-5)
    fit = evaluation.odometry_fit(odom, true)
    assert fit.statistic == pytest.approx(np.quantile(expected, 0.8), rel=1e-5)
    assert (fit.windows, fit.visits) == (len(windows), 40)


def test_odometry_fit_is_zero_for_the_same_motion_and_scale_free() -> None:
    true = square_route(12.0)[::6, :2]
    moved = _rigid(true, 2.0, np.array([-40.0, 7.0]))
    fit = evaluation.odometry_fit(moved, true)
    assert fit.statistic is not None and fit.statistic < 1e-9 and fit.fits and fit.windows > 40
    other = evaluation.odometry_fit(3.0 * moved, 3.0 * true, window_m=24.0)
    assert other.windows == fit.windows and other.statistic < 1e-9
    wrong = evaluation.odometry_fit(3.0 * moved[::-1], 3.0 * true, window_m=24.0)
    assert wrong.statistic == pytest.approx(evaluation.odometry_fit(moved[::-1], true).statistic, rel=1e-9)


def test_odometry_fit_accepts_drifting_odometry_and_refuses_another_route() -> None:
    """The hardest pair measured: a 12 m square loop's visits against the ground truth of an 18 m square
    loop driven at the same speed (the same straight stretches, corners elsewhere), beside the loop's own
    ground truth under Intel's heading drift (0.057 rad/m) and a 3 % scale error."""
    loop, ring = square_route(12.0), square_route(18.0)
    visits = np.arange(0, len(loop), 6)  # a landmark every 3 s
    odom = drifting_odometry(loop, heading_drift=0.057, scale=0.03)[visits, :2]
    own = evaluation.odometry_fit(odom, loop[visits, :2])
    other = evaluation.odometry_fit(odom, ring[visits, :2])
    assert own.statistic < 0.5 * evaluation.ODOMETRY_FIT_LIMIT and own.fits
    assert other.statistic > 1.5 * evaluation.ODOMETRY_FIT_LIMIT and not other.fits
    # odometry that did not move at all does not fit a truth that did
    assert not evaluation.odometry_fit(np.zeros_like(odom), loop[visits, :2]).fits


def test_odometry_fit_without_windows_is_not_judged() -> None:
    true = np.array([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0], [np.nan, np.nan], [6.0, 0.0]])
    fit = evaluation.odometry_fit(np.zeros((5, 2)), true)  # 6 m of travel: no 8 m window
    assert (fit.statistic, fit.windows, fit.visits, fit.fits) == (None, 0, 4, True)
    assert evaluation.odometry_fit(np.zeros((0, 2)), np.zeros((0, 2))).statistic is None
    with pytest.raises(ConfigError, match="quantile"):
        evaluation.odometry_fit(np.zeros((5, 2)), true, quantile=1.5)
    with pytest.raises(ConfigError, match="window_m"):
        evaluation.fit_windows(true[:3], 0.0)
    with pytest.raises(ModelError, match="one odometry position per true position"):
        evaluation.odometry_fit(np.zeros((4, 2)), true)


def write_route_gt(path: Path, poses: np.ndarray, stamps: np.ndarray, *, raw: np.ndarray | None) -> Path:
    """``poses`` at ``stamps`` as a ground truth: a CARMEN file with ``raw`` as its raw odometry, or (``raw``
    None) a ``ground_truth.json``."""
    if raw is not None:
        rows = [
            f"{k} {k} {t} {p[0]} {p[1]} {p[2]} {r[0]} {r[1]} {r[2]}"
            for k, (t, p, r) in enumerate(zip(stamps, poses, raw, strict=True))
        ]
        path.write_text(GT_HEADER + "\n".join(rows) + "\n")
        return path
    doc = {
        "schema": "ptm_ros.ground_truth/1",
        "frame_id": "map",
        "poses": {"stamp": stamps.tolist(), "x": poses[:, 0].tolist(), "y": poses[:, 1].tolist()}
        | {"yaw": poses[:, 2].tolist()},
    }
    path.write_text(json.dumps(doc))
    return path


def route_ptm(path: Path, odometry: np.ndarray, stamps: np.ndarray) -> Path:
    """A ptm.json of visits with this odometry at these stamps (one topology: all distinct)."""
    landmarks = [
        Landmark(i, float(t), tuple(float(v) for v in p))
        for i, (t, p) in enumerate(zip(stamps, odometry, strict=True))
    ]
    return save_ptm(make_ptm(landmarks, {tuple(range(len(landmarks))): 1.0}), path)


@pytest.mark.parametrize("carmen", [True, False], ids=["carmen-raw-odometry", "simulator-poses"])
def test_cli_refuses_a_ground_truth_whose_motion_the_odometry_does_not_follow(
    carmen: bool, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue #25: another run's ground truth on an overlapping clock (every landmark inside its time span)
    is refused with the figures and the way round it (--force); the run's own is scored."""
    stamps = 100.0 + 0.5 * np.arange(len(square_route(12.0)))
    loop, ring = square_route(12.0), square_route(18.0)[: len(stamps)]
    odom = drifting_odometry(loop, heading_drift=0.03, scale=0.02)
    visits = np.arange(0, len(stamps), 6)
    ptm = route_ptm(tmp_path / "run" / "ptm.json", odom[visits], stamps[visits])
    own = write_route_gt(
        tmp_path / ("own.txt" if carmen else "own.json"), loop, stamps, raw=odom if carmen else None
    )
    other_raw = drifting_odometry(ring, heading_drift=0.03, scale=0.02) if carmen else None
    other = write_route_gt(tmp_path / ("other.txt" if carmen else "other.json"), ring, stamps, raw=other_raw)

    code, doc, err = run_cli([str(ptm), "--ground-truth", str(own)], capsys)
    assert code == 0, err
    assert doc is not None and doc["n_visits_without_truth"] == 0
    fit = doc["odometry_fit"]
    assert fit["against"] == ("raw odometry" if carmen else "poses") and fit["fits"] and fit["windows"] > 40
    assert fit["statistic"] < (1e-9 if carmen else 0.5 * evaluation.ODOMETRY_FIT_LIMIT)

    code, doc, err = run_cli([str(ptm), "--ground-truth", str(other)], capsys)
    assert code == 2 and doc is None
    line = one_error_line(err, "ptm-eval")
    assert "does not move as the ground truth's" in line and "--force" in line
    figure = float(re.search(r"relative residual ([0-9.]+)", line).group(1))
    assert figure > evaluation.ODOMETRY_FIT_LIMIT and f"below {evaluation.ODOMETRY_FIT_LIMIT:g}" in line

    code, doc, err = run_cli([str(ptm), "--ground-truth", str(other), "--force"], capsys)
    assert code == 0, err
    assert doc is not None and not doc["odometry_fit"]["fits"]
    assert doc["odometry_fit"]["statistic"] == pytest.approx(figure, abs=0.006)


# --------------------------------------------------------------------------- absolute trajectory error


def _rigid(xy: np.ndarray, theta: float, t: np.ndarray) -> np.ndarray:
    c, s = math.cos(theta), math.sin(theta)
    return xy @ np.array([[c, -s], [s, c]]).T + t


def _brute_ate(est: np.ndarray, true: np.ndarray) -> float:
    """The smallest RMSE over rigid motions by a generic optimiser from several starting angles."""
    from scipy.optimize import minimize

    def cost(p: np.ndarray) -> float:
        return float(np.mean(np.sum((_rigid(est, p[0], p[1:]) - true) ** 2, axis=1)))

    best = min(
        (
            minimize(
                cost,
                [a, 0.0, 0.0],
                method="Nelder-Mead",
                options={"xatol": 1e-10, "fatol": 1e-14, "maxiter": 20_000},
            )
            for a in np.linspace(-math.pi, math.pi, 8, endpoint=False)
        ),
        key=lambda r: r.fun,
    )
    return math.sqrt(best.fun)


def test_ate_is_zero_for_a_rigidly_moved_path_and_recovers_the_motion() -> None:
    rng = np.random.default_rng(3)
    for _ in range(5):
        est = np.cumsum(rng.normal(size=(50, 2)), axis=0)
        theta, t = rng.uniform(-math.pi, math.pi), rng.normal(scale=20.0, size=2)
        true = _rigid(est, theta, t)
        assert evaluation.absolute_trajectory_error(est, true) < 1e-9
        got_theta, got_t = evaluation.rigid_alignment(est, true)
        assert math.isclose(math.remainder(got_theta - theta, 2 * math.pi), 0.0, abs_tol=1e-12)
        np.testing.assert_allclose(got_t, t, atol=1e-9)


def test_ate_matches_a_generic_optimiser_on_random_paths() -> None:
    rng = np.random.default_rng(11)
    for n in (2, 3, 10, 40):
        est = rng.normal(scale=5.0, size=(n, 2))
        true = _rigid(est, rng.uniform(-3, 3), rng.normal(size=2)) + rng.normal(scale=0.7, size=(n, 2))
        ate = evaluation.absolute_trajectory_error(est, true)
        assert ate == pytest.approx(_brute_ate(est, true), rel=1e-6, abs=1e-9)
        # never better than the identity nor worse than the unaligned RMSE
        assert ate <= math.sqrt(np.mean(np.sum((est - true) ** 2, axis=1))) + 1e-12


def test_ate_cannot_align_a_mirror_image() -> None:
    # A reflection is not a rigid motion: an L-shaped path and its mirror image stay apart.
    est = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [2.0, 1.0], [2.0, 2.0]])
    mirror = est * [1.0, -1.0]
    ate = evaluation.absolute_trajectory_error(est, mirror)
    assert ate > 0.3
    assert ate == pytest.approx(_brute_ate(est, mirror), rel=1e-6)
    assert evaluation.absolute_trajectory_error(est[:1], mirror[:1] + 7.0) == 0.0  # one point: exact


def test_ate_errors() -> None:
    xy = np.zeros((3, 2))
    with pytest.raises(ModelError, match="same non-zero number"):
        evaluation.absolute_trajectory_error(xy, xy[:2])
    with pytest.raises(ModelError, match="same non-zero number"):
        evaluation.absolute_trajectory_error(xy[:0], xy[:0])
    with pytest.raises(ModelError, match=r"true_xy must be \(n, 2\)"):
        evaluation.absolute_trajectory_error(xy, np.zeros((3, 3)))
    with pytest.raises(ModelError, match="est_xy must be finite"):
        evaluation.absolute_trajectory_error(np.where(xy == 0, np.nan, xy), xy)


# --------------------------------------------------------------------------------------------------
# Calibration over many runs (issue #23)


def brute_ece(p: np.ndarray, y: np.ndarray, n_bins: int) -> float:
    """ECE by a plain loop over bins [k/M, (k+1)/M), the last one closed at 1."""
    total = 0.0
    for k in range(n_bins):
        lo, hi = k / n_bins, (k + 1) / n_bins
        inside = [r for r in range(len(p)) if lo <= p[r] < hi or (k == n_bins - 1 and p[r] == 1.0)]
        if inside:
            gap = np.mean([y[r] for r in inside]) - np.mean([p[r] for r in inside])
            total += len(inside) / len(p) * abs(gap)
    return total


def test_ece_and_brier_by_hand() -> None:
    p, y = [0.95, 0.95, 0.15, 0.15], [True, False, False, False]
    # Bin 9: mean p 0.95, half right -> 0.45 x 2/4; bin 1: mean p 0.15, none right -> 0.15 x 2/4.
    assert evaluation.expected_calibration_error(p, y) == pytest.approx(0.225 + 0.075, abs=1e-12)
    assert evaluation.brier_score([0.9, 0.2, 0.5], [1, 0, 0]) == pytest.approx((0.01 + 0.04 + 0.25) / 3)
    # Bin edges: 0 in the first bin, 0.1 in the second, 1 in the last.
    bins = evaluation.reliability_bins([0.0, 0.1, 1.0, 0.999], [0, 1, 1, 0])
    assert [b.count for b in bins] == [1, 1, 0, 0, 0, 0, 0, 0, 0, 2]
    assert (bins[9].mean_probability, bins[9].accuracy) == (pytest.approx(0.9995), 0.5)
    assert math.isnan(bins[5].accuracy) and math.isnan(bins[5].mean_probability)
    # One bin: ECE = |right rate - mean p|.
    assert evaluation.expected_calibration_error([0.2, 0.6], [1, 1], n_bins=1) == pytest.approx(0.6)


def test_ece_matches_brute_force_on_random_samples() -> None:
    rng = np.random.default_rng(4)
    for n_bins in (1, 5, 10, 15):
        p = np.concatenate([rng.random(60), [0.0, 1.0, 0.5, 0.3, 0.7]])
        y = rng.random(p.size) < p**2
        assert evaluation.expected_calibration_error(p, y, n_bins) == pytest.approx(brute_ece(p, y, n_bins))


def test_calibrated_sample_has_small_ece_and_a_shifted_one_a_large_one() -> None:
    rng = np.random.default_rng(7)
    p = rng.random(20000)
    calibrated = rng.random(p.size) < p
    assert evaluation.expected_calibration_error(p, calibrated) < 0.02
    overconfident = rng.random(p.size) < np.clip(p - 0.3, 0.0, 1.0)
    ece = evaluation.expected_calibration_error(p, overconfident)
    assert ece > 0.2
    # Brier score E[p^2 - 2 p q + q] with q the true rate: 1/6 when q = p (uniform p); with q = max(p - 0.3,
    # 0): 1/3 - 2 (1/3 - 0.15 - 0.009 + 0.0135) + 0.245 = 0.20267.
    assert evaluation.brier_score(p, calibrated) == pytest.approx(1 / 6, abs=0.01)
    assert evaluation.brier_score(p, overconfident) == pytest.approx(0.20267, abs=0.01)


def test_chance_ece_matches_the_binomial_expectation() -> None:
    # All runs state p = 0.5 (one bin): ECE = |K/n - 1/2| with K ~ Binomial(n, 1/2).
    n = 20
    exact = sum(math.comb(n, k) * 0.5**n * abs(k / n - 0.5) for k in range(n + 1))
    eces = evaluation.chance_calibration_errors(np.full(n, 0.5), np.random.default_rng(0), redraws=20000)
    assert eces.shape == (20000,)
    assert eces.mean() == pytest.approx(exact, abs=4 * eces.std() / math.sqrt(eces.size))
    # Certain forecasts are redrawn as themselves: chance ECE 0. Same seed, same redraws.
    certain = evaluation.chance_calibration_errors([0.0, 1.0, 1.0], np.random.default_rng(1), redraws=50)
    assert np.all(certain == 0.0)
    again = evaluation.chance_calibration_errors(np.full(n, 0.5), np.random.default_rng(0), redraws=20000)
    assert np.array_equal(eces, again)


def test_calibration_summary_counts_overconfident_failures() -> None:
    p = [0.9, 0.8, 0.6, 0.99]
    right = [True, False, True, False]
    summary = evaluation.calibration_summary(
        p,
        right,
        np.random.default_rng(0),
        consistent_mass=[0.9, 0.01, 0.7, 0.049],
        true_topology_mass=[0.9, 0, 0.6, 0],
    )
    assert summary.overconfident_failures == 2  # consistent mass below 0.05
    assert summary.n_runs == 4 and summary.map_right_rate == 0.5
    assert summary.mean_map_probability == pytest.approx(np.mean(p))
    assert summary.ece == pytest.approx(brute_ece(np.array(p), np.array(right, dtype=float), 10))
    assert summary.brier == pytest.approx(evaluation.brier_score(p, right))
    assert summary.mean_true_topology_mass == pytest.approx(0.375)
    assert 0.0 < summary.chance_ece <= summary.chance_ece_p95
    doc = json.loads(json.dumps(summary.as_dict()))  # NaN-free JSON
    assert len(doc["bins"]) == 10 and doc["bins"][0]["accuracy"] is None
    assert doc["bins"][9]["count"] == 2 and doc["bins"][9]["accuracy"] == 0.5


def test_calibration_input_errors() -> None:
    with pytest.raises(ModelError, match="non-empty"):
        evaluation.expected_calibration_error([], [])
    with pytest.raises(ModelError, match=r"in \[0, 1\]"):
        evaluation.brier_score([1.2], [1])
    with pytest.raises(ModelError, match="one outcome per probability"):
        evaluation.brier_score([0.2, 0.3], [1])
    with pytest.raises(ModelError, match="booleans"):
        evaluation.brier_score([0.2], [0.5])
    with pytest.raises(ConfigError, match="n_bins"):
        evaluation.expected_calibration_error([0.2], [1], n_bins=0)
    with pytest.raises(ConfigError, match="redraws"):
        evaluation.chance_calibration_errors([0.2], np.random.default_rng(0), redraws=0)


def test_map_errors_against_truth_by_brute_force() -> None:
    assert evaluation.map_errors_against_truth([0, 1, 0, 2], [5, 6, 5, 7]) == (0, 0)
    assert evaluation.map_errors_against_truth([0, 0, 1], [0, 1, 1]) == (1, 1)
    rng = np.random.default_rng(3)
    for _ in range(50):
        lab, truth = rng.integers(0, 3, 7), rng.integers(0, 3, 7)
        fm = sum(lab[i] == lab[j] and truth[i] != truth[j] for i, j in itertools.combinations(range(7), 2))
        mm = sum(lab[i] != lab[j] and truth[i] == truth[j] for i, j in itertools.combinations(range(7), 2))
        assert evaluation.map_errors_against_truth(lab, truth) == (fm, mm)
        assert ((fm, mm) == (0, 0)) == (canonical(lab.tolist()) == canonical(truth.tolist()))
    with pytest.raises(ModelError, match="equally long"):
        evaluation.map_errors_against_truth([0, 1], [0])


SIM_GT = {
    "schema": "ptm_ros.ground_truth/1",
    "frame_id": "map",
    "poses": {"stamp": [0.0, 10.0, 20.0], "x": [0.0, 10.0, 0.0], "y": [0.0, 0.0, 0.0], "yaw": [0.0] * 3},
    "places": [{"id": "a", "x": 0.0, "y": 0.0, "kind": "junction"}, {"id": "b", "x": 10.0, "y": 0.0}],
    "passages": [{"stamp": 0.0, "place": "a"}, {"stamp": 10.0, "place": "b"}, {"stamp": 20.0, "place": "a"}],
}


def sim_run_dir(
    root: Path, tops: dict[tuple[int, ...], float], stamps: tuple[float, ...] = (0.05, 10.0, 19.9)
) -> Path:
    """A run directory with a ptm.json over visits at ``stamps`` and the simulator-style ground truth."""
    root.mkdir(parents=True)
    (root / "ground_truth.json").write_text(json.dumps(SIM_GT))
    landmarks = [Landmark(i, t, (0.0, 0.0, 0.0)) for i, t in enumerate(stamps)]
    save_ptm(make_ptm(landmarks, tops), root / "ptm.json")
    return root


def test_calibration_record_right_and_wrong_maps(tmp_path: Path) -> None:
    from ptm_ros.tools.evaluate import calibration_record

    right = sim_run_dir(tmp_path / "right", {(0, 1, 0): 0.75, (0, 1, 2): 0.25})
    rec = calibration_record(load_ptm(right / "ptm.json"), right / "ground_truth.json")
    assert rec["map_right"] is True and rec["map_probability"] == pytest.approx(0.75)
    assert (rec["map_false_merges"], rec["map_missed_merges"]) == (0, 0)
    assert rec["true_topology_mass"] == pytest.approx(0.75) and not rec["overconfident_failure"]
    # A missed revisit stated at 0.97: wrong, and an overconfident failure (consistent mass 0.03).
    wrong = sim_run_dir(tmp_path / "wrong", {(0, 1, 2): 0.97, (0, 1, 0): 0.03})
    rec = calibration_record(load_ptm(wrong / "ptm.json"), wrong / "ground_truth.json")
    assert rec["map_right"] is False and (rec["map_false_merges"], rec["map_missed_merges"]) == (0, 1)
    assert rec["consistent_mass"] == pytest.approx(0.03) and rec["overconfident_failure"]
    # A visit 5 m from every place: no exact truth, the MAP neither right nor wrong.
    far = sim_run_dir(tmp_path / "far", {(0, 1, 2): 1.0}, stamps=(0.05, 5.0, 19.9))
    rec = calibration_record(load_ptm(far / "ptm.json"), far / "ground_truth.json")
    assert rec["map_right"] is None and rec["true_topology_mass"] is None


def test_cli_calibration_over_run_directories(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    sim_run_dir(tmp_path / "runs" / "a", {(0, 1, 0): 0.75, (0, 1, 2): 0.25})
    sim_run_dir(tmp_path / "runs" / "b", {(0, 1, 2): 0.97, (0, 1, 0): 0.03})
    sim_run_dir(tmp_path / "runs" / "c", {(0, 1, 2): 1.0}, stamps=(0.05, 5.0, 19.9))
    plot = tmp_path / "rel.png"
    code, doc, err = run_cli(["--calibration", str(tmp_path / "runs"), "--plot", str(plot)], capsys)
    assert code == 0, err
    assert doc is not None and doc["schema"] == "ptm_ros.calibration/1"
    assert (doc["n_runs"], doc["n_runs_without_true_topology"]) == (3, 1)
    assert [r["map_right"] for r in doc["runs"]] == [True, False, None]
    cal = doc["calibration"]
    assert cal["n_runs"] == 2 and cal["overconfident_failures"] == 1
    assert cal["ece"] == pytest.approx(brute_ece(np.array([0.75, 0.97]), np.array([1.0, 0.0]), 10))
    assert cal["brier"] == pytest.approx((0.25**2 + 0.97**2) / 2)
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # The same runs named one by one (ptm.json files and a run directory) give the same figures.
    names = [
        str(tmp_path / "runs" / "a" / "ptm.json"),
        str(tmp_path / "runs" / "b"),
        str(tmp_path / "runs" / "c"),
    ]
    code, again, err = run_cli(["--calibration", *names], capsys)
    assert code == 0 and again is not None and again["calibration"] == cal


def test_cli_calibration_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = sim_run_dir(tmp_path / "a", {(0, 1, 0): 1.0})
    (run / "ground_truth.json").unlink()  # no ground truth beside it, none in its (absent) bag
    code, _, err = run_cli(["--calibration", str(run)], capsys)
    assert code == 2 and "no ground truth" in err
    (tmp_path / "empty").mkdir()
    code, _, err = run_cli(["--calibration", str(tmp_path / "empty")], capsys)
    assert code == 2 and "no ptm.json" in err
    far = sim_run_dir(tmp_path / "far", {(0, 1, 2): 1.0}, stamps=(0.05, 5.0, 19.9))
    with pytest.raises(SystemExit) as exc:  # one ptm.json at a time without --calibration
        eval_main([str(run / "ptm.json"), str(far / "ptm.json"), "--ground-truth", str(far)])
    assert exc.value.code == 2


def test_the_timeline_against_the_truth_of_the_visits_so_far():
    """Issue #25: after each visit the mass the PTM listed on the truth cut to the visits so far (or
    None, bounded by the least listed mass and the unlisted rest), and the first decision of a
    single-answer method that contradicts the truth of the visits so far."""
    from ptm_ros.model.ptm import TimelineStep
    from ptm_ros.scoring.evaluation import cut, first_wrong_visit, timeline_masses, unlisted_bound

    truth = (3, 1, 3, 7)  # any ids: visits 0 and 2 are one place
    assert [cut(truth, n) for n in range(1, 5)] == [(0,), (0, 1), (0, 1, 0), (0, 1, 0, 2)]
    steps = (
        TimelineStep(1, (((0,), 1.0),)),
        TimelineStep(2, (((0, 1), 0.8), ((0, 0), 0.2))),
        TimelineStep(3, (((0, 1, 2), 0.7), ((0, 0, 1), 0.25))),
        TimelineStep(4, (((0, 1, 0, 2), 0.9), ((0, 1, 2, 3), 0.06))),
    )
    assert timeline_masses(steps, truth) == (1.0, 0.8, None, 0.9)
    assert timeline_masses(steps, (0, 0, 1, 2)) == (1.0, 0.2, 0.25, None)
    assert [unlisted_bound(st) for st in steps] == pytest.approx([0.0, 0.0, 0.05, 0.04])
    assert unlisted_bound(TimelineStep(1, ())) == 1.0
    with pytest.raises(ModelError, match="labels of 3 visits cannot be cut to 4"):
        timeline_masses(steps, truth[:3])
    assert first_wrong_visit((5, 6, 5, 8), truth) is None  # the truth, under other ids
    assert first_wrong_visit((0, 0, 1, 2), truth) == 1  # joined visit 1 to visit 0's place
    assert first_wrong_visit((0, 1, 2, 0), truth) == 2  # missed the return to visit 0's place
    assert first_wrong_visit((0, 1, 0, 1), truth) == 3
    with pytest.raises(ModelError, match="labels of 3 visits against a truth of 4"):
        first_wrong_visit((0, 1, 0), truth)


def test_a_score_with_place_ids_keeps_the_true_topology():
    ptm = make_ptm([Landmark(k, float(k), (*XY4[k], 0.0)) for k in range(4)], {(0, 1, 2, 0): 1.0})
    assert score_ptm(ptm, XY4, true_places=[4, 2, 9, 4]).true_labels == (0, 1, 2, 0)
    assert score_ptm(ptm, XY4).true_labels is None


def brute_pair_table(
    xy: np.ndarray, tops: list[tuple[tuple[int, ...], float]], edges: tuple[float, ...]
) -> tuple[list[int], list[float], list[int]]:
    """Per bin of ``edges``: scored pairs outside the contradictory chains, summed P(i ~ j) and same
    pairs, by a plain loop over pairs."""
    total = sum(p for _, p in tops)
    count, psum, same = [0] * (len(edges) - 1), [0.0] * (len(edges) - 1), [0] * (len(edges) - 1)
    chains = single_linkage_places(xy, 1.5)
    spans = {c: max(math.dist(a, b) for a in xy[chains == c] for b in xy[chains == c]) for c in set(chains)}
    for i, j in itertools.combinations(range(len(xy)), 2):
        d = math.dist(xy[i], xy[j])
        if 1.5 <= d <= 4.0 or (chains[i] == chains[j] and spans[chains[i]] > 4.0):
            continue
        p = sum(w for t, w in tops if t[i] == t[j]) / total
        b = next(k for k in range(len(edges) - 1) if p < edges[k + 1] or k == len(edges) - 2)
        count[b] += 1
        psum[b] += p
        same[b] += d < 1.5
    return count, psum, same


def test_pair_calibration_matches_a_plain_loop_on_random_ptms() -> None:
    rng = np.random.default_rng(11)
    for _ in range(25):
        n = int(rng.integers(2, 12))
        xy = rng.uniform(0.0, 8.0, size=(n, 2))
        tops = list({canonical(rng.integers(0, 4, size=n).tolist()) for _ in range(int(rng.integers(1, 6)))})
        probs = rng.dirichlet(np.ones(len(tops))) * rng.uniform(0.3, 1.0)
        listed = list(zip(tops, probs, strict=True))
        table = score_ptm(make(xy, listed), xy).pairs
        assert table is not None
        count, psum, same = brute_pair_table(xy, listed, PAIR_BIN_EDGES)
        assert list(table.count) == count and list(table.same) == same
        assert list(table.probability_sum) == pytest.approx(psum)
        assert table.confident_false_merges == count[-1] - same[-1] and table.confident_misses == same[0]
        mid = sum(count[1:-1])
        gap = sum(abs(s - p) for s, p in zip(same[1:-1], psum[1:-1], strict=True)) / mid if mid else math.nan
        assert table.doubtful == mid and (table.doubtful_gap == pytest.approx(gap) or math.isnan(gap))


def test_pair_calibration_by_hand() -> None:
    # XY4: the one same pair (0, 3) at 0.5 m; (1, 2) at 14.1 m; the pairs 0-1, 0-2, 1-3, 2-3 beyond 4 m.
    s = score_ptm(make(XY4, [((0, 1, 2, 0), 0.5), ((0, 0, 1, 0), 0.3), ((0, 1, 2, 3), 0.2)]), XY4)
    doc = s.as_dict()["pair_calibration"]
    # P(0 ~ 3) = 0.8 (same); P(0 ~ 1) = P(1 ~ 3) = 0.3 (different); the other three 0.
    assert doc["pairs"] == 6 and doc["doubtful_pairs"] == 3
    assert doc["confident_false_merges"] == 0 and doc["confident_misses"] == 0
    assert doc["doubtful_gap"] == pytest.approx((abs(1 - 0.8) + abs(0 - 0.6)) / 3)
    bins = {(b["lo"], b["hi"]): b for b in doc["bins"]}
    assert bins[(0.0, 0.02)]["count"] == 3 and bins[(0.0, 0.02)]["share_same"] == 0.0
    assert bins[(0.3, 0.5)]["count"] == 2 and bins[(0.3, 0.5)]["mean_probability"] == pytest.approx(0.3)
    assert bins[(0.7, 0.9)]["same"] == 1 and bins[(0.9, 0.98)]["mean_probability"] is None
    # A confident wrong merge and a confident miss are counted as such.
    s = score_ptm(make(XY4, [((0, 0, 1, 2), 1.0)]), XY4)
    assert s.pairs is not None and (s.pairs.confident_false_merges, s.pairs.confident_misses) == (1, 1)
    assert s.pairs.summary() == (
        "pair calibration: 0 of 6 pairs stated 0.02-0.98; confident false merges (different, stated "
        ">= 0.98) 1, confident misses (same, stated < 0.02) 1"
    )
    # A chain 1.2 m apart spanning 4.8 m (no topology scores it right) and a far visit: the chain's
    # contradictory pairs (4 same, 1 different) are left out, its other pairs (1.5-4 m) are unscored.
    chain = np.array([[1.2 * k, 0.0] for k in range(5)] + [[0.0, 20.0]])
    s = score_ptm(make(chain, [((0, 0, 0, 1, 1, 2), 0.6), ((0, 0, 0, 0, 0, 1), 0.4)]), chain)
    assert s.n_contradictory_pairs == 5 and s.n_scored_pairs == 10 and s.pairs is not None
    assert sum(s.pairs.count) == 5 and s.pairs.count[0] == 5  # the far visit's pairs, stated 0


def test_pair_tables_pool_by_addition_and_round_trip_through_json() -> None:
    rng = np.random.default_rng(4)
    p, y = rng.uniform(0, 1, 300) ** 3, rng.uniform(0, 1, 300) < 0.4
    whole = PairReliability.of(p, y)
    pooled = PairReliability.of(p[:120], y[:120]) + PairReliability.of(p[120:], y[120:])
    assert pooled.count == whole.count and pooled.same == whole.same
    assert pooled.probability_sum == pytest.approx(whole.probability_sum)
    assert PairReliability.from_dict(json.loads(json.dumps(whole.as_dict()))) == whole
    assert sum(PairReliability.of([], []).count) == 0 and math.isnan(PairReliability.of([], []).doubtful_gap)
    assert PairReliability.of([1.0, 0.98, 0.0], [True, False, False]).count[-1] == 2  # 1 in the last bin
    with pytest.raises(ModelError, match="different bins"):
        _ = whole + PairReliability.of(p, y, edges=(0.0, 0.1, 0.5, 1.0))
    with pytest.raises(ConfigError, match="edges"):
        PairReliability.of(p, y, edges=(0.0, 0.5, 1.0))
    with pytest.raises(ModelError, match="between 0 and"):
        PairReliability(count=(1,) * 8, probability_sum=(0.0,) * 8, same=(2,) + (0,) * 7)
    with pytest.raises(ModelError, match="in \\[0, 1\\]"):
        PairReliability.of([1.2], [True])


def test_cli_calibration_pools_the_pairs_and_runs_without_exact_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    sim_run_dir(tmp_path / "runs" / "a", {(0, 1, 0): 0.75, (0, 1, 2): 0.25})
    sim_run_dir(tmp_path / "runs" / "b", {(0, 1, 2): 0.97, (0, 1, 0): 0.03})
    code, doc, err = run_cli(["--calibration", str(tmp_path / "runs")], capsys)
    assert code == 0 and doc is not None, err
    tables = [PairReliability.from_dict(r["pair_calibration"]) for r in doc["runs"]]
    assert PairReliability.from_dict(doc["pair_calibration"]) == tables[0] + tables[1]
    # The revisit pair (0, 2) of both runs: stated 0.75 and 0.03, one place both times.
    assert doc["pair_calibration"]["confident_misses"] == 0 and doc["pair_calibration"]["doubtful_pairs"] == 2
    # Runs with no exact truth (a real run's trajectory): no MAP calibration, the pairs and their diagram.
    far = sim_run_dir(tmp_path / "far", {(0, 1, 2): 1.0}, stamps=(0.05, 5.0, 19.9))
    plot = tmp_path / "pairs.png"
    code, doc, err = run_cli(["--calibration", str(far), "--plot", str(plot)], capsys)
    assert code == 0 and doc is not None, err
    assert doc["calibration"] is None and doc["pair_calibration"]["pairs"] >= 1
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_calibration_finds_the_carmen_ground_truth_ptm_run_scored_against(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Real runs scored by ``ptm-run --ground-truth FILE`` record the file (``trajectory_error``): the
    calibration mode finds it, each run its own, and pools their pairs."""
    gt_a = write_carmen_gt(tmp_path / "a.txt", [0.0, 10.0, 20.0], [(0.0, 0.0), (10.0, 0.0), (0.0, 0.0)])
    gt_b = write_carmen_gt(tmp_path / "b.txt", [0.0, 10.0, 20.0], [(0.0, 0.0), (0.0, 10.0), (0.0, 20.0)])
    landmarks = [Landmark(i, t, (100.0, 0.0, 0.0)) for i, t in enumerate((0.0, 10.0, 19.9))]
    for name, gt in (("a", gt_a), ("b", gt_b)):
        ptm = make_ptm(landmarks, {(0, 1, 0): 0.7, (0, 1, 2): 0.3})
        ptm = replace(ptm, extra={"trajectory_error": {"ate_smoothed_m": 0.1, "ground_truth": str(gt)}})
        save_ptm(ptm, tmp_path / "runs" / name / "ptm.json")
    code, doc, err = run_cli(["--calibration", str(tmp_path / "runs")], capsys)
    assert code == 0 and doc is not None, err
    assert [r["ground_truth"] for r in doc["runs"]] == [str(gt_a), str(gt_b)]
    assert doc["calibration"] is None  # CARMEN: no places, no exact truth
    # Run a revisits A (0 ~ 2 one place, stated 0.7); on run b's straight path visits 0 and 2 are 20 m apart.
    pairs = doc["pair_calibration"]
    assert pairs["doubtful_pairs"] == 2 and pairs["bins"][5]["same"] == 1 and pairs["bins"][5]["count"] == 2
    gt_a.unlink()  # a recorded file that is gone is no ground truth
    code, _, err = run_cli(["--calibration", str(tmp_path / "runs" / "a")], capsys)
    assert code == 2 and "no ground truth" in err
