"""Issue #25: whole corrupted bags through ``ptm-run`` and ``ptm-eval``, and through the node suite over
DDS (``ptm-bringup --bag``) (property-based, hypothesis).

A small simulated bag is corrupted by a generated :class:`bag_corruption.Plan`: backwards and jumping
stamps on any topic, duplicates, NaN / inf / empty / over-long scans, wrong image encodings, header
stamps that are no ROS time, a topic that stops midway, a storage file cut short or overwritten. Each
run must either end with a PTM from the good messages, every bad message counted, or exit 2 with one
line on stderr (no traceback). Then ``ptm-eval`` must score that PTM against the bag's ground truth.
Through ``ptm-bringup`` the same holds for every process: no traceback in any node's log, exit 0 with a
ptm.json (the landmark detector's final ``/diagnostics`` count the bad messages, under the names the
reader uses) or exit 2 with one line.

Seeded (``derandomize=True``) and small: ``PTM_FUZZ_EXAMPLES`` examples (default 6) through ``ptm-run``,
``PTM_BRINGUP_FUZZ_EXAMPLES`` (default 2 per test) through ``ptm-bringup`` (20-60 s each);
``bench/bench_fuzz.py`` runs a larger budget through ``ptm-run``.
"""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest
from bag_corruption import INSERTED, REPLACED, TOPIC_STREAMS, Insert, Plan, Replace, Stretch, corrupt
from cli_helpers import call, one_error_line
from hypothesis import HealthCheck, Phase, currently_in_test_context, event, given, settings
from hypothesis import strategies as st
from ros_helpers import BRINGUP, Inbox, ProcessLogs, assert_no_orphans, dds_env, ros_context
from run_cache import once_per_run

from ptm_ros.io.simulator import SimConfig, simulate, write_run
from ptm_ros.io.worlds import get_world
from ptm_ros.model.ptm import from_json_dict
from ptm_ros.tools import evaluate as eval_tool
from ptm_ros.tools import run as run_tool

pytestmark = pytest.mark.slow  # ptm-run on many damaged bags (3-20 s a test)

EXAMPLES = int(os.environ.get("PTM_FUZZ_EXAMPLES", "6"))
BRINGUP_EXAMPLES = int(os.environ.get("PTM_BRINGUP_FUZZ_EXAMPLES", "2"))
RUN_ARGS = ("--quiet", "--no-report", "--particles", "10", "--seed", "0")
#: ptm-bringup's parameters: those of RUN_ARGS
BRINGUP_PARAMS = "inference: {particles: 10, seed: 0}\n"
TOPICS = tuple(TOPIC_STREAMS)


def assert_one_line_or_ok(code: int, err: str, prog: str) -> None:
    assert "Traceback" not in err
    assert code in (0, 2), f"{prog} exited {code}: {err}"
    if code == 2:
        one_error_line(err, prog)


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> tuple[Path, dict]:
    """A tiny simulated bag (t-junction, four visits) and its ptm.json (made once per run)."""

    def make() -> tuple[Path, dict]:
        root = tmp_path_factory.mktemp("fuzz_clean")
        bag = write_run(
            simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(0), visits=4), root / "bag"
        )
        code, _, err = call(run_tool.main, [bag, "--out", root / "out", *RUN_ARGS])
        assert code == 0, err
        return bag, json.loads((root / "out" / "ptm.json").read_text())

    return once_per_run(tmp_path_factory, f"{__name__}.clean", make)


def stream_skips(skipped: dict[str, int], stream: str) -> int:
    return sum(n for reason, n in skipped.items() if reason.startswith(f"{stream}-"))


def check_run(bag: Path, out: Path, plan: Plan, written, clean_ptm: dict) -> dict | None:
    """ptm-run on a corrupted bag, then ptm-eval on its PTM; the ptm.json (None after an exit 2)."""
    code, _, err = call(run_tool.main, [bag, "--out", out, *RUN_ARGS])
    if currently_in_test_context():  # --hypothesis-show-statistics: how the runs ended
        event(f"ptm-run exit {code}" + (f": {err.split(':')[2].strip()[:40]}" if code else ""))
    assert_one_line_or_ok(code, err, "ptm-run")
    if code == 2:
        # only a bag that cannot be read, or one left without the odometry visits need
        assert plan.truncate is not None or plan.smash is not None or plan.missing_from, err
        return None
    doc = json.loads((out / "ptm.json").read_text())
    diag = doc["diagnostics"]
    for reason, n in written.at_least.items():
        assert diag["skipped"].get(reason, 0) >= n, (reason, diag["skipped"])
    for stream in TOPIC_STREAMS.values():
        accounted = diag["received"][stream] + stream_skips(diag["read_skipped"], stream)
        if plan.truncate is None and plan.smash is None:  # every message written is used or counted
            assert accounted == written.messages[stream], (stream, diag)
        else:
            assert accounted <= written.messages[stream]
    n = len(doc["landmarks"])
    assert all(len(t["labels"]) == n for t in doc["topologies"])
    assert sum(t["probability"] for t in doc["topologies"]) <= 1.0 + 1e-9
    stamps = [lm["stamp"] for lm in doc["landmarks"]]
    assert stamps == sorted(stamps)
    if plan.neutral:  # only inserted bad messages: exactly the clean bag's PTM
        assert doc["landmarks"] == clean_ptm["landmarks"]
        assert doc["topologies"] == clean_ptm["topologies"]
    code, text, err = call(eval_tool.main, [out / "ptm.json", "--ground-truth", bag / "ground_truth.json"])
    assert_one_line_or_ok(code, err, "ptm-eval")
    if code == 0:
        assert 0.0 <= json.loads(text)["consistent_mass"] <= 1.0 + 1e-9
    return doc


# ------------------------------------------------------------------------------------------ strategies

fractions = st.floats(0.0, 1.0, allow_nan=False)


@st.composite
def inserts(draw) -> Insert:
    kind = draw(st.sampled_from(sorted(INSERTED)))
    topic = INSERTED[kind][0] or draw(st.sampled_from(TOPICS))
    shift = {"back-copy": st.sampled_from([0.01, 0.3, 5.0, 100.0]), "far-copy": st.sampled_from([30.0, 1e4])}
    return Insert(kind, topic, draw(fractions), draw(shift.get(kind, st.just(1.0))))


stretches = st.builds(
    Stretch,
    topic=st.sampled_from(TOPICS),
    at=fractions,
    length=st.integers(1, 12) | st.integers(100, 1000),
    shift_s=st.sampled_from([-1000.0, -100.0, -5.0, -0.5, 0.5, 5.0, 100.0, 1e6]),
)
replaces = st.builds(Replace, kind=st.sampled_from(sorted(REPLACED)), at=fractions)
neutral_plans = st.builds(
    Plan,
    inserts=st.lists(inserts(), min_size=1, max_size=8).map(tuple),
    duplicate_every=st.none() | st.integers(20, 200),
)
damaging_plans = st.builds(
    Plan,
    inserts=st.lists(inserts(), max_size=4).map(tuple),
    stretches=st.lists(stretches, max_size=3).map(tuple),
    replaces=st.lists(replaces, max_size=3).map(tuple),
    missing_from=st.lists(st.tuples(st.sampled_from(TOPICS), fractions), max_size=1).map(tuple),
    truncate=st.none() | st.floats(0.2, 0.95),
    duplicate_every=st.none() | st.integers(20, 200),
    storage=st.sampled_from(["mcap", "sqlite3"]),
    smash=st.none() | st.floats(0.0, 0.99),
)
FUZZ = settings(
    max_examples=EXAMPLES,
    derandomize=True,
    deadline=None,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@FUZZ
@given(plan=neutral_plans)
def test_inserted_bad_messages_are_counted_and_change_nothing(clean, plan, tmp_path_factory):
    work = tmp_path_factory.mktemp("neutral")
    written = corrupt(clean[0], work / "bag", plan)
    assert check_run(written.path, work / "out", plan, written, clean[1]) is not None


@FUZZ
@given(plan=damaging_plans)
def test_damaged_bags_give_a_ptm_of_the_good_messages_or_one_line(clean, plan, tmp_path_factory):
    work = tmp_path_factory.mktemp("damaged")
    written = corrupt(clean[0], work / "bag", plan)
    check_run(written.path, work / "out", plan, written, clean[1])


def test_the_issue_corruption_gives_a_ptm_with_every_bad_message_counted(clean, tmp_path):
    """Issue #25's bag: ten odometry messages stamped 5 s back, every 97th message duplicated, NaN-,
    inf-filled and empty scans. It used to fail after the inference ("visit stamps must be increasing
    odometry stamps") and write no ptm.json."""
    plan = Plan(
        stretches=(Stretch("/odom", 0.5, 10, -5.0),),
        replaces=(Replace("nan", 0.2), Replace("inf", 0.4), Replace("empty", 0.6), Replace("nan", 0.8)),
        duplicate_every=97,
    )
    written = corrupt(clean[0], tmp_path / "bag", plan)
    doc = check_run(written.path, tmp_path / "out", plan, written, clean[1])
    assert doc is not None and len(doc["landmarks"]) == len(clean[1]["landmarks"])
    skipped = doc["diagnostics"]["read_skipped"]
    duplicates = sum(written.messages.values()) - sum(clean[1]["diagnostics"]["received"].values())
    assert skipped["odometry-stamp-backwards"] == 10
    assert skipped["scan-non-finite"] + skipped["scan-empty"] >= 4
    assert sum(skipped.values()) == 10 + 4 + duplicates


# ------------------------------------------------------------------------------ through the node suite


def detector_counts(statuses: list) -> dict[str, str]:
    """The landmark detector's final ``/diagnostics`` values (the status it publishes when its input is
    finished); fails the test when none came."""
    final = [s for s in statuses if s.name.startswith("landmark_detector:")]
    final = [{kv.key: kv.value for kv in s.values} for s in final]
    final = [v for v in final if v.get("finished") == "True"]
    assert final, "the landmark detector never reported a finished input on /diagnostics"
    return final[-1]


def check_bringup(bag: Path, out: Path, plan: Plan, written, clean_ptm: dict, monkeypatch, logs: ProcessLogs):
    """ptm-bringup --bag on a corrupted bag (the node suite over DDS, a probe on /diagnostics); the
    ptm.json (None after an exit 2)."""
    from diagnostic_msgs.msg import DiagnosticArray

    params = out.parent / "params.yaml"
    params.write_text(BRINGUP_PARAMS)
    cmd = [
        *BRINGUP,
        "--bag",
        str(bag),
        "--rate",
        "0",
        "--params",
        str(params),
        "--out",
        str(out),
        "--no-report",
    ]
    with ros_context(monkeypatch) as ros:
        probe = ros.node("fuzz_probe")
        diagnostics = Inbox(probe, DiagnosticArray, "/diagnostics", 1000)
        ros.spin(probe)
        name = f"ptm-bringup on {bag.parent.name}"
        try:
            proc = subprocess.run(
                cmd, env=dds_env(ros.domain_id), capture_output=True, text=True, timeout=300, check=False
            )
        except subprocess.TimeoutExpired as err:
            partial = b"".join(x for x in (err.stdout, err.stderr) if isinstance(x, bytes))
            logs.add(name, lambda: partial.decode(errors="replace"))
            raise
        finally:
            assert_no_orphans(str(out), str(bag))
        logs.add(name, lambda: proc.stdout + proc.stderr)
        statuses = [s for m in diagnostics.items for s in m.status]
    if currently_in_test_context():  # --hypothesis-show-statistics: what was tried, how it ended
        damage = [k for k in ("stretches", "replaces", "missing_from") if getattr(plan, k)]
        damage += [k for k in ("truncate", "smash") if getattr(plan, k) is not None]
        event(f"ptm-bringup exit {proc.returncode} on {'+'.join(damage) or 'inserted messages only'}")
    assert "Traceback" not in proc.stdout + proc.stderr, "a process of the suite raised (full log below)"
    assert proc.returncode in (0, 2), f"ptm-bringup exited {proc.returncode} (full log below)"
    if proc.returncode == 2:  # a bag that cannot be read, or damaged so that no landmark visit is left
        one_error_line(proc.stderr, "ptm-bringup")
        assert not plan.neutral, proc.stderr
        assert not (out / "ptm.json").exists()
        return None
    doc = json.loads((out / "ptm.json").read_text())
    n = len(doc["landmarks"])
    assert doc["stream"]["complete"] and doc["stream"]["visits"] == n
    assert all(len(t["labels"]) == n for t in doc["topologies"])
    assert sum(t["probability"] for t in doc["topologies"]) <= 1.0 + 1e-9
    stamps = [lm["stamp"] for lm in doc["landmarks"]]
    assert stamps == sorted(stamps)
    counts = detector_counts(statuses)
    for reason, k in written.at_least.items():  # every bad message of the plan counted, by the reader's name
        assert int(counts.get(reason, 0)) >= k, (reason, counts)
        assert doc["diagnostics"]["skipped"].get(reason, 0) >= k, (reason, doc["diagnostics"])  # in ptm.json
    if plan.truncate is None and plan.smash is None:  # every message written reached the detector
        for topic, stream in TOPIC_STREAMS.items():
            assert int(counts.get(f"received.{topic}", 0)) == written.messages[stream], (topic, counts)
    if plan.neutral:  # only inserted bad messages: the clean bag's visits (ptm-run's, exactly)
        online, offline = from_json_dict(doc), from_json_dict(clean_ptm)
        assert online.landmarks == offline.landmarks
        assert [t.labels for t in online.topologies] == [t.labels for t in offline.topologies]
    return doc


BRINGUP_FUZZ = settings(
    FUZZ,
    max_examples=BRINGUP_EXAMPLES,
    phases=[Phase.explicit, Phase.reuse, Phase.generate],  # no shrinking: a minute per example
)


@pytest.mark.dds
@BRINGUP_FUZZ
@given(plan=neutral_plans)
def test_the_node_suite_counts_inserted_bad_messages_and_maps_the_rest(
    clean, plan, tmp_path_factory, monkeypatch, process_logs
):
    work = tmp_path_factory.mktemp("bringup_neutral")
    written = corrupt(clean[0], work / "bag", plan)
    assert check_bringup(written.path, work / "out", plan, written, clean[1], monkeypatch, process_logs)


@pytest.mark.dds
@BRINGUP_FUZZ
@given(plan=damaging_plans)
def test_the_node_suite_maps_damaged_bags_or_refuses_them_in_one_line(
    clean, plan, tmp_path_factory, monkeypatch, process_logs
):
    work = tmp_path_factory.mktemp("bringup_damaged")
    written = corrupt(clean[0], work / "bag", plan)
    check_bringup(written.path, work / "out", plan, written, clean[1], monkeypatch, process_logs)
