"""Shared pytest fixtures."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import call
from ros_helpers import ProcessLogs
from run_cache import once_per_run

from ptm_ros.config import load_config
from ptm_ros.io.bag import read_run
from ptm_ros.io.simulator import SimConfig, simulate, write_run
from ptm_ros.io.worlds import get_world
from ptm_ros.tools.pipeline import corrected_odometry, detect_visits, run_extractor

REPO = Path(__file__).resolve().parents[1]
DATASETS = REPO.parent / "shared" / "datasets"


def pytest_configure(config: pytest.Config) -> None:
    """The suite's markers: ``make check`` runs the tests that carry neither (``-m "not slow and not dds"``),
    ``make test`` runs them all."""
    config.addinivalue_line(
        "markers",
        "slow: 2 s or more on the 2-core machine (ptm-run, the real logs, bringups): not in make check",
    )
    config.addinivalue_line(
        "markers", "dds: starts rclpy nodes or processes talking over DDS on a ROS domain: not in make check"
    )


#: The logs of the processes a test started (fixture ``process_logs``), kept on its item for the report.
PROCESS_LOGS = pytest.StashKey[ProcessLogs]()


@pytest.fixture
def process_logs(request: pytest.FixtureRequest) -> ProcessLogs:
    """Where a test registers the logs of the processes it starts (``logs.add("ptm-bringup", lambda:
    run.log)``): each is shown in full below the failure when the test fails."""
    logs = ProcessLogs()
    request.node.stash[PROCESS_LOGS] = logs
    return logs


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> object:
    """A failed test's report gets the full log of every process it registered (``process_logs``)."""
    report = yield
    logs = item.stash.get(PROCESS_LOGS, None)
    if logs is not None and report.failed:
        for name, text in logs.sections():
            report.sections.append((f"full log of {name} ({call.when})", text))
    return report


@pytest.fixture(scope="session")
def datasets_dir() -> Path:
    """``../shared/datasets`` beside the checkout; tests needing it skip when it is absent."""
    if not (DATASETS / "README.md").is_file():
        pytest.skip(f"real datasets not available at {DATASETS} (clone with ../shared beside the checkout)")
    return DATASETS


@pytest.fixture(scope="session")
def multi_loop_run(tmp_path_factory):
    """A simulated multi-loop run (20 visits) through the bag round trip: the run, the default config, its
    visits, the corrected odometry, the true topology (visits of one simulated place share a label) and
    the simulator's true poses at the odometry stamps (made once per run: :func:`run_cache.once_per_run`)."""
    return once_per_run(
        tmp_path_factory, "conftest.multi_loop_run", lambda: _multi_loop_run(tmp_path_factory)
    )


def _multi_loop_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("sim") / "two"
    sim = simulate(get_world("multi-loop"), SimConfig(), np.random.default_rng(0), visits=20)
    write_run(sim, out)
    run = read_run(out)
    config = load_config()
    extractor = run_extractor(run, config)
    visits = detect_visits(run, config, extractor=extractor)
    odom = corrected_odometry(run, extractor)
    assert len(sim.true_poses) == len(run.odometry.stamps)  # the bag's odometry is the simulator's
    true_xy = sim.true_poses[np.searchsorted(run.odometry.stamps, [v.stamp for v in visits]), :2]
    labels: list[int] = []
    for k, xy in enumerate(true_xy):
        near = [labels[j] for j in range(k) if np.linalg.norm(true_xy[j] - xy) < 1.5]
        labels.append(near[0] if near else max(labels, default=-1) + 1)
    assert len(set(labels)) < len(labels), "the run must revisit a place"
    return run, config, visits, odom, labels, sim.true_poses


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory) -> tuple[Path, Path, str, str]:
    """A private copy of ``bags/demo`` (for the orphan check of the one test that replays it) and
    ``ptm-run`` on it with ``make demo``'s parameters (config/demo.yaml; the map, the report, the progress
    bars): ``(bag, output directory, stdout, stderr)``; made once per run."""

    def make() -> tuple[Path, Path, str, str]:
        from ptm_ros.tools import run as run_cli

        bag = tmp_path_factory.mktemp("demo_run") / "demo"
        shutil.copytree(REPO / "bags" / "demo", bag)
        out = bag.parent / "run"
        code, printed, err = call(
            run_cli.main, [bag, "--out", out, "--params", REPO / "config" / "demo.yaml"]
        )
        assert code == 0, err
        return bag, out, printed, err

    return once_per_run(tmp_path_factory, "conftest.demo_run", make)


@pytest.fixture(scope="session")
def sim_bag(tmp_path_factory):
    """A short simulated t-junction run (5 visits of its places, seed 4)."""
    out = tmp_path_factory.mktemp("nodes") / "tj"
    write_run(simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(4), visits=5), out)
    return out


@pytest.fixture(scope="session")
def sim_extraction(sim_bag, tmp_path_factory):
    """Equidistant visits of :func:`sim_bag`, with signatures and laser patches, and the bag's odometry as
    they saw it (laser-corrected, as the detector publishes it): made once per run."""

    def make():
        # equidistant visits: enough of them on this short bag (laser surprise finds only its 2 junctions)
        run, config = read_run(sim_bag), load_config(None, {"detector": {"kind": "equidistant"}})
        extractor = run_extractor(run, config)
        return detect_visits(run, config, extractor=extractor), corrected_odometry(run, extractor)

    return once_per_run(tmp_path_factory, "conftest.sim_extraction", make)


@pytest.fixture(scope="session")
def sim_visits(sim_extraction):
    """The visits of :func:`sim_extraction`."""
    return sim_extraction[0]


@pytest.fixture(scope="session")
def sim_odometry(sim_extraction):
    """The corrected odometry of :func:`sim_extraction`, a pose per odometry sample of :func:`sim_bag`."""
    return sim_extraction[1]
