"""The filter session (:mod:`ptm_ros.session`): the one RBPF orchestration ``ptm-run`` and the
``topology_filter`` node drive; streaming equals offline, one checkpoint schema that either resumes."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ptm_ros.config import PtmConfig, load_config
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.factories import cached, make_registrar
from ptm_ros.inference.persistence import load_filter_state, save_filter_state
from ptm_ros.session import FilterSession, infer


def no_laser() -> PtmConfig:
    return load_config(None, {"model": {"use_laser": False}, "inference": {"particles": 30}})


@pytest.mark.slow
def test_streaming_session_equals_the_offline_rbpf_after_every_visit(sim_visits):
    """The ensemble after visit n is ptm-run's RBPF on visits 0..n, exactly (appearance refit + replay)."""
    config = load_config(None, {"inference": {"particles": 30}})
    session = FilterSession(config)
    registrar = cached(make_registrar(sim_visits, config))
    assert any(v.signature is not None for v in sim_visits) and any(v.patch is not None for v in sim_visits)
    for n, visit in enumerate(sim_visits):
        session.add(visit)
        offline = infer(sim_visits[: n + 1], config, registrar=registrar)
        online = session.inference()
        assert online.probabilities == offline.probabilities  # same topologies, bit-identical masses
        for lab in offline.probabilities:
            assert np.array_equal(online.positions[lab], offline.positions[lab])
    assert session.replays > 0  # the appearance priors did change along the way


def test_session_rejects_out_of_order_visits_and_resets(sim_visits):
    session = FilterSession(no_laser())
    session.add(sim_visits[0])
    before = session.inference().probabilities
    with pytest.raises(DataError, match="expected visit 1, got visit 2"):
        session.add(sim_visits[2])
    assert session.inference().probabilities == before and len(session.visits) == 1
    session.reset()
    assert session.filter is None and not session.visits
    with pytest.raises(DataError, match="no visit"):
        session.inference()
    with pytest.raises(ConfigError, match="use ptm-run for 'exact'"):
        FilterSession(load_config(None, {"inference": {"method": "exact"}}))


def test_frozen_appearance_priors_stop_replays(sim_visits):
    from ptm_ros.model.appearance import fit_appearance_model

    # with every visit carrying a signature: replays only while at most 3 visits, then the fit is frozen
    signed = [replace(v, index=i) for i, v in enumerate(v for v in sim_visits if v.signature is not None)]
    assert len(signed) >= 5
    session = FilterSession(no_laser(), refit_max_visits=3)
    for v in signed:
        session.add(v)
    assert session.replays == 2
    frozen = fit_appearance_model(signed[:3], no_laser().model.appearance)
    assert np.array_equal(session.filter.appearance.nig.mu, frozen.nig.mu)
    assert np.array_equal(session.filter.appearance.nig.beta, frozen.nig.beta)
    # appearance switching on (a second visit with a signature; visits without one are missing
    # measurements) replays the filter, even when the priors are frozen; a missing one later does not
    session = FilterSession(no_laser(), refit_max_visits=3)
    visits = [replace(v, signature=None) if n < 4 or n == 6 else v for n, v in enumerate(signed)]
    for n, v in enumerate(visits):
        before = session.replays
        session.add(v)
        if n >= 3:
            assert (session.replays > before) == (n == 5)
    assert session.filter.appearance is not None


@pytest.mark.parametrize(
    ("laser", "refit", "k"),
    [(False, 0, 4), (True, 3, 5)],  # appearance refit + replay after every visit; frozen priors, updates
)
def test_session_restored_from_a_state_file_continues_exactly(sim_visits, tmp_path, laser, refit, k):
    """Issue #8: a session saved after k visits, restored into a new session and continued, ends exactly
    where the uninterrupted session does (ensemble, positions, replays, registration counters)."""
    config = load_config(
        None, {"model": {"use_laser": laser}, "inference": {"particles": 30 if laser else 20}}
    )
    whole = FilterSession(config, refit_max_visits=refit)
    for v in sim_visits:
        whole.add(v)
    first = FilterSession(config, refit_max_visits=refit)
    for v in sim_visits[:k]:
        first.add(v)
    save_filter_state(tmp_path / "s.npz", first.state_dict(), meta={})
    resumed = FilterSession(config, refit_max_visits=refit)
    resumed.load_state(load_filter_state(tmp_path / "s.npz")[0])
    assert resumed.visits == first.visits and resumed.filter.log_weights() == first.filter.log_weights()
    if laser:
        assert resumed._pairs.keys() == first._pairs.keys() and resumed.registrations == first.registrations
    for v in sim_visits[k:]:
        resumed.add(v)
    assert resumed.inference().probabilities == whole.inference().probabilities  # bit-identical masses
    for lab, pos in whole.inference().positions.items():
        assert np.array_equal(resumed.inference().positions[lab], pos)
    assert resumed.filter.log_evidence == whole.filter.log_evidence
    assert resumed.replays == whole.replays and resumed.registrations == whole.registrations
    if refit:
        assert resumed.replays < len(sim_visits) - 1  # the restored filter itself was updated


def test_session_state_errors_leave_an_empty_session(sim_visits):
    session = FilterSession(no_laser())
    for v in sim_visits[:3]:
        session.add(v)
    state = session.state_dict()
    with pytest.raises(DataError, match="not a filter session state"):
        session.load_state({"schema": "ptm_ros.rbpf/1"})
    for broken in (
        {k: v for k, v in state.items() if k != "pairs"},
        {**state, "built_at": 7},
        {**state, "visits": state["visits"][:2]},
    ):
        with pytest.raises(DataError, match="malformed filter session state"):
            session.load_state(broken)
        assert session.filter is None and not session.visits
    session.load_state(state)
    assert len(session.visits) == 3 and session.filter.visits == session.visits


@pytest.mark.parametrize("k", [3, 6])
def test_an_offline_session_resumes_a_live_state_as_if_never_interrupted(sim_visits, tmp_path, k):
    """One checkpoint schema: a live session's state (priors re-fitted to the visits so far) resumed by an
    offline session (priors fitted to the whole run) replays the saved visits with its own priors, and
    ends exactly where the uninterrupted offline run does."""
    config = load_config(None, {"inference": {"particles": 30}})
    live = FilterSession(config, refit_max_visits=0)
    for v in sim_visits[:k]:
        live.add(v)
    save_filter_state(tmp_path / "s.npz", live.state_dict(), meta={})
    offline = FilterSession(config, fitted_to=sim_visits)
    offline.load_state(load_filter_state(tmp_path / "s.npz")[0])
    assert offline.replays == live.replays + 1  # the restored filter ran with the live priors
    assert offline.pairs.keys() >= live.pairs.keys()
    whole = infer(sim_visits, config, registrar=cached(make_registrar(sim_visits, config)))
    resumed = infer(sim_visits, config, session=offline)
    assert resumed.probabilities == whole.probabilities  # bit-identical masses
    assert offline.filter.log_evidence == whole.details["log_evidence"]
    for lab, pos in whole.positions.items():
        assert np.array_equal(resumed.positions[lab], pos)


def test_a_live_session_resumes_an_offline_state_and_refits_as_it_goes(sim_visits, tmp_path):
    """The other way: an offline state (priors of the whole run) resumed by a live session that re-fits
    after every visit ends where the uninterrupted live session does."""
    config = load_config(None, {"inference": {"particles": 30}})
    offline = FilterSession(config, fitted_to=sim_visits)
    for v in sim_visits[:4]:
        offline.add(v)
    save_filter_state(tmp_path / "s.npz", offline.state_dict(), meta={})
    live = FilterSession(config, refit_max_visits=0)
    live.load_state(load_filter_state(tmp_path / "s.npz")[0])
    assert live.filter.log_weights() == offline.filter.log_weights()  # continues with the saved priors
    whole = FilterSession(config, refit_max_visits=0)
    for v in sim_visits:
        whole.add(v)
    for v in sim_visits[4:]:
        live.add(v)
    assert live.inference().probabilities == whole.inference().probabilities
    assert live.filter.log_evidence == whole.filter.log_evidence


def test_an_offline_session_fits_its_priors_once(sim_visits):
    """``fitted_to``: the priors of the whole run from the first visit on, never a replay."""
    from ptm_ros.model.appearance import fit_appearance_model

    config = no_laser()
    session = FilterSession(config, fitted_to=sim_visits)
    for v in sim_visits:
        session.add(v)
    assert session.replays == 0
    fitted = fit_appearance_model(sim_visits, config.model.appearance)
    assert np.array_equal(session.filter.appearance.nig.mu, fitted.nig.mu)
    assert session.inference().probabilities == infer(sim_visits, config).probabilities


def test_the_ptm_says_which_visits_the_map_is_unsure_of(sim_visits):
    """``build_ptm`` (ptm-run's ptm.json and the node's ptm_graph) carries ``extra["doubts"]``: the
    visits whose place the ensemble is unsure of, with their answers (:mod:`ptm_ros.reporting.doubts`)."""
    from ptm_ros.model.ptm import to_json_dict

    config = no_laser()
    session = FilterSession(config, fitted_to=sim_visits)
    for v in sim_visits:
        session.add(v)
    ptm = session.to_ptm()
    doc = to_json_dict(ptm)["doubts"]
    assert doc["map_probability"] == ptm.topologies[0].probability
    assert doc["listed_mass"] == pytest.approx(sum(t.probability for t in ptm.topologies))
    assert all(0 < d["visit"] < len(sim_visits) for d in doc["visits"])  # visit 0 opens a place, surely
    for d in doc["visits"]:  # the answers of a visit in doubt: a split of its probability
        assert max(a["probability"] for a in d["answers"]) < 0.95
        assert sum(a["probability"] for a in d["answers"]) <= 1.0 + 1e-9


def test_exact_enumeration_too_large_names_the_limit_and_the_alternatives(sim_visits):
    config = load_config(None, {"inference": {"method": "exact", "max_exact_visits": 2}})
    with pytest.raises(
        ConfigError, match=r"inference.max_exact_visits is 2 \(at most 12\); use --method rbpf or "
    ):
        infer(sim_visits[:3], config)


def test_the_ptm_carries_the_filters_timeline_and_the_greedy_answer(sim_visits, tmp_path):
    """Issue #25: ptm.json's ``inference.timeline`` is the filter's PTM after every visit (the
    ``inference.timeline`` most probable topologies of the visits so far, the last one the PTM's own top)
    and ``greedy`` the greedy baseline's answer on the same visits; a live session's timeline at the end is
    the offline one (its last replay ran with the priors of the whole run), and a restored session, having
    decided the restored visits again, ends with the same greedy answer and timeline."""
    from ptm_ros.model.ptm import ptm_greedy, ptm_timeline
    from ptm_ros.scoring.baselines import GreedyConfig, greedy_association

    config = load_config(
        None, {"model": {"use_laser": False}, "inference": {"particles": 30, "timeline": 2, "greedy": True}}
    )
    offline = FilterSession(config, fitted_to=sim_visits)
    live = FilterSession(config, refit_max_visits=0)
    for n, v in enumerate(sim_visits):
        offline.add(v)
        live.add(v)
        assert live.greedy == greedy_association(sim_visits[: n + 1], config.model.odometry, GreedyConfig())
    ptm = offline.to_ptm()
    steps = ptm_timeline(ptm)
    assert [st.visits for st in steps] == list(range(1, len(sim_visits) + 1))
    assert len(steps[0].topologies) == 1 and all(len(st.topologies) == 2 for st in steps[1:])
    assert [(t.labels, t.probability) for t in ptm.topologies[:2]] == list(steps[-1].topologies)
    assert ptm_greedy(ptm) == offline.greedy == live.greedy
    assert ptm.extra["greedy"]["places"] == max(live.greedy) + 1
    assert ptm_timeline(live.to_ptm()) == steps
    assert infer(sim_visits, config).greedy == offline.greedy
    exact = load_config(
        None, {"model": {"use_laser": False}, "inference": {"method": "exact", "greedy": True}}
    )
    assert infer(sim_visits[:5], exact).greedy == greedy_association(
        sim_visits[:5], config.model.odometry, GreedyConfig()
    )
    assert "timeline" not in infer(sim_visits[:5], exact).details
    untimed = FilterSession(replace(config, inference=replace(config.inference, timeline=0, greedy=False)))
    untimed.add(sim_visits[0])
    assert ptm_timeline(untimed.to_ptm()) == () and "timeline" not in untimed.to_ptm().inference
    assert untimed.greedy is None and "greedy" not in untimed.to_ptm().extra  # off by default (O(N²))
    assert infer(sim_visits[:5], load_config(None, {"model": {"use_laser": False}})).greedy is None
    half = FilterSession(config, refit_max_visits=0)
    for v in sim_visits[:4]:
        half.add(v)
    save_filter_state(tmp_path / "s.npz", half.state_dict(), meta={})
    resumed = FilterSession(config, refit_max_visits=0)
    resumed.load_state(load_filter_state(tmp_path / "s.npz")[0])
    assert resumed.greedy == half.greedy
    for v in sim_visits[4:]:
        resumed.add(v)
    assert resumed.greedy == live.greedy and ptm_timeline(resumed.to_ptm()) == steps


def test_particles_max_reaches_the_filter_and_ptm_json(sim_visits):
    """``inference.particles_max`` above ``particles``: the session's filter keeps more topologies where the
    posterior is spread, up to the cap, and the PTM reports the most it held (schema-valid); off, neither."""
    from jsonschema import Draft202012Validator

    from ptm_ros.model.ptm import ptm_schema, to_json_dict

    held = {}
    for cap in (0, 200):
        config = load_config(
            None, {"model": {"use_laser": False}, "inference": {"particles": 5, "particles_max": cap}}
        )
        session = FilterSession(config, fitted_to=sim_visits)
        for v in sim_visits:
            session.add(v)
        assert session.filter is not None
        held[cap] = max(h.n_topologies for h in session.filter.history)
        doc = to_json_dict(session.to_ptm())
        assert [e.message for e in Draft202012Validator(ptm_schema()).iter_errors(doc)] == []
        assert ("particles_peak" in doc["inference"]) == (cap > 0)
    assert held[0] <= 5 < held[200] <= 200
