"""The offline pipeline end to end: simulated bag → visits → exact PTM → ptm.json, report, score."""

from __future__ import annotations

import itertools
import json
import math
import re
import shutil
from pathlib import Path
from types import SimpleNamespace

import jsonschema
import numpy as np
import pytest
from cli_helpers import call
from run_cache import once_per_run
from scipy.optimize import minimize

from ptm_ros.config import PtmConfig, load_config
from ptm_ros.errors import DataError
from ptm_ros.io.bag import read_run
from ptm_ros.io.simulator import SimConfig, simulate, write_run
from ptm_ros.io.worlds import get_world
from ptm_ros.maps.map_quality import ClassGrid
from ptm_ros.maps.occupancy import FREE, OCCUPIED, load_map
from ptm_ros.maps.routes import RouteConfig, crossing_segments
from ptm_ros.model.geometry import between, compose
from ptm_ros.model.partitions import bell, canonical, num_places
from ptm_ros.model.ptm import Landmark, Ptm, from_json_dict, load_ptm, make_ptm, ptm_schema, to_json_dict
from ptm_ros.reporting.chain_trace import CHAINS_KEY, SRQ_KEY, TRACE, find_chain_trace
from ptm_ros.reporting.report import MAP_COMPARISON, REFERENCE_CAPTION, ROUTES_CAPTION, SRQ, SURPRISE
from ptm_ros.session import cold_chain_details
from ptm_ros.tools import run as run_cli
from ptm_ros.tools.evaluate import main as eval_main
from ptm_ros.tools.outputs import inference_notes, route_notes, write_route_graph
from ptm_ros.tools.pipeline import detect_visits, run_offline
from ptm_ros.tools.workers import RegistrationPool


@pytest.fixture(scope="module")
def tjunction_bag(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "tj"
    run = simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(4), visits=5)
    write_run(run, out)
    return out


def small_config(**over) -> PtmConfig:
    base = {
        "detector": {"kind": "equidistant", "equidistant": {"spacing": 5.0}},
        "inference": {"method": "exact"},
    }
    base.update(over)
    return load_config(None, base)


def segment_distances(points: np.ndarray, segments: np.ndarray) -> np.ndarray:
    """Distance of each point ``(n, 2)`` to the nearest segment ``(m, 4)``."""
    a, b = segments[:, :2], segments[:, 2:]
    ab = b - a
    t = np.clip(np.einsum("nki,ki->nk", points[:, None] - a, ab) / np.sum(ab**2, axis=1), 0.0, 1.0)
    return np.min(np.linalg.norm(points[:, None] - (a + t[..., None] * ab), axis=2), axis=1)


def brute_ate(est: np.ndarray, true: np.ndarray) -> float:
    """RMSE after the rigid motion a generic optimiser finds (several starting angles)."""

    def cost(p: np.ndarray) -> float:
        c, s = math.cos(p[0]), math.sin(p[0])
        moved = est @ np.array([[c, s], [-s, c]]) + p[1:]
        return float(np.mean(np.sum((moved - true) ** 2, axis=1)))

    starts = [[a, *(true.mean(0) - est.mean(0))] for a in np.linspace(-3.0, 3.0, 6)]
    opts = {"xatol": 1e-9, "fatol": 1e-12, "maxiter": 10_000}
    return math.sqrt(min(minimize(cost, x0, method="Nelder-Mead", options=opts).fun for x0 in starts))


def check_route_graph(path: Path, ptm: Ptm, map_yaml: Path | None = None) -> dict:
    """The nav2 route graph GeoJSON: nodes = MAP places and the waypoints of rerouted edges, directed
    edges straight between existing nodes, ids unique over nodes and edges, finite coordinates,
    probabilities in (0, 1], every passage of the MAP topology an edge, a chain of hops or a dropped
    edge; with the run's map (``map_yaml``), no edge segment through its walls."""
    doc = json.loads(path.read_text())
    assert doc["type"] == "FeatureCollection"
    nodes = [f for f in doc["features"] if f["geometry"]["type"] == "Point"]
    edges = [f for f in doc["features"] if f["geometry"]["type"] == "MultiLineString"]
    assert len(nodes) + len(edges) == len(doc["features"])
    places = [f for f in nodes if "place" in f["properties"]["metadata"]]
    assert len(places) == num_places(ptm.map_topology.labels)
    assert len(nodes) - len(places) == doc["metadata"]["waypoints"]
    ids = [f["properties"]["id"] for f in doc["features"]]
    assert len(set(ids)) == len(ids) and all(isinstance(i, int) and i >= 0 for i in ids)
    node_xy = {f["properties"]["id"]: f["geometry"]["coordinates"] for f in nodes}
    assert all(len(xy) == 2 and all(math.isfinite(v) for v in xy) for xy in node_xy.values())
    directed = set()
    for e in edges:
        p = e["properties"]
        assert p["startid"] in node_xy and p["endid"] in node_xy and p["startid"] != p["endid"]
        assert e["geometry"]["coordinates"] == [[node_xy[p["startid"]], node_xy[p["endid"]]]]
        assert 0.0 < p["metadata"]["probability"] <= 1.0
        directed.add(tuple(p["metadata"].get("places", (p["startid"], p["endid"]))))
    assert all((b, a) in directed for a, b in directed)  # each connection in both directions
    dropped = {tuple(d["places"]) for d in doc["metadata"]["dropped_edges"]}
    labels = ptm.map_topology.labels
    steps = {(a, b) for a, b in itertools.pairwise(labels) if a != b}
    assert all(s in directed or tuple(sorted(s)) in dropped for s in steps)  # every passage is an edge
    if map_yaml is not None:
        grid = load_map(map_yaml)
        assert crossing_segments(doc, ClassGrid(grid.classes(), grid.origin, grid.resolution)) == 0
    return doc


@pytest.mark.slow
def test_visits_follow_the_odometry(tjunction_bag):
    run = read_run(tjunction_bag)
    diag = {}
    visits = detect_visits(run, small_config(laser_odometry={"enabled": False}), diag)
    assert 4 <= len(visits) <= 8
    stamps = run.odometry.stamps
    for v in visits:
        k = int(np.flatnonzero(stamps == v.stamp)[0])  # a visit sits exactly on an odometry message
        assert v.pose == tuple(run.odometry.poses[k])  # pose unchanged without laser odometry
        assert v.signature is not None and v.patch is not None and len(v.patch) > 30
    travel = sum(v.travel for v in visits[1:])
    assert 5.0 * (len(visits) - 1) <= travel < 5.0 * (len(visits) - 1) + 0.2
    assert diag["visits_without_panorama"] == 0 and diag["visits"] == len(visits)
    # with laser odometry (the default) the scans are matched and the poses move off the wheel odometry
    # (the equidistant firings follow the corrected travel, so stamps may shift by a sample or two)
    corrected = detect_visits(run, small_config(), diag)
    assert abs(len(corrected) - len(visits)) <= 1
    for v in corrected:  # ptm.json keeps the input odometry (CONTRACT.md), plus the corrected pose
        k = int(np.flatnonzero(stamps == v.stamp)[0])
        assert v.odom_pose == tuple(run.odometry.poses[k])
        lm = Landmark.from_visit(v)
        assert lm.pose == v.odom_pose and lm.corrected_pose == v.pose and lm.map_pose == v.pose
    doc = to_json_dict(make_ptm([Landmark.from_visit(v) for v in corrected], {(0,) * len(corrected): 1.0}))
    back = from_json_dict(json.loads(json.dumps(doc)))
    assert [lm.corrected_pose for lm in back.landmarks] == [v.pose for v in corrected]
    assert [lm.pose for lm in back.landmarks] == [v.odom_pose for v in corrected]
    assert diag["laser_odometry"]["matched"] >= 0.9 * len(run.scans.stamps)
    assert any(
        v.pose != tuple(run.odometry.poses[int(np.flatnonzero(stamps == v.stamp)[0])]) for v in corrected
    )


@pytest.mark.slow
def test_run_offline_writes_a_valid_scored_ptm(tjunction_bag, tmp_path, capsys):
    config = small_config()
    result = run_offline(tjunction_bag, tmp_path, config)
    ptm = load_ptm(tmp_path / "ptm.json")
    n = len(ptm.landmarks)
    assert len(ptm.topologies) == min(bell(n), config.inference.top)
    total = sum(t.probability for t in ptm.topologies)
    assert total <= 1.0 + 1e-9 and (bell(n) > config.inference.top or math.isclose(total, 1.0))
    probs = [t.probability for t in ptm.topologies]
    assert probs == sorted(probs, reverse=True)
    assert ptm.inference["method"] == "exact" and ptm.inference["seed"] == 0
    assert ptm.topologies[0].positions is not None
    assert len(ptm.topologies[0].positions) == len(set(ptm.topologies[0].labels))
    doc = json.loads((tmp_path / "ptm.json").read_text())
    jsonschema.validate(doc, ptm_schema())
    assert doc["detector"] == "equidistant" and "diagnostics" in doc
    assert load_config(tmp_path / "config.yaml") == config.__class__(
        **{
            **config.__dict__,
            "detector": config.detector.__class__(**{**config.detector.__dict__, "kind": "equidistant"}),
        }
    )
    assert (tmp_path / "report.html").is_file() and (tmp_path / "ptm_histogram.png").is_file()
    assert result.score is not None  # the simulator's ground truth beside the bag was found
    s = result.score.as_dict(per_topology=False)
    assert 0.0 <= s["map_f1"] <= 1.0 and s["n_visits"] == n
    names = {"ptm.json", "config.yaml", "route_graph.geojson", "map.pgm", "map.yaml", "map.png"}
    assert {p.name for p in result.files.values()} == names
    assert all(p.parent == tmp_path and p.is_file() for p in result.files.values())
    graph = check_route_graph(tmp_path / "route_graph.geojson", ptm, tmp_path / "map.yaml")
    assert graph["metadata"]["walls"] == "checked against the run's occupancy map"
    assert graph["metadata"]["node_positions"] == (
        "medoid of the places' visits on the trajectory the map was drawn along"
    )
    # The map, in the odometry frame, moved into the world frame: occupied cells on the simulated walls,
    # the walls covered, the true path through free cells.
    truth = json.loads((tjunction_bag / "ground_truth.json").read_text())
    offset = np.array(truth["odometry_frame_offset"])
    grid = load_map(tmp_path / "map.yaml")
    rows, cols = np.nonzero(grid.data == OCCUPIED)
    xy = np.asarray(grid.origin[:2]) + (np.column_stack([cols, rows]) + 0.5) * grid.resolution
    occupied = compose(offset, np.column_stack([xy, np.zeros(len(xy))]))[:, :2]
    walls = get_world("t-junction").segments
    d = segment_distances(occupied, walls)
    assert np.median(d) < 0.1 and np.percentile(d, 90) < 0.2, np.percentile(d, [50, 90])
    a, b = walls[:, :2], walls[:, 2:]
    samples = np.concatenate([a[k] + np.linspace(0, 1, 20)[:, None] * (b[k] - a[k]) for k in range(len(a))])
    gaps = np.min(np.linalg.norm(samples[:, None] - occupied[None], axis=2), axis=1)
    assert np.mean(gaps < 0.25) > 0.9
    true_poses = np.column_stack([truth["poses"][k] for k in ("x", "y", "yaw")])
    in_odom = between(offset, true_poses)[:, :2]
    ij = np.floor((in_odom - grid.origin[:2]) / grid.resolution).astype(int)
    assert np.mean(grid.data[ij[:, 1], ij[:, 0]] == FREE) > 0.99
    # Trajectory errors at the odometry stamps (the simulator's truth is at exactly those stamps).
    ate = doc["trajectory_error"]
    assert ate == dict(result.trajectory_error) and ate["ground_truth"].endswith("ground_truth.json")
    odom = read_run(tjunction_bag).odometry
    assert ate["poses"] == len(odom.stamps) == len(true_poses)
    assert ate["ate_odometry_m"] == pytest.approx(brute_ate(odom.poses[:, :2], true_poses[:, :2]), rel=1e-5)
    assert 0.0 < ate["ate_smoothed_m"] < ate["ate_odometry_m"]  # the MAP topology's loops correct drift
    assert doc["timing"]["map_s"] > 0.0 and doc["timing"]["smoothing_s"] > 0.0
    md = (tmp_path / "report.md").read_text()
    assert "(map.png)" in md and "absolute trajectory error" in md
    # The map against the same scans at the true poses (ptm_ros.maps.map_quality); ptm-eval scores it
    # again.
    quality = doc["map_quality"]
    assert quality["leak"] < 0.02 and 0.8 < quality["free_area_ratio"] < 1.25, quality
    assert quality["wall_precision"] > 0.9 and quality["wall_recall"] > 0.9, quality
    assert "free-space leak" in md
    assert f"![{REFERENCE_CAPTION}]({MAP_COMPARISON})" in md and (tmp_path / MAP_COMPARISON).is_file()
    assert (
        eval_main([str(tmp_path / "ptm.json"), "--ground-truth", str(tjunction_bag / "ground_truth.json")])
        == 0
    )
    assert json.loads(capsys.readouterr().out)["map_quality"] == quality


def test_route_graph_is_kept_off_the_walls_and_logged(tmp_path):
    """write_route_graph with the map's classes: an edge through a wall is rerouted, one with no way
    round dropped, and ptm-run's log says so."""
    classes = np.full((100, 120), FREE, dtype=np.int8)
    classes[:70, 60] = OCCUPIED  # a wall at x = 6 m from y = 0 to 7 m, 0.1 m cells
    classes[:, 30] = OCCUPIED  # and at x = 3 m across the whole map
    walls = ClassGrid(classes, (0.0, 0.0, 0.0), 0.1)
    poses = [(1.0, 5.0, 0.0), (4.5, 5.0, 0.0), (9.0, 5.0, 0.0)]
    ptm = make_ptm([Landmark(k, float(k), p) for k, p in enumerate(poses)], {(0, 1, 2): 1.0})
    notes = []
    path = write_route_graph(
        ptm, tmp_path / "g.geojson", grid=walls, config=RouteConfig(corridor=3.0), log=notes.append
    )
    doc = json.loads(path.read_text())
    assert crossing_segments(doc, walls) == 0
    assert doc["metadata"]["rerouted_edges"] == 1 and [
        d["places"] for d in doc["metadata"]["dropped_edges"]
    ] == [[0, 1]]
    assert notes[0].startswith("route graph: 1 connections rerouted around the map's walls through")
    assert notes[1].startswith("route graph: dropped the edge between places 0 and 1 (p = 1.000): ")
    assert (
        route_notes(json.loads(write_route_graph(ptm, tmp_path / "s.geojson").read_text())["metadata"]) == []
    )


@pytest.mark.slow
def test_a_scale_map_without_ground_truth_and_the_route_graph_beside_it(tjunction_bag, tmp_path):
    """occupancy.mode scale: map_scale.png + map.yaml (mode scale) whose trinary view is the map the
    route graph and the report use; without a ground truth the report shows the map next to the route
    graph."""
    bag = tmp_path / "bag"
    shutil.copytree(tjunction_bag, bag, ignore=shutil.ignore_patterns("ground_truth.json"))
    config = small_config(model={"use_laser": False}, occupancy={"mode": "scale"})
    result = run_offline(bag, tmp_path / "o", config)
    assert result.score is None and "map_quality" not in result.ptm.extra
    names = {"ptm.json", "config.yaml", "route_graph.geojson", "map_scale.png", "map.yaml", "map.png"}
    assert {p.name for p in result.files.values()} == names and not (tmp_path / "o" / "map.pgm").exists()
    saved = load_map(tmp_path / "o" / "map.yaml")
    assert saved.mode == "scale" and saved.image.name == "map_scale.png"
    assert np.any((saved.data > 0) & (saved.data < 100))  # the occupancy between the thresholds
    # the route graph is kept off the walls of that map as map_server reads it (its trinary view)
    check_route_graph(tmp_path / "o" / "route_graph.geojson", result.ptm, tmp_path / "o" / "map.yaml")
    md = (tmp_path / "o" / "report.md").read_text()
    assert f"![{ROUTES_CAPTION}]({MAP_COMPARISON})" in md and (tmp_path / "o" / MAP_COMPARISON).is_file()


def test_cli_warns_about_skipped_input(monkeypatch, tmp_path, capsys):
    """Messages the extractor skipped (bad stamps, malformed scans, ...) are named on stderr, not dropped
    silently."""
    assert run_cli.skipped_warning({"skipped": {}}) == ""
    assert run_cli.skipped_warning({}) == ""
    line = run_cli.skipped_warning({"skipped": {"scan-malformed": 2, "odometry-stamp-backwards": 1}})
    assert line.startswith("skipped 3 input messages (odometry-stamp-backwards 1, scan-malformed 2)")

    result = SimpleNamespace(diagnostics={"skipped": {"scan-empty": 4}})
    monkeypatch.setattr("ptm_ros.tools.pipeline.run_offline", lambda *a, **k: result)
    monkeypatch.setattr(run_cli, "format_summary", lambda result, top, total_s=None: "summary")
    assert run_cli.main([str(tmp_path), "--out", str(tmp_path / "o"), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "ptm-run: warning: skipped 4 input messages (scan-empty 4)" in captured.err
    assert captured.out.strip() == "summary"


def test_cli_reports_errors_with_exit_code(tmp_path, capsys):
    assert run_cli.main([str(tmp_path / "missing.bag"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "ptm-run: error" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("inference: {method: magic}\n")
    assert run_cli.main([str(tmp_path), "--out", str(tmp_path / "o"), "--params", str(bad), "--quiet"]) == 2
    assert "InferenceConfig.method must be one of" in capsys.readouterr().err


@pytest.mark.slow
def test_cli_prints_topologies_and_score(tjunction_bag, tmp_path, capsys):
    params = tmp_path / "p.yaml"
    params.write_text(
        "detector: {kind: equidistant, equidistant: {spacing: 5.0}}\nmodel: {use_laser: false}\n"
    )
    code = run_cli.main(
        [str(tjunction_bag), "--out", str(tmp_path / "o"), "--params", str(params), "--quiet", "--no-map"]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "most probable topologies" in out and "#1 p = " in out and "MAP F1" in out
    assert "trajectory error (ATE" in out and "route_graph.geojson" in out
    written = {p.name for p in (tmp_path / "o").iterdir()}
    assert {"ptm.json", "route_graph.geojson", "report.html"} <= written
    assert not written & {"map.pgm", "map.yaml", "map.png"}  # --no-map
    doc = check_route_graph(tmp_path / "o" / "route_graph.geojson", load_ptm(tmp_path / "o" / "ptm.json"))
    assert doc["metadata"]["walls"] == "not checked: no map" and doc["metadata"]["waypoints"] == 0
    assert doc["metadata"]["node_positions"] == "the MAP topology's place positions"


@pytest.mark.slow
def test_mcmc_and_rbpf_agree_with_exact_on_a_small_run(tjunction_bag, tmp_path):
    """The three estimators over the same visits and model: MCMC's visited-set estimate and the filter
    (particles >= the number of topologies it can hold) against enumeration."""
    from ptm_ros.model.posterior import total_variation

    model = {"use_laser": False, "odometry": {"n_samples": 0}}
    ptms = {}
    for method in ("exact", "mcmc", "rbpf"):
        cfg = small_config(model=model, inference={"method": method, "top": 10_000, "particles": 10_000})
        ptms[method] = run_offline(tjunction_bag, tmp_path / method, cfg, write_report=False).ptm
        jsonschema.validate(json.loads((tmp_path / method / "ptm.json").read_text()), ptm_schema())
    dist = {m: {t.labels: t.probability for t in p.topologies} for m, p in ptms.items()}
    assert total_variation(dist["exact"], dist["mcmc"]) < 0.01
    assert total_variation(dist["exact"], dist["rbpf"]) < 0.05  # EKF linearisation vs batch Laplace
    assert ptms["mcmc"].inference["converged"] is True
    assert ptms["mcmc"].inference["initial"] == "singletons"  # "auto" on a short run
    assert "versus_rbpf" not in ptms["mcmc"].inference
    inf = ptms["mcmc"].inference
    assert 0.0 <= inf["doubling_pair"] <= inf["doubling_tv"] + 1e-5  # a pair's marginal moves <= TV
    assert 0.0 <= inf["chain_pair"] <= inf["chain_tv"] + 1e-5
    (line,) = inference_notes(inf)
    assert line.startswith(f"MCMC: {inf['iterations']} sweeps of 2 chains from singletons")
    assert ", converged;" in line
    assert f"between chains {inf['chain_pair']:.3f}" in line
    assert inference_notes(ptms["rbpf"].inference) == [] == inference_notes(ptms["exact"].inference)


#: The model of the MCMC runs started from the filter: importance sampling, the separation prior
#: integrated, as the filter does.
NO_LASER = {"use_laser": False}


@pytest.fixture(scope="module")
def tjunction_exact_no_laser(tjunction_bag, tmp_path_factory) -> Ptm:
    """The exact PTM of :func:`tjunction_bag` under :data:`NO_LASER`."""
    exact_cfg = small_config(model=NO_LASER, inference={"method": "exact", "top": 10_000})
    return run_offline(tjunction_bag, tmp_path_factory.mktemp("exact"), exact_cfg, write_report=False).ptm


@pytest.mark.slow
@pytest.mark.parametrize("start", [{"initial": "rbpf"}, {"initial": "auto", "auto_filter_visits": 3}])
def test_mcmc_from_the_filters_ensemble_reports_how_it_differs(
    tjunction_bag, tjunction_exact_no_laser, tmp_path, start
):
    """``initial: rbpf`` (or ``auto`` on a run longer than ``auto_filter_visits``): the chains start from
    the filter's topologies and ptm.json compares the PTMs."""
    from ptm_ros.model.posterior import total_variation

    inference = {"method": "mcmc", "top": 10_000, "particles": 50, "mcmc": {**start, "chains": 2}}
    ptm = run_offline(tjunction_bag, tmp_path / "m", small_config(model=NO_LASER, inference=inference)).ptm
    jsonschema.validate(json.loads((tmp_path / "m" / "ptm.json").read_text()), ptm_schema())
    exact = tjunction_exact_no_laser
    versus = ptm.inference["versus_rbpf"]
    assert ptm.inference["initial"] == "rbpf"
    assert 1 <= versus["rbpf_topologies"] <= 50
    assert versus["tv"] < 0.01 and versus["tv_reweighted"] < 0.01  # small run: both PTMs are exact
    assert versus["map_equal"] is (versus["map_gain_nats"] == 0.0)
    assert versus["rbpf_map_among"] is True  # the filter's MAP starts chain 0
    assert versus["pair_max_diff"] < 0.05 and versus["pairs_differing"] == 0 < versus["pairs_in_play"]
    dist = {t.labels: t.probability for t in ptm.topologies}
    assert total_variation({t.labels: t.probability for t in exact.topologies}, dist) < 0.01


@pytest.mark.slow
def test_surprise_detector_and_mcmc_figures_in_the_report(tjunction_bag, tmp_path):
    """A surprise detector's trace is drawn in the report. MCMC's cold-chain states go to
    ``mcmc_trace.json`` with ``write_trace`` (``ptm-run --trace``), and the report draws their SRQ plot;
    ptm.json keeps a summary of the chains either way (issue #25)."""
    over = {
        "model": {"use_laser": False},
        "inference": {"method": "mcmc"},
        "detector": {"kind": "laser-surprise"},
    }
    cfg = load_config(None, over)
    result = run_offline(tjunction_bag, tmp_path, cfg, write_trace=True)
    assert result.ptm.extra["detector"] == "laser-surprise"
    md = (tmp_path / "report.md").read_text()
    assert (tmp_path / SURPRISE).is_file() and f"({SURPRISE})" in md
    assert inference_notes(result.ptm.inference)[0] in md
    saved = load_ptm(tmp_path / "ptm.json")
    assert SRQ_KEY not in saved.inference and SRQ_KEY not in result.ptm.inference
    summary = saved.inference[CHAINS_KEY]
    assert summary["chains"] == saved.inference["chains"] and summary["trace"] == TRACE
    assert result.files["mcmc_trace"] == tmp_path / TRACE
    trace = find_chain_trace(saved, tmp_path)
    assert trace is not None and [len(c) for c in trace["chains"]] == summary["states"]
    assert all(len(lab) == len(saved.landmarks) for lab in trace["topologies"])
    assert max(max(c) for c in trace["chains"]) < len(trace["topologies"])  # ids index the topologies
    assert (tmp_path / SRQ).is_file() and f"({SRQ})" in md
    # ptm-eval's report finds the trace the summary names beside ptm.json, and says how MCMC ended
    report = tmp_path / "eval"
    argv = [str(tmp_path / "ptm.json"), "--ground-truth", str(tjunction_bag), "--report", str(report)]
    assert eval_main([*argv, "--no-topologies"]) == 0
    assert (report / SRQ).is_file() and inference_notes(saved.inference)[0] in (
        report / "report.md"
    ).read_text()


@pytest.mark.slow
def test_mcmc_without_trace_keeps_the_summary_only(tjunction_bag, tmp_path):
    cfg = load_config(None, {"model": {"use_laser": False}, "inference": {"method": "mcmc"}})
    result = run_offline(tjunction_bag, tmp_path, cfg, write_map=False)
    assert not (tmp_path / TRACE).exists() and "mcmc_trace" not in result.files
    summary = load_ptm(tmp_path / "ptm.json").inference[CHAINS_KEY]
    assert summary["trace"] is None and len(summary["srq_max_deviation"]) == summary["chains"]
    md = (tmp_path / "report.md").read_text()
    assert (
        not (tmp_path / SRQ).exists()
        and "the SRQ plot needs the chains' states: run ptm-run with --trace" in md
    )


def testcold_chain_details_become_json_values():
    res = SimpleNamespace(cold_states=[np.array([3, 3, 4]), [(0, 1, 0), (0, 1, 1)]], cold_thin=np.int64(5))
    got = cold_chain_details(res)
    assert got == {"cold_chain_states": [[3, 3, 4], [[0, 1, 0], [0, 1, 1]]], "cold_chain_thin": 5}
    assert json.loads(json.dumps(got)) == got
    assert cold_chain_details(SimpleNamespace()) == {}  # an McmcResult without the fields
    assert cold_chain_details(SimpleNamespace(cold_states=[[], []], cold_thin=1)) == {}
    labelled = SimpleNamespace(
        cold_states=[np.array([0, 1])], cold_thin=1, state_labels=((0, 0), (0, np.int64(1)))
    )
    assert cold_chain_details(labelled)["cold_chain_labels"] == [[0, 0], [0, 1]]


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (lambda d: d["landmarks"][1].update(stamp=math.nan), "landmark 1: stamp nan must be finite"),
        (lambda d: d["landmarks"][0].update(pose=[0.0, math.inf, 0.0]), "3 finite numbers"),
        (lambda d: d["topologies"][0].update(positions=[[0.0, 0.0]]), "one \\(x, y\\) per place"),
        (lambda d: d["topologies"][0].update(positions=[[0.0, 0.0], [math.nan, 1.0]]), "must be finite"),
    ],
)
def test_ptm_json_with_non_finite_or_misshapen_values_is_refused(edit, match):
    """ptm.json is validated in one place (``ptm_ros.model.ptm.from_json_dict``, used by ptm-eval and the map
    publisher): stamps, poses and place positions finite, one position per place."""
    landmarks = [Landmark(k, float(k), (float(k), 0.0, 0.0)) for k in range(3)]
    doc = to_json_dict(make_ptm(landmarks, {(0, 1, 0): 1.0}, positions={(0, 1, 0): [[0.0, 0.0], [1.0, 0.0]]}))
    assert from_json_dict(json.loads(json.dumps(doc))).topologies[0].positions == ((0.0, 0.0), (1.0, 0.0))
    bad = json.loads(json.dumps(doc))
    edit(bad)
    with pytest.raises(DataError, match=f"invalid ptm.json: .*{match}"):
        from_json_dict(bad)


DEMO_BAG = Path(__file__).resolve().parents[1] / "bags" / "demo"
DEMO_PARAMS = DEMO_BAG.parents[1] / "config" / "demo.yaml"
#: The phases of ptm-run on the demo bag (a particle filter, a map, a ground truth, a report), in order.
DEMO_PHASES = (
    "reading the bag",
    "landmark visits",
    "particle filter",
    "smoothing",
    "map",
    "map quality",
    "route graph",
    "report",
)


@pytest.fixture(scope="module")
def demo_quiet(tmp_path_factory):
    """``make demo``'s ptm-run (config/demo.yaml) on the demo bag, quiet, without the map: the output
    directory and what it printed, ``(dir, stdout, stderr)``."""

    def run() -> tuple[Path, str, str]:
        out = tmp_path_factory.mktemp("demo") / "quiet"
        code, printed, err = call(
            run_cli.main, [DEMO_BAG, "--out", out, "--params", DEMO_PARAMS, "--quiet", "--no-map"]
        )
        assert code == 0, err
        return out, printed, err

    return once_per_run(tmp_path_factory, f"{__name__}.demo_quiet", run)


@pytest.mark.slow
def test_ptm_run_shows_every_phase_on_stderr_unless_quiet(demo_run, demo_quiet):
    """Issue #25: a named progress bar per phase on stderr (stdout keeps the summary), none with --quiet;
    the summary's figures rounded, the consistent mass explained, the ESS a share of the particles."""
    loud = SimpleNamespace(out=demo_run[2], err=demo_run[3])  # ptm-run with the map and the report
    bars = [ln.split(":")[0] for ln in loud.err.replace("\r", "\n").splitlines() if "%|" in ln]
    shown = list(dict.fromkeys(bars))  # each bar redraws itself: its first line, in order
    assert shown == list(DEMO_PHASES), loud.err
    assert "%|" not in loud.out
    # the same run with --quiet (and without the map, whose phases were shown above)
    quiet = SimpleNamespace(out=demo_quiet[1], err=demo_quiet[2])
    assert all(ln.startswith("ptm-run: ") for ln in quiet.err.splitlines()), quiet.err  # notes only
    assert "%|" not in quiet.err
    assert not [ln for ln in quiet.err.splitlines() for p in DEMO_PHASES if ln.startswith(f"{p}:")]
    same = [ln for ln in quiet.out.splitlines() if ln.startswith("  #")]  # the topologies
    assert same and same == [ln for ln in loud.out.splitlines() if ln.startswith("  #")]
    out = loud.out  # the whole summary, map and report included
    assert re.findall(r"\d\.\d{5,}", out) == []  # no float printed in full
    assert (
        re.search(r"ESS \d\.\d\d/100", out)
        and "(consistent mass = the posterior mass of the topologies" in out
        and "pair calibration: " in out
        and "odometry check: " in out  # the translation noise the registrations suggest
    )


#: What ``make demo``'s bag shows, measured (ptm-run, defaults + config/demo.yaml): the truth's mass after
#: each visit 1, 1, 1, 1, 0.618, 0.598, 0.784, 0.981 (the loop closure holds 0.38–0.40 at visits 4–5);
#: the greedy answer wrong from visit 4 on. The thresholds leave a margin: the truth below LOW somewhere
#: (an alternative holds a quarter of the mass or more), split (SPLIT) at two visits or more, above HIGH
#: at the end.
DEMO_LOW, DEMO_SPLIT, DEMO_HIGH = 0.75, (0.1, 0.9), 0.9


@pytest.mark.slow
def test_the_demo_bag_splits_the_mass_until_the_robot_returns_while_greedy_commits_wrong(demo_quiet):
    """Issue #25, ``make demo`` shows why a PTM: on ``bags/demo`` (two junctions alike, told apart only
    when the robot returns to the first) the filter's PTM after each visit splits its mass between the
    loop closure and the truth for a stretch of visits and ends on the truth, while the greedy baseline
    commits to the wrong loop closure and never leaves it."""
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.ptm import ptm_greedy, ptm_timeline
    from ptm_ros.reporting.report import TIMELINE
    from ptm_ros.scoring.evaluation import first_wrong_visit, timeline_masses
    from ptm_ros.tools.evaluate import score_against_ground_truth

    out, printed, _ = demo_quiet
    ptm = load_ptm(out / "ptm.json")
    truth = score_against_ground_truth(ptm, load_ground_truth(DEMO_BAG / "ground_truth.json")).true_labels
    assert truth is not None and len(truth) == len(ptm.landmarks) == 8
    masses = timeline_masses(ptm_timeline(ptm), truth)
    assert all(m is not None for m in masses), masses
    assert min(masses) < DEMO_LOW and masses[-1] > DEMO_HIGH, masses
    split = [k for k, m in enumerate(masses) if DEMO_SPLIT[0] <= m <= DEMO_SPLIT[1]]
    assert len(split) >= 2 and split == list(range(split[0], split[-1] + 1)), masses  # a stretch of visits
    assert ptm.topologies[0].labels == truth and masses[-1] > max(masses[split[0] : split[-1] + 1])
    greedy = ptm_greedy(ptm)
    assert greedy is not None and greedy != truth
    wrong = first_wrong_visit(greedy, truth)
    assert wrong == split[0]  # greedy commits where the PTM splits, and stays wrong
    assert greedy[wrong] == greedy[0] != truth[wrong]  # a loop closure onto the first junction
    assert "greedy baseline" in printed and f"wrong, from visit {wrong} on" in printed
    rows = [
        ln.split() for ln in printed.splitlines() if re.match(r"\s+\d+\s+\d\.\d{3}\s+(right|wrong)\s", ln)
    ]
    assert [r[0] for r in rows] == [str(k) for k in range(8)]
    assert [float(r[1]) for r in rows] == pytest.approx(masses, abs=5e-4)
    assert [r[2] for r in rows] == ["right"] * wrong + ["wrong"] * (8 - wrong)
    assert (out / TIMELINE).is_file()


def demo_like_ptm(n_extra: int = 0) -> tuple[Ptm, tuple[int, ...]]:
    """A PTM whose timeline splits the mass at visit 4 between the truth (a new place) and a loop closure
    onto visit 0's place, the greedy answer, and settles on the truth at visit 7; ``n_extra`` sure visits
    more."""
    from ptm_ros.model.ptm import TimelineStep, greedy_dict, timeline_list

    truth = (0, 1, 2, 3, 4, 5, 4, 0, *range(6, 6 + n_extra))
    greedy = (0, 1, 2, 3, 0, 4, 0, 5, *range(6, 6 + n_extra))
    split = {4: 0.22, 5: 0.24, 6: 0.46}
    steps = []
    for n in range(1, len(truth) + 1):
        t, g = canonical(truth[:n]), canonical(greedy[:n])
        if n - 1 in split:
            steps.append(TimelineStep(n, ((g, 1 - split[n - 1]), (t, split[n - 1]))))
        elif t == g:
            steps.append(TimelineStep(n, ((t, 1.0),)))
        else:
            steps.append(TimelineStep(n, ((t, 0.99), (g, 0.005))))
    landmarks = [Landmark(k, float(k), (float(k), 0.0, 0.0)) for k in range(len(truth))]
    ptm = make_ptm(landmarks, {truth: 0.99, greedy: 0.005}, inference={"method": "rbpf"})
    return Ptm(
        ptm.landmarks,
        ptm.topologies,
        inference={"method": "rbpf", "timeline": timeline_list(steps)},
        extra={"greedy": greedy_dict(greedy, 0.99)},
    ), truth


def test_the_summary_prints_how_the_mass_moved_and_the_greedy_answer_beside_it():
    """Issue #25: a row per visit (the truth's mass, whether the greedy answer so far is right, the most
    probable topologies marked * true and g greedy), then the greedy answer and where it went wrong; a
    long timeline keeps the visits where the mass moved; without a truth, only the marks of greedy."""
    from ptm_ros.tools.outputs import greedy_notes
    from ptm_ros.tools.run import TIMELINE_ROWS, eventful, timeline_lines

    ptm, truth = demo_like_ptm()
    lines = timeline_lines(ptm, canonical(truth))
    assert lines[1].split() == ["visit", "truth", "greedy", "topologies"]
    assert lines[2].split() == ["0", "1.000", "right", "1.000", "0*g"]
    assert lines[6].split() == ["4", "0.220", "wrong", "0.780", "01230g", "0.220", "01234*"]
    assert lines[9].split() == ["7", "0.990", "wrong", "0.990", "01234540*", "0.005", "01230405g"]
    assert len(lines) == 10
    (note,) = greedy_notes(ptm, canonical(truth))
    assert note.endswith(
        "01230405, 6 places: wrong, from visit 4 on: there it closed a loop onto the place of visit 0, and "
        "visit 4 is a new place"
    )
    assert greedy_notes(ptm, canonical((0, 1, 2, 3, 0, 4, 0, 5))) == [
        note.split(": wrong")[0] + ": the true topology"
    ]
    assert timeline_lines(ptm)[1].split() == ["visit", "topologies"]
    assert timeline_lines(ptm)[6].split() == ["4", "0.780", "01230g", "0.220", "01234"]
    assert (
        greedy_notes(Ptm(ptm.landmarks, ptm.topologies))
        == []
        == timeline_lines(Ptm(ptm.landmarks, ptm.topologies))
    )

    long, truth = demo_like_ptm(n_extra=2 * TIMELINE_ROWS)
    lines = timeline_lines(long, canonical(truth))
    from ptm_ros.model.ptm import ptm_timeline

    assert eventful(ptm_timeline(long), 4) == [0, 4, 5, 6, 7, len(truth) - 1]
    visits = [ln.split()[0] for ln in lines[2:]]
    assert visits == ["0", "…", "4", "5", "6", "7", "…", str(len(truth) - 1)]
    assert lines[3] == "  … 3 visits with one topology holding >= 0.95 of the mass"


TIMINGS = {"timing", "wall_s", "update_ms_median", "update_ms_p95", "reweight_ms"}


def _without_timings(doc):
    """A ptm.json document without its wall-clock figures (which differ between any two runs)."""
    if isinstance(doc, dict):
        return {k: _without_timings(v) for k, v in doc.items() if k not in TIMINGS}
    if isinstance(doc, list):
        return [_without_timings(v) for v in doc]
    return doc


@pytest.mark.slow
def test_worker_processes_give_the_same_files(tjunction_bag, tmp_path, monkeypatch):
    """``--jobs 2`` builds the patches, the filter's registrations and the report's figures in worker
    processes: the same ptm.json (but for the timings), map and route graph as one process, and the
    same report figures."""
    submitted: list[str] = []
    submit = RegistrationPool.submit

    def spy(self, fn, /, *args, **kwargs):
        submitted.append(fn.__name__)
        return submit(self, fn, *args, **kwargs)

    monkeypatch.setattr(RegistrationPool, "submit", spy)
    config = small_config(inference={"method": "rbpf", "particles": 50}, detector={"kind": "equidistant"})
    run_offline(tjunction_bag, tmp_path / "one", config, jobs=1)
    assert submitted == []
    run_offline(tjunction_bag, tmp_path / "two", config, jobs=2)
    assert {"passage_patch", "register_patch_pair", "draw_histogram", "draw_topologies"} <= set(submitted)
    one, two = (json.loads((tmp_path / d / "ptm.json").read_text()) for d in ("one", "two"))
    assert _without_timings(one) == _without_timings(two)
    for name in ("map.pgm", "map.yaml", "route_graph.geojson"):
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes(), name
    figures = {p.name for p in (tmp_path / "one").glob("*.png")}
    assert {"ptm_histogram.png", "ptm_topologies.png"} <= figures
    assert figures == {p.name for p in (tmp_path / "two").glob("*.png")}
