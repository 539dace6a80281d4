"""Landmarks fixed in the environment (the thesis' Intel protocol, Ch. 4.5: placed 5 m from each other):
landmarks placed along the true path, their visits, the scheduled detector, and
``ptm-run --detector ground-truth``."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest

from ptm_ros.config import load_config
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.factories import make_detector
from ptm_ros.io.groundtruth import (
    GroundTruthTrajectory,
    Passage,
    Place,
    load_ground_truth,
    load_sim_gt,
    save_sim_gt,
    with_placed_landmarks,
)
from ptm_ros.io.simulator import SimConfig, simulate, write_run
from ptm_ros.io.worlds import get_world
from ptm_ros.model.geometry import interpolate_poses
from ptm_ros.model.posterior import same_place_probabilities
from ptm_ros.perception.detectors import (
    PlacedLandmarksConfig,
    ScheduledDetector,
    landmark_passages,
    place_landmarks,
    resample_path,
)
from ptm_ros.tools import evaluate as eval_cli
from ptm_ros.tools import run as run_cli
from ptm_ros.tools.outputs import RunResult
from ptm_ros.tools.pipeline import run_offline


def square_laps(laps: int = 2, side: float = 20.0, speed: float = 0.5, dt: float = 0.1) -> tuple:
    """Stamps and positions of ``laps`` laps around a square, one sample every ``dt`` s."""
    corners = np.array([[0, 0], [side, 0], [side, side], [0, side], [0, 0]], dtype=float)
    one = np.concatenate(
        [
            a + np.linspace(0, 1, int(side / (speed * dt)), endpoint=False)[:, None] * (b - a)
            for a, b in itertools.pairwise(corners)
        ]
    )
    xy = np.concatenate([one] * laps + [corners[:1]])
    return np.arange(len(xy)) * dt, xy


def greedy_by_hand(xy: np.ndarray, spacing: float) -> np.ndarray:
    marks = [xy[0]]
    for p in xy:
        if min(math.dist(p, m) for m in marks) >= spacing:
            marks.append(p)
    return np.array(marks)


def test_place_landmarks_is_the_sequential_greedy_scan_and_covers_the_path() -> None:
    rng = np.random.default_rng(3)
    heading = np.cumsum(rng.normal(0.0, 0.15, 3000))
    xy = np.cumsum(0.1 * np.column_stack([np.cos(heading), np.sin(heading)]), axis=0)
    for spacing in (2.0, 5.0):
        marks = place_landmarks(xy, spacing)
        assert np.array_equal(marks, greedy_by_hand(xy, spacing))
        gaps = np.hypot(*(marks[:, None] - marks[None]).transpose(2, 0, 1))
        assert np.all(gaps[np.triu_indices(len(marks), 1)] >= spacing)
        nearest = np.min(np.hypot(*(xy[:, None] - marks[None]).transpose(2, 0, 1)), axis=1)
        assert np.all(nearest < spacing)
    assert place_landmarks(np.zeros((0, 2)), 5.0).shape == (0, 2)


def test_each_lap_visits_each_landmark_once_at_its_closest_approach() -> None:
    stamps, xy = square_laps(laps=3)
    marks = place_landmarks(xy, 5.0)
    assert len(marks) == 16  # every 5 m around an 80 m square
    visits = landmark_passages(stamps, xy, marks, 1.0, 2.0)
    assert [s for s, _ in visits] == sorted(s for s, _ in visits)
    counts = np.bincount([j for _, j in visits], minlength=len(marks))
    # the start landmark is also passed at the very end of the last lap
    assert counts.tolist() == [4] + [3] * (len(marks) - 1)
    for stamp, j in visits:
        k = int(np.flatnonzero(stamps == stamp)[0])
        d = np.hypot(*(xy - marks[j]).T)
        lo, hi = k, k
        while lo > 0 and d[lo - 1] <= 2.0:
            lo -= 1
        while hi + 1 < len(d) and d[hi + 1] <= 2.0:
            hi += 1
        assert d[k] == pytest.approx(d[lo : hi + 1].min()) and d[k] <= 1.0


def test_grazing_the_capture_circle_is_one_visit_leaving_it_is_two() -> None:
    # in and out of the 1 m circle, never beyond 2 m, then away and back
    r = [3.0, 0.9, 1.5, 0.8, 1.9, 0.95, 3.0, 0.5, 3.0]
    xy = np.column_stack([r, np.zeros(len(r))])
    stamps = np.arange(len(r), dtype=float)
    visits = landmark_passages(stamps, xy, np.zeros((1, 2)), 1.0, 2.0)
    assert visits == [(3.0, 0), (7.0, 0)]
    # without hysteresis (leave = capture) each dip is a visit: the simulator's passages
    assert [s for s, _ in landmark_passages(stamps, xy, np.zeros((1, 2)), 1.0)] == [1.0, 3.0, 5.0, 7.0]


def test_resample_path_is_uniform_in_length_and_keeps_the_ends() -> None:
    stamps = np.array([0.0, 1.0, 2.0, 3.0, 5.0])
    xy = np.array([[0, 0], [1, 0], [1, 0], [1, 2], [1, 2.5]], dtype=float)  # stands still from 1 to 2 s
    t, p = resample_path(stamps, xy, 0.1)
    assert p[0].tolist() == [0, 0] and p[-1].tolist() == [1, 2.5] and t[-1] == 5.0
    assert np.allclose(np.hypot(*np.diff(p, axis=0).T)[:-1], 0.1)
    assert np.all(np.diff(t) > 0)
    assert t[np.argmin(np.hypot(*(p - [1, 1]).T))] == pytest.approx(2.5)  # halfway from 2 s to 3 s
    assert resample_path([4.0], [[1.0, 1.0]], 0.1)[0].tolist() == [4.0]
    t, p = resample_path([0.0, 1.0, 2.0], [[0, 0], [0.25, 0], [0.25, 0]], 0.1)  # stands still at the end
    assert t.tolist() == pytest.approx([0.0, 0.4, 0.8, 1.0]) and p[-1].tolist() == [0.25, 0]
    with pytest.raises(DataError, match="finite"):
        resample_path([0.0, 1.0], [[0, 0], [np.nan, 0]], 0.1)
    with pytest.raises(DataError):
        resample_path([0.0, 1.0], [[0, 0]], 0.1)


def test_scheduled_detector_fires_at_the_first_sample_at_or_after_each_stamp() -> None:
    det = ScheduledDetector([2.5, 1.0, 2.6])
    fired = [
        (t, det.last_landmark_stamp)
        for t in (0.0, 1.0, 2.0, 3.0, 4.0, 5.0)
        if det.on_odometry(t, np.zeros(3))
    ]
    assert fired == [(1.0, 1.0), (3.0, 2.5), (4.0, 2.6)]  # two stamps in one gap: one per sample
    with pytest.raises(DataError, match="finite"):
        ScheduledDetector([1.0, math.inf])


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("spacing", 0.0, "spacing"),
        ("step", math.nan, "step"),
        ("capture_radius", 3.0, "spacing / 2"),
        ("leave_radius", 0.5, "below capture_radius"),
    ],
)
def test_config_validation(field: str, value: float, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        PlacedLandmarksConfig(**{field: value})


def test_with_placed_landmarks_and_the_simulator_schema_round_trip(tmp_path: Path) -> None:
    stamps, xy = square_laps(laps=2)
    truth = GroundTruthTrajectory(stamps, np.column_stack([xy, np.zeros(len(xy))]), frame_id="map")
    placed = with_placed_landmarks(truth, PlacedLandmarksConfig(spacing=10.0))
    marks = greedy_by_hand(resample_path(stamps, xy, 0.05)[1], 10.0)
    assert [(pl.id, pl.x, pl.y, pl.kind) for pl in placed.places] == [
        (k, x, y, "placed") for k, (x, y) in enumerate(marks.tolist())
    ]
    k = len(marks)
    assert 6 <= k <= 8  # about every 10 m around the 80 m square
    assert len(placed.passages) == 2 * k + 1 and {ps.place for ps in placed.passages} == set(range(k))
    assert with_placed_landmarks(placed) is placed  # a truth with passages keeps its own
    back = load_sim_gt(save_sim_gt(placed, tmp_path / "gt.json"))
    assert np.array_equal(back.stamps, placed.stamps)
    assert np.array_equal(back.poses_corrected, placed.poses_corrected)
    assert (back.places, back.passages, back.frame_id) == (placed.places, placed.passages, "map")
    assert isinstance(back.places[0], Place) and isinstance(back.passages[0], Passage)
    assert back.poses_raw is None
    # a ground truth with its raw odometry (CARMEN's) keeps it: ptm-eval checks the odometry against it
    raw = placed.poses_corrected + np.array([100.0, -3.0, 0.25])
    with_raw = load_sim_gt(save_sim_gt(dataclasses.replace(placed, poses_raw=raw), tmp_path / "raw.json"))
    assert with_raw.poses_raw is not None and np.array_equal(with_raw.poses_raw, raw)


@pytest.fixture(scope="module")
def loop_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("sim") / "loop"
    write_run(simulate(get_world("aliased-loop"), SimConfig(), np.random.default_rng(2), visits=8), out)
    return out


@pytest.mark.slow
def test_ptm_run_with_the_ground_truth_detector_scores_the_true_topology(
    loop_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """On a simulated bag the detector fires at the simulator's passages (its world's places), so every
    visit has a true place and the mass on the true topology is scored; ``ptm-eval`` on the written
    ground truth agrees with ``ptm-run``."""
    out = tmp_path / "o"
    argv = [str(loop_bag), "--out", str(out), "--detector", "ground-truth"]
    assert run_cli.main([*argv, "--quiet", "--no-map", "--no-report"]) == 0
    printed = capsys.readouterr().out
    doc = json.loads((out / "ptm.json").read_text())
    truth = load_ground_truth(loop_bag)
    assert doc["detector"] == "ground-truth"
    assert [lm["stamp"] for lm in doc["landmarks"]] == pytest.approx(
        [p.stamp for p in truth.passages], abs=0.06
    )
    assert "mass on the true topology" in printed
    # the true wall time of the whole run, with its phases (issue #25: the inference alone was printed)
    done = re.search(
        r"done in ([0-9.]+) s of wall time \(to the PTM ([0-9.]+) s, smoothing ([0-9.]+) s", printed
    )
    assert done is not None, printed
    # three figures printed to 0.1 s, each within 0.05 s of its value: the sum of the parts may exceed the
    # whole by up to 0.15 s (4.3 against 4.2 + 0.2 failed a bound of 0.1 by the float rounding of the sum)
    assert float(done[1]) >= float(done[2]) + float(done[3]) - 0.15 - 1e-9
    assert eval_cli.main([str(out / "ptm.json"), "--ground-truth", str(out), "--no-topologies"]) == 0
    score = json.loads(capsys.readouterr().out)
    assert score["true_places_from"] == "place-ids" and score["n_true_places"] == len(
        {p.place for p in truth.passages}
    )
    # the default noise model (a real robot's, broader than the simulator's) leaves the early closure of
    # this 8-visit aliased loop open: exact enumeration puts 0.54 on the truth, the filter 0.39; what
    # must hold is that the truth keeps real mass, not a confident wrong answer
    assert score["true_topology_mass"] > 0.25
    assert f"mass on the true topology = {score['true_topology_mass']:.3f}" in printed


def test_the_ground_truth_detector_needs_a_ground_truth(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ConfigError, match="needs the run's ground truth"):
        make_detector("ground-truth", load_config())
    bag = tmp_path / "bag"
    write_run(simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(0), visits=3), bag)
    (bag / "ground_truth.json").unlink()
    assert (
        run_cli.main([str(bag), "--out", str(tmp_path / "o"), "--detector", "ground-truth", "--quiet"]) == 2
    )
    assert "needs the run's ground truth: pass --ground-truth FILE" in capsys.readouterr().err


def test_a_ground_truth_of_another_clock_is_refused_before_the_work(
    loop_bag: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    truth = load_ground_truth(loop_bag)
    shifted = dataclasses.replace(
        truth,
        stamps=truth.stamps + 1e6,
        passages=tuple(dataclasses.replace(p, stamp=p.stamp + 1e6) for p in truth.passages),
    )
    gt = save_sim_gt(shifted, tmp_path / "late.json")
    argv = [
        str(loop_bag),
        "--out",
        str(tmp_path / "o"),
        "--detector",
        "ground-truth",
        "--ground-truth",
        str(gt),
    ]
    assert run_cli.main([*argv, "--quiet"]) == 2
    err = capsys.readouterr().err  # ptm-run's check of the ground truth against the bag's odometry
    assert "of the bag's odometry (1 m of travel apart) lie outside the ground truth's time span" in err
    assert "on another clock?" in err and "--force" in err
    assert run_cli.main([*argv, "--quiet", "--force"]) == 2  # forced, yet no landmark visit to make
    assert "all lie outside the bag's odometry" in capsys.readouterr().err
    assert not (tmp_path / "o" / "ptm.json").exists()


def _thesis_protocol(run: Path, raw: str, ground_truth: str, tmp_path: Path) -> RunResult:
    """A shared real run converted to a bag and replayed at the defaults with landmarks placed every 5 m
    along its ground truth (``--detector ground-truth``), scored, into ``tmp_path / "o"``."""
    from ptm_ros.tools import convert

    bag = tmp_path / run.name
    assert convert.main([str(run / raw), str(bag)]) == 0
    config = load_config(None, {"detector": {"kind": "ground-truth"}})
    return run_offline(
        bag, tmp_path / "o", config, ground_truth=run / ground_truth, write_report=False, write_map=False
    )


@pytest.mark.slow
def test_intel_with_landmarks_every_5_m_beats_the_thesis(datasets_dir: Path, tmp_path: Path) -> None:
    """The thesis' Intel experiment (Ch. 4.5, Fig. 57: landmarks placed 5 m from each other, 63 visits,
    72 % of the mass on the true topology with MC³), replayed with the filter at its defaults."""
    result = _thesis_protocol(datasets_dir / "intel", "intel-raw-910.clf.gz", "intel-gt-910.txt", tmp_path)
    assert result.score is not None
    assert 55 <= len(result.ptm.landmarks) <= 75
    assert result.score.true_topology_mass > 0.72, result.score.true_topology_mass
    assert result.score.map.counts.f1 > 0.95
    # the README's next step: ptm-eval against the ground truth ptm-run wrote (with Intel's raw odometry,
    # which drifts 0.057 rad/m off its poses) accepts it as this run's
    code = eval_cli.main(
        [str(tmp_path / "o" / "ptm.json"), "--ground-truth", str(tmp_path / "o"), "--no-topologies"]
    )
    assert code == 0


@pytest.mark.slow
def test_aces_with_landmarks_every_5_m_is_not_sure_of_a_wrong_chain(
    datasets_dir: Path, tmp_path: Path
) -> None:
    """Issue #23's thesis protocol on ACES (landmarks 5 m apart along the true path). After one bend of the
    path, the landmarks of two parallel corridors line up; under the area model of a new place every
    lined-up merge gained the area's Occam factor again, and the MAP merged a chain of visits 20 m apart
    at p 0.95 (MAP F1 0.789, no mass on topologies without a wrong pair). Under the step prior (the
    default) the truth and its neighbour share the mass (``bench/thesis_protocol.md``: 0.33 and 0.37 since
    the laser odometry's retry, the neighbour merging the loop's return with the starting landmark 5.2 m
    away; 0.48 and 0.37 the other way round before): no pair of visits more than 4 m apart in truth is one
    place with probability above 0.7."""
    result = _thesis_protocol(datasets_dir / "aces", "aces-raw-440.clf.gz", "aces-gt-440.txt", tmp_path)
    assert result.score is not None
    assert result.score.map.counts.f1 > 0.9
    assert result.score.consistent_mass > 0.2, result.score.consistent_mass
    truth = load_ground_truth(datasets_dir / "aces" / "aces-gt-440.txt")
    stamps = np.array([v.stamp for v in result.ptm.landmarks])
    xy = interpolate_poses(truth.stamps, truth.poses_corrected, stamps)[:, :2]
    apart = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1)) > 4.0
    tops = result.ptm.topologies
    same = same_place_probabilities({t.labels: t.probability for t in tops}, len(stamps))
    assert same[apart].max() < 0.7, same[apart].max()
