"""The topology filter node's logic without rclpy (:class:`ptm_ros.nodes.filter_inbox.FilterInbox`): the
detector's visit stream (gaps, duplicates, sessions, restarts, end markers), the filter session it feeds,
and the state file (autosave, resume, unusable files). The node wires it to topics; the DDS tests of
``test_nodes.py`` check that wiring."""

from __future__ import annotations

import json
import re
from dataclasses import replace

import numpy as np
import pytest

from ptm_ros.config import load_config
from ptm_ros.errors import DataError, ModelError
from ptm_ros.inference.persistence import load_filter_state
from ptm_ros.nodes.filter_inbox import BENIGN, COUNTERS, MAX_VISIT_GAP, FilterInbox, Reaction
from ptm_ros.nodes.messages import END_SCHEMA, visit_message
from ptm_ros.perception.landmarks import visit_to_json


class Lines:
    """A logger that keeps its lines: ``(level, message)``."""

    def __init__(self) -> None:
        self.items: list[tuple[str, str]] = []

    def debug(self, message: str) -> None:
        self.items.append(("debug", message))

    def info(self, message: str) -> None:
        self.items.append(("info", message))

    def warning(self, message: str) -> None:
        self.items.append(("warning", message))

    def error(self, message: str) -> None:
        self.items.append(("error", message))


def inbox(**kwargs) -> FilterInbox:
    """A filter inbox without laser, 20 particles (the configuration a node gets from its parameters)."""
    config = load_config(None, {"model": {"use_laser": False}, "inference": {"particles": 20}})
    return FilterInbox(config, Lines(), **kwargs)


def end(count, session=None) -> str:
    doc = {"schema": END_SCHEMA, "visits": count}
    return json.dumps(doc if session is None else {**doc, "session": session})


def stream_messages(visits, session) -> list[str]:
    """The detector's history on landmark_visits: its visits (numbered from 0), then its end marker."""
    return [
        *(visit_message(replace(v, index=i), session) for i, v in enumerate(visits)),
        end(len(visits), session),
    ]


@pytest.fixture
def visits(sim_visits):
    return [replace(u, signature=None) for u in sim_visits]


@pytest.mark.slow
def test_bookkeeping_of_gaps_duplicates_rejections_and_restarts(sim_visits, monkeypatch):
    """Visit stream anomalies without session ids."""
    box = inbox()
    v = sim_visits
    assert box.receive(visit_to_json(v[0])) is Reaction.NEW_VISIT
    box.receive(visit_to_json(v[1]))
    box.receive(visit_to_json(v[3]))  # visit 2 never arrives
    assert box.receive(visit_to_json(v[1])) is Reaction.NONE  # a duplicate
    box.receive(visit_to_json(v[0]))  # visit 0 delivered again: a duplicate too, not a restart
    assert any(u.signature is not None for u in box.session.visits)
    box.receive(
        visit_to_json(replace(v[4], signature=np.zeros(3), signature_spread=None))
    )  # unlike the map's
    real_add = box.session.add

    def add(visit):
        if visit.stamp == v[4].stamp:
            raise ModelError("a visit the models cannot use")
        return real_add(visit)

    monkeypatch.setattr(box.session, "add", add)
    assert box.receive(visit_to_json(v[4])) is Reaction.NONE
    assert box.counters["gaps"] == 1 and box.counters["duplicates"] == 2
    assert box.counters["invalid"] == 1 and box.counters["rejected"] == 1
    assert len(box.session.visits) == 3 and box.counters["resets"] == 0
    assert [u.stamp for u in box.session.visits] == [v[0].stamp, v[1].stamp, v[3].stamp]
    assert not box.complete
    assert box.receive(end(4)) is Reaction.NONE
    assert not box.complete and box.counters["invalid"] == 2  # 5 visits arrived: not the end
    assert box.receive(end(5)) is Reaction.PUBLISH
    assert box.complete  # every announced visit was consumed, mapped or not
    box.receive(visit_to_json(replace(v[5], index=0)))  # a different visit 0: the detector restarted
    assert len(box.session.visits) == 1 and not box.complete and box.counters["resets"] == 1
    assert box.forget() == 1 and box.session.filter is None
    box.receive(visit_to_json(v[5]))  # after a reset, numbering starts again from the next visit
    assert [u.index for u in box.session.visits] == [0] and box.session.visits[0].stamp == v[5].stamp
    assert box.receive("{not json") is Reaction.NONE and box.counters["invalid"] == 3
    assert box.counters["messages"] == 12 and box.counters["internal_errors"] == 0
    # each kind of problem is logged once as a warning, then at debug level
    warned = [m for level, m in box._logger.items if level == "warning" and "'invalid'" in m]
    assert len(warned) == 1


def test_follows_detector_sessions(visits):
    """Visits carry the detector's session id: a new session (from visit 0) starts a new map; visits of
    another session, old visits, implausible index jumps and inconsistent end markers are dropped."""
    v = visits

    def msg(visit, session, index=None):
        return visit_message(visit if index is None else replace(visit, index=index), session)

    box = inbox()
    for k in range(3):
        box.receive(msg(v[k], "a"))
    box.receive(msg(v[3], "b", index=1))  # another session, not from its start
    box.receive(end(3, "b"))
    assert box.counters["foreign"] == 2 and len(box.session.visits) == 3
    box.receive(msg(v[3], "a", index=3 + MAX_VISIT_GAP + 1))  # a corrupt index
    box.receive(msg(v[1], "a", index=3))  # older than the map's latest visit
    assert box.counters["implausible"] == 1 and box.counters["out_of_order"] == 1
    box.receive(msg(v[0], "a"))  # visit 0 of the same session again: a duplicate
    assert box.counters["duplicates"] == 1 and box.counters["resets"] == 0
    box.receive(msg(v[0], "b"))  # session b starts (same data: a looped bag): a new map
    box.receive(msg(v[1], "b"))
    assert box.counters["resets"] == 1 and len(box.session.visits) == 2
    box.receive(msg(v[2], "a"))  # the old session is over
    box.receive(end(1, "b"))  # fewer visits than already arrived
    assert box.counters["foreign"] == 3 and box.counters["invalid"] == 1 and not box.complete
    box.receive(end(2, "b"))
    assert box.complete and [u.stamp for u in box.session.visits] == [v[0].stamp, v[1].stamp]
    assert box.problems() == 7  # foreign 3, implausible, out_of_order, invalid and duplicates 1 each
    assert box.counters["internal_errors"] == 0


def test_autosaves_and_resumes_from_the_detector_history(visits, tmp_path):
    """Issue #8: a filter killed after its last autosave, restarted with ``resume``, skips the visits the
    detector's transient-local history redelivers that it restored, maps the rest and ends exactly as a
    filter that was never interrupted. An earlier detector session in that history starts no map."""
    v = visits
    old, new = stream_messages(v[:2], "r"), stream_messages(v[2:], "s")  # a looped bag: two sessions
    history = old + new
    state = tmp_path / "filter" / "state.npz"
    reference = inbox()
    for m in history:
        reference.receive(m)
    assert reference.complete and len(reference.session.visits) == len(v) - 2

    first = inbox(state_file=state, autosave_every=2)
    for m in old + new[:5]:  # session r (2 visits, end), then visits 0..4 of session s
        first.receive(m)
    assert first.persistence["saves"] == 4  # r: 2 visits; its end; s: visits 0-1, 2-3
    assert load_filter_state(state)[0]["next_index"] == 4  # then killed: no save at shutdown

    resumed = inbox(state_file=state, autosave_every=2)
    assert resumed.resume(state) is Reaction.PUBLISH
    assert resumed.persistence["resumed_visits"] == 4 and resumed.counters["resets"] == 1
    assert [u.stamp for u in resumed.session.visits] == [u.stamp for u in v[2:6]]
    for m in history:  # what a restarted subscription receives from the detector
        resumed.receive(m)
    assert resumed.complete and resumed.session.visits == reference.session.visits
    assert resumed.session.inference().probabilities == reference.session.inference().probabilities
    values = resumed.diagnostics()
    assert values["redelivered"] == len(old) + 4  # session r whole, visits 0-3 of s
    assert values["resets"] == 1 and values["accepted"] == len(v)  # before and after the kill
    bad = [k for k in COUNTERS if k not in BENIGN and values[k]]
    assert not bad and values["persistence"]["resume_rejected"] == 0 and resumed.problems() == 0
    saved, meta = load_filter_state(state)  # saved at the end marker
    assert saved["end_count"] == len(v) - 2 and meta["config"]["inference"]["particles"] == 20
    assert resumed.save_state() == state and not resumed.dirty
    resumed.receive(new[4])  # after the redelivery, a repeat is a duplicate again
    assert resumed.counters["duplicates"] == 1
    with pytest.raises(DataError, match="state_file is not set"):
        inbox().save_state()


def test_an_empty_new_detector_session_ends_the_input_with_the_map_as_it_is(visits):
    """A restarted detector that finds no visit before its input ends: its end marker (0 visits) makes
    the map final; an end marker of another session announcing visits is still foreign."""
    box = inbox()
    for m in stream_messages(visits[:3], "a")[:3]:
        box.receive(m)
    box.receive(stream_messages(visits[:2], "b")[-1])  # "b" announces 2 visits it never sent
    assert box.counters["foreign"] == 1 and not box.complete
    assert box.receive(stream_messages([], "c")[-1]) is Reaction.PUBLISH
    assert box.complete and box.counters["ends"] == 1 and len(box.session.visits) == 3
    assert box.counters["resets"] == 0


def test_resume_from_an_unusable_state_file_starts_afresh(visits, tmp_path):
    """A corrupt or foreign state file, or one made with another configuration, is moved aside and the
    filter starts afresh (an error line); the detector's history then rebuilds the map."""
    state = tmp_path / "state.npz"
    fresh = inbox(state_file=state, autosave_every=1)
    assert fresh.resume(state) is Reaction.NONE  # no file yet: a normal start
    assert fresh.persistence == {"resumed_visits": 0, "resume_rejected": 0, "saves": 0, "save_failures": 0}
    for m in stream_messages(visits[:3], "s")[:3]:
        fresh.receive(m)
    good = state.read_bytes()
    particles_21 = load_config(None, {"model": {"use_laser": False}, "inference": {"particles": 21}})
    cases = [
        ({"config": particles_21}, good, r"another config \(inference.particles differ\)"),
        ({"refit_max_visits": 5}, good, "another refit_max_visits"),
        ({}, good[: len(good) // 2], "truncated or corrupt"),
        ({}, b"not a state", "not a ptm_ros filter state"),
    ]
    for extra, content, reason in cases:
        state.write_bytes(content)
        config = extra.pop("config", fresh.config)
        box = FilterInbox(config, Lines(), state_file=state, autosave_every=1, **extra)
        assert box.resume(state) is Reaction.NONE
        assert box.session.filter is None and box.persistence["resume_rejected"] == 1
        assert not state.exists() and (tmp_path / "state.npz.rejected").read_bytes() == content
        errors = [m for level, m in box._logger.items if level == "error"]
        assert len(errors) == 1 and re.search(f"cannot resume from {state}: .*{reason}", errors[0])
        box.state_file = None
        for m in stream_messages(visits[:3], "s"):  # the detector's history rebuilds the map
            box.receive(m)
        assert box.session.visits == fresh.session.visits and box.complete
        assert box.diagnostics()["persistence"]["resume_rejected"] == 1 and box.problems() == 1  # WARN


def test_a_failed_save_is_counted_and_the_old_file_stays(visits, tmp_path):
    """An autosave that cannot write (its directory is a file) is logged once and counted; no raise."""
    blocker = tmp_path / "file"
    blocker.write_text("x")
    box = inbox(state_file=blocker / "state.npz", autosave_every=1)
    for m in stream_messages(visits[:2], "s"):
        box.receive(m)
    assert box.persistence["save_failures"] == 3 and box.persistence["saves"] == 0
    assert len(box.session.visits) == 2 and box.problems() == 3
    warned = [m for level, m in box._logger.items if level == "warning" and "cannot save" in m]
    assert len(warned) == 1
