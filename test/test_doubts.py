"""Where the map is unsure (:mod:`ptm_ros.reporting.doubts`): answers per visit against brute force, plain
words."""

from __future__ import annotations

import numpy as np
import pytest

from ptm_ros.errors import ModelError
from ptm_ros.model.partitions import enumerate_partitions
from ptm_ros.model.posterior import same_place_probabilities
from ptm_ros.model.ptm import Landmark, make_ptm
from ptm_ros.reporting.doubts import doubt_lines, doubts_dict, find_doubts, first_visits


def ptm_of(weighted, n):
    landmarks = [Landmark(k, 10.0 * k, (float(k), 0.0, 0.0)) for k in range(n)]
    return make_ptm(landmarks, weighted)


def test_a_visit_in_doubt_names_its_answers_most_probable_first():
    ptm = ptm_of({(0, 1, 0): 0.6, (0, 1, 2): 0.3, (0, 1, 1): 0.1}, 3)
    doubts = find_doubts(ptm)
    assert [d.visit for d in doubts.visits] == [2]
    (d,) = doubts.visits
    assert d.stamp == 20.0
    assert [a.place_of for a in d.answers] == [0, None, 1]
    assert [a.probability for a in d.answers] == pytest.approx([0.6, 0.3, 0.1])
    assert doubts.map_probability == pytest.approx(0.6) and doubts.runner_up_probability == pytest.approx(0.3)
    assert [a.place_of for a in find_doubts(ptm, 0.2).visits[0].answers] == [0, None]
    lines = doubt_lines(doubts)
    assert lines[0] == (
        "the map is unsure where 1 visit is: the most probable topology holds 0.60 of the probability, "
        "the next one 0.30"
    )
    assert lines[1] == (
        "visit 2 (t = 20.0 s) is the place of visit 0 (0.60) or a new place (0.30) "
        "or the place of visit 1 (0.10)"
    )
    assert doubts_dict(doubts)["visits"][0]["answers"][1] == {
        "place_of": None,
        "probability": pytest.approx(0.3),
    }


def test_a_sure_map_says_so_and_listed_masses_are_renormalised():
    sure = find_doubts(ptm_of({(0, 1, 0): 1.0}, 3))
    assert sure.sure and doubt_lines(sure) == [
        "the map is sure where every visit is: the most probable topology holds 1.00 of the probability"
    ]
    # listed masses summing to 0.8: answers are shares of the listed mass
    part = find_doubts(ptm_of({(0, 1, 0): 0.4, (0, 1, 2): 0.4}, 3))
    assert [a.probability for a in part.visits[0].answers] == pytest.approx([0.5, 0.5])
    assert part.listed_mass == pytest.approx(0.8)
    assert doubt_lines(part)[-1] == "(answers from the listed topologies, which hold 0.80 of the probability)"


@pytest.mark.parametrize("seed", range(5))
def test_answers_against_brute_force_on_random_ptms(seed):
    """Over random distributions on all partitions of 6 visits: each visit's answers sum to 1, the
    probability of revisiting the place first seen at i is at most the same-place marginal of (i, j), and
    summed over every visit of that place it is exactly the same-place marginal with i's first visit."""
    rng = np.random.default_rng(seed)
    parts = list(enumerate_partitions(6))
    chosen = rng.choice(len(parts), size=12, replace=False)
    w = rng.dirichlet(np.full(12, 0.3))
    dist = {tuple(parts[k]): float(p) for k, p in zip(chosen, w, strict=True)}
    doubts = find_doubts(ptm_of(dist, 6), threshold=1e-12)
    same = same_place_probabilities(dist, 6)
    new = np.array([sum(p for lab, p in dist.items() if first_visits(lab)[j] == j) for j in range(6)])
    by_visit = {d.visit: d for d in doubts.visits}
    for j in range(6):
        if j not in by_visit:  # sure: one answer holds (almost) everything
            continue
        answers = by_visit[j].answers
        assert sum(a.probability for a in answers) == pytest.approx(1.0)
        for a in answers:
            if a.place_of is None:
                assert a.probability == pytest.approx(new[j])
            else:
                assert a.probability <= same[a.place_of, j] + 1e-12
                brute = sum(p for lab, p in dist.items() if first_visits(lab)[j] == a.place_of)
                assert a.probability == pytest.approx(brute)


def test_bad_threshold_and_empty_ptm():
    with pytest.raises(ModelError, match="threshold"):
        find_doubts(ptm_of({(0,): 1.0}, 1), 0.5)
    with pytest.raises(ModelError, match="without topologies"):
        find_doubts(ptm_of({}, 0))


def test_the_filter_node_logs_only_a_doubt_about_its_newest_visit():
    from ptm_ros.nodes.topology_filter import newest_doubt

    assert newest_doubt(ptm_of({(0, 1, 0): 0.6, (0, 1, 2): 0.4}, 3)).startswith("visit 2 (t = 20.0 s) is")
    assert newest_doubt(ptm_of({(0, 1, 0, 2): 0.6, (0, 1, 2, 3): 0.4}, 4)) is None  # visit 2 in doubt, 3 sure
    assert newest_doubt(None) is None
