"""The offline pipeline end to end: simulated bag → visits → exact PTM → ptm.json, report, score."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ptm_ros.config import PtmConfig, load_config
from ptm_ros.io.bag import read_run
from ptm_ros.io.simulator import SimConfig, simulate, write_run
from ptm_ros.io.worlds import get_world
from ptm_ros.partitions import bell
from ptm_ros.ptm import load_ptm
from ptm_ros.tools import run as run_cli
from ptm_ros.tools.pipeline import detect_visits, run_offline


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
    assert diag["laser_odometry"]["matched"] >= 0.9 * len(run.scans.stamps)
    assert any(
        v.pose != tuple(run.odometry.poses[int(np.flatnonzero(stamps == v.stamp)[0])]) for v in corrected
    )


def test_run_offline_writes_a_valid_scored_ptm(tjunction_bag, tmp_path):
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


def test_cli_reports_errors_with_exit_code(tmp_path, capsys):
    assert run_cli.main([str(tmp_path / "missing.bag"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "ptm-run: error" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("inference: {method: magic}\n")
    assert run_cli.main([str(tmp_path), "--out", str(tmp_path / "o"), "--params", str(bad), "--quiet"]) == 2
    assert "inference method" in capsys.readouterr().err


def test_cli_prints_topologies_and_score(tjunction_bag, tmp_path, capsys):
    params = tmp_path / "p.yaml"
    params.write_text(
        "detector: {kind: equidistant, equidistant: {spacing: 5.0}}\nmodel: {use_laser: false}\n"
    )
    code = run_cli.main(
        [str(tjunction_bag), "--out", str(tmp_path / "o"), "--params", str(params), "--quiet"]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    assert "most probable topologies" in out and "#1 p = " in out and "MAP F1" in out


def test_mcmc_and_rbpf_agree_with_exact_on_a_small_run(tjunction_bag, tmp_path):
    """The three estimators over the same visits and model: MCMC's visited-set estimate and the filter
    (particles >= the number of topologies it can hold) against enumeration."""
    from ptm_ros.posterior import total_variation

    model = {"use_laser": False, "odometry": {"n_samples": 0}}
    ptms = {}
    for method in ("exact", "mcmc", "rbpf"):
        cfg = small_config(model=model, inference={"method": method, "top": 10_000, "particles": 10_000})
        ptms[method] = run_offline(tjunction_bag, tmp_path / method, cfg, write_report=False).ptm
    dist = {m: {t.labels: t.probability for t in p.topologies} for m, p in ptms.items()}
    assert total_variation(dist["exact"], dist["mcmc"]) < 0.01
    assert total_variation(dist["exact"], dist["rbpf"]) < 0.05  # EKF linearisation vs batch Laplace
    assert ptms["mcmc"].inference["converged"] is True
