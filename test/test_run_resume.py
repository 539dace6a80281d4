"""``ptm-run --autosave/--resume`` (issue #8): a run killed mid-way and resumed from its state file writes
the same ptm.json as an uninterrupted run; a state of another run, or a damaged one, is refused."""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ptm_ros.config import load_config
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.inference.persistence import (
    first_different_visit,
    load_filter_state,
    save_filter_state,
    visit_from_state,
)
from ptm_ros.io.bag import read_run
from ptm_ros.io.simulator import SimConfig, simulate, write_run
from ptm_ros.io.worlds import get_world
from ptm_ros.nodes.filter_inbox import FilterInbox, Reaction
from ptm_ros.nodes.messages import END_SCHEMA, visit_message
from ptm_ros.tools import run as run_cli
from ptm_ros.tools.checkpoint import RunCheckpoint, check_run_state, run_state_meta
from ptm_ros.tools.outputs import OUTPUT_FILES
from ptm_ros.tools.pipeline import detect_visits, run_offline

REPO = Path(__file__).resolve().parents[1]
# Equidistant visits every 1.5 m with laser patches (unrefined, no laser odometry: fast to detect), so
# that the filter, which registers patches, takes most of the run.
PARAMS = {
    "detector": {"kind": "equidistant", "equidistant": {"spacing": 1.5}},
    "laser_odometry": {"enabled": False},
    "laser": {"refine": False},
}
PARAMS_YAML = (
    "detector: {kind: equidistant, equidistant: {spacing: 1.5}}\n"
    "laser_odometry: {enabled: false}\nlaser: {refine: false}\n"
)
TIMING_KEYS = ("update_ms_median", "update_ms_p95", "reweight_ms")  # wall times inside ``inference``


def simulated_bag(path: Path, visits: int, seed: int) -> Path:
    run = simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(seed), visits=visits)
    return write_run(run, path)


@pytest.fixture(scope="module")
def bag(tmp_path_factory) -> Path:
    return simulated_bag(tmp_path_factory.mktemp("sim") / "tj", 5, 4)  # test_pipeline's bag: 16 visits here


@pytest.fixture(scope="module")
def params(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("params") / "p.yaml"
    path.write_text(PARAMS_YAML)
    return path


@pytest.fixture(scope="module")
def visits(bag) -> list:
    """The run's landmark visits under :data:`PARAMS` (what ptm-run and the detector node find)."""
    return detect_visits(read_run(bag), load_config(None, PARAMS))


def comparable(doc: dict) -> dict:
    """A ptm.json document without its timings (the only fields a resumed run may change)."""
    out = dict(doc)
    out.pop("timing")
    out["inference"] = {k: v for k, v in doc["inference"].items() if k not in TIMING_KEYS}
    return out


def read_ptm(out: Path) -> dict:
    return json.loads((out / OUTPUT_FILES["ptm"]).read_text())


def saved_visits(path: Path) -> int:
    state, _ = load_filter_state(path)
    return len(state["filter"]["visits"])


def saved_visit_list(state: dict) -> list:
    return [visit_from_state(d) for d in state["filter"]["visits"]]


@pytest.fixture(scope="module")
def reference(bag, params, tmp_path_factory) -> dict:
    """ptm.json of an uninterrupted run without any state file."""
    out = tmp_path_factory.mktemp("reference")
    assert (
        run_cli.main(
            [str(bag), "--out", str(out), "--params", str(params), "--quiet", "--no-report", "--no-map"]
        )
        == 0
    )
    assert not (out / OUTPUT_FILES["state"]).exists()
    return read_ptm(out)


class Interrupted(Exception):
    """Stands for a kill between two visits in the in-process test."""


def interrupt_after(k: int):
    """A ``progress`` wrapper that hands over ``k`` visits, then stops the run."""

    def wrap(items, total):
        for n, item in enumerate(items):
            if n == k:
                raise Interrupted
            yield item

    return wrap


@pytest.fixture(scope="module")
def partial_state(bag, tmp_path_factory) -> Path:
    """The state file of a run saved every 2 visits and interrupted after 5: it holds 4 visits. The run
    was asked to resume from a file that did not exist yet: it started afresh and said so."""
    out = tmp_path_factory.mktemp("partial")
    notes: list[str] = []
    checkpoint = RunCheckpoint(out / "state.npz", every=2, resume=True)
    with pytest.raises(Interrupted):
        run_offline(
            bag,
            out,
            load_config(None, PARAMS),
            progress=interrupt_after(5),
            write_report=False,
            write_map=False,
            checkpoint=checkpoint,
            log=notes.append,
        )
    assert any("starting afresh" in n for n in notes), notes
    assert not (out / OUTPUT_FILES["ptm"]).exists()
    assert saved_visits(checkpoint.path) == 4
    return checkpoint.path


@pytest.mark.slow
def test_resume_in_process_gives_the_uninterrupted_ptm(bag, reference, partial_state, tmp_path):
    state = shutil.copy(partial_state, tmp_path / "state.npz")
    notes: list[str] = []
    result = run_offline(
        bag,
        tmp_path,
        load_config(None, PARAMS),
        write_report=False,
        write_map=False,
        checkpoint=RunCheckpoint(state, every=2, resume=True),
        log=notes.append,
    )
    assert result.resumed_visits == 4
    assert any("resumed from" in n and "4 of 16" in n for n in notes), notes
    n = len(reference["landmarks"])
    assert n == 16 and saved_visits(state) == n  # saved after the last visit too
    # the registration cache and its counters were restored: the same diagnostics, not more registrations
    assert read_ptm(tmp_path)["diagnostics"] == reference["diagnostics"]
    assert comparable(read_ptm(tmp_path)) == comparable(reference)


@pytest.mark.slow
def test_killed_run_resumes_to_the_uninterrupted_ptm(bag, params, reference, tmp_path):
    """SIGKILL a ``ptm-run --autosave 1`` subprocess once its state holds a few visits, then resume."""
    out = tmp_path / "out"
    state = out / OUTPUT_FILES["state"]
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "ptm_ros.tools.run", str(bag), "--out", str(out), "--params", str(params)]
    cmd += ["--quiet", "--no-report", "--no-map", "--autosave", "1"]
    n = len(reference["landmarks"])
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120.0
        while proc.poll() is None and time.monotonic() < deadline:
            if state.exists() and saved_visits(state) >= 3:
                break
            time.sleep(0.02)
        proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == -signal.SIGKILL, f"ptm-run ended by itself before the kill: {err.decode()}"
    killed_at = saved_visits(state)
    assert 3 <= killed_at < n
    assert not (out / OUTPUT_FILES["ptm"]).exists()
    done = subprocess.run(
        [*cmd, "--resume"], env=env, capture_output=True, text=True, timeout=300, check=False
    )
    assert done.returncode == 0, done.stderr
    assert f"{killed_at} of {n} visits already filtered" in done.stderr
    assert saved_visits(state) == n
    assert comparable(read_ptm(out)) == comparable(reference)


def resume_error(bag: Path, params: Path, state: Path, tmp_path: Path, capsys, *extra: str) -> str:
    """Run ``ptm-run --resume`` expecting exit code 2; its one-line error message."""
    args = [str(bag), "--out", str(tmp_path / "o"), "--params", str(params), "--quiet", "--no-report"]
    code = run_cli.main([*args, "--resume", "--state-file", str(state), *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert err.startswith("ptm-run: error: ") and "\n" not in err
    assert not (tmp_path / "o" / OUTPUT_FILES["ptm"]).exists()
    return err


def test_state_of_other_parameters_is_refused(bag, params, partial_state, tmp_path, capsys):
    err = resume_error(bag, params, partial_state, tmp_path, capsys, "--seed", "7")
    assert "other parameters" in err and "inference.seed" in err
    err = resume_error(bag, params, partial_state, tmp_path, capsys, "--particles", "5")
    assert "inference.particles" in err
    other = tmp_path / "other.yaml"
    other.write_text(PARAMS_YAML.replace("1.5", "2.0"))
    err = resume_error(bag, other, partial_state, tmp_path, capsys)
    assert "detector.equidistant.spacing" in err
    assert saved_visits(partial_state) == 4  # the file is left as it was


def test_state_of_another_bag_is_refused(params, partial_state, tmp_path, capsys):
    other = simulated_bag(tmp_path / "other", 3, 5)
    err = resume_error(other, params, partial_state, tmp_path, capsys)
    assert "landmark visits" in err and "another bag" in err


def test_state_of_other_visits_is_refused(bag, partial_state, visits):
    """Same number of visits but other values: the fingerprint, and the saved visits themselves."""
    config = load_config(None, PARAMS)
    state, meta = load_filter_state(partial_state)
    assert len(check_run_state(state, meta, visits, partial_state)) == 4
    moved = [*visits[:2], replace(visits[2], stamp=visits[2].stamp + 1e-6), *visits[3:]]
    with pytest.raises(DataError, match="visits differ"):
        check_run_state(state, meta, moved, partial_state)
    used = replace(config, detector=replace(config.detector, kind="equidistant"))
    forged = run_state_meta(used, bag, moved)  # a meta that matches the moved visits: the saved ones do not
    with pytest.raises(DataError, match="its visit 2 differs"):
        check_run_state(state, forged, moved, partial_state)
    patch = visits[3].patch.copy()
    patch[0, 0] += 1e-9  # one coordinate of one laser patch point
    other_patch = [*visits[:3], replace(visits[3], patch=patch), *visits[4:]]
    assert first_different_visit(saved_visit_list(state), other_patch) == 3
    assert first_different_visit(saved_visit_list(state), visits) is None


def test_corrupt_or_foreign_state_is_refused(bag, params, partial_state, tmp_path, capsys):
    data = bytearray(partial_state.read_bytes())
    corrupt = tmp_path / "corrupt.npz"
    data[len(data) // 2] ^= 0xFF
    corrupt.write_bytes(bytes(data))
    assert "corrupt" in resume_error(bag, params, corrupt, tmp_path, capsys)
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(partial_state.read_bytes()[: len(data) // 3])
    assert "corrupt" in resume_error(bag, params, truncated, tmp_path, capsys)
    foreign = tmp_path / "other.npz"
    state, _ = load_filter_state(partial_state)
    save_filter_state(foreign, state, meta={"node": "map_publisher"})
    assert "written by map_publisher" in resume_error(bag, params, foreign, tmp_path, capsys)
    save_filter_state(foreign, state, meta={"node": "topology_filter"})
    assert "lack the configuration" in resume_error(bag, params, foreign, tmp_path, capsys)


# ------------------------------------------------------------------ one schema: ptm-run <-> the node


def node_inbox(state_file: Path | None = None) -> FilterInbox:
    """The topology filter node's logic with the run's configuration (as its parameters would give)."""
    return FilterInbox(load_config(None, PARAMS), logging.getLogger("test_run_resume"), state_file=state_file)


def detector_messages(visits, session: str) -> list[str]:
    """The detector node's history of the run on landmark_visits: every visit, then its end marker."""
    end = json.dumps({"schema": END_SCHEMA, "visits": len(visits), "session": session})
    return [*(visit_message(v, session) for v in visits), end]


@pytest.mark.slow
def test_ptm_run_resumes_a_state_the_filter_node_saved(bag, params, reference, visits, tmp_path):
    """A checkpoint of the node (6 of the run's visits, from a detector session) resumed by ``ptm-run``:
    the same ptm.json as the uninterrupted run."""
    node = node_inbox(tmp_path / "node.npz")
    for text in detector_messages(visits, "detector-1")[:6]:
        node.receive(text)
    node.save_state()
    out = tmp_path / "out"
    argv = [str(bag), "--out", str(out), "--params", str(params), "--quiet", "--no-report", "--no-map"]
    assert run_cli.main([*argv, "--resume", "--state-file", str(tmp_path / "node.npz")]) == 0
    assert comparable(read_ptm(out)) == comparable(reference)
    assert read_ptm(out)["inference"]["n_topologies"] == reference["inference"]["n_topologies"]


@pytest.mark.slow
def test_the_filter_node_resumes_a_state_ptm_run_saved(partial_state, visits, tmp_path):
    """``ptm-run``'s checkpoint (4 visits) resumed by the node, then the whole run replayed by a new
    detector session (as ``ptm-bringup --bag`` does): the session is adopted, the 4 visits are skipped as
    redelivered, and the map ends where the uninterrupted node's does."""
    fresh = node_inbox()
    for text in detector_messages(visits, "detector-1"):
        fresh.receive(text)
    state = shutil.copy(partial_state, tmp_path / "state.npz")
    node = node_inbox(tmp_path / "node.npz")
    assert node.resume(Path(state)) is Reaction.PUBLISH
    assert node.persistence["resumed_visits"] == 4 and len(node.session.visits) == 4
    node.save_state()  # before any detector: the adoption is pending in the node's own state too
    node = node_inbox(tmp_path / "node.npz")
    assert node.resume(tmp_path / "node.npz") is Reaction.PUBLISH
    for text in detector_messages(visits, "detector-2"):
        node.receive(text)
    assert node.counters["redelivered"] == 4 and node.counters["resets"] == 0
    assert node.counters["accepted"] == len(visits) - 4 and node.complete
    assert node.current_ptm().topologies == fresh.current_ptm().topologies
    other = node_inbox()  # another run's detector: its visit 0 is not the state's, a new map starts
    assert other.resume(Path(state)) is Reaction.PUBLISH
    moved = [replace(visits[0], stamp=visits[0].stamp + 1e-3), *visits[1:]]
    other.receive(detector_messages(moved, "detector-3")[0])
    assert other.counters["redelivered"] == 0 and len(other.session.visits) == 1


def test_other_methods_and_bad_options_are_refused(bag, params, tmp_path, capsys):
    base = [str(bag), "--out", str(tmp_path / "o"), "--params", str(params), "--quiet"]
    for extra in (
        ["--method", "mcmc", "--autosave", "1"],
        ["--method", "exact", "--resume"],
        ["--autosave", "0"],
        ["--state-file", str(tmp_path / "s.npz")],
        ["--jobs", "0"],
    ):
        assert run_cli.main([*base, *extra]) == 2, extra
        err = capsys.readouterr().err.strip()
        assert err.startswith("ptm-run: error: ") and "\n" not in err, err
    assert not (tmp_path / "o").exists()
    with pytest.raises(ConfigError, match="needs the particle filter"):
        run_offline(
            bag,
            tmp_path / "o",
            load_config(None, {**PARAMS, "inference": {"method": "mcmc"}}),
            checkpoint=RunCheckpoint(tmp_path / "s.npz", every=1),
        )
    with pytest.raises(ConfigError, match="nothing to do"):
        RunCheckpoint(tmp_path / "s.npz")
    with pytest.raises(ConfigError, match=">= 0"):
        RunCheckpoint(tmp_path / "s.npz", every=-1)
