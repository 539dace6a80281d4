"""Where the map is unsure, in words a robot operator reads (thesis claim 1: "cognizant of failure").

A PTM answers "have I been here before?" for every landmark visit with a distribution, not a guess. For
visit ``j`` the answers are the places it can belong to: a place first seen at an earlier visit ``i``
(``j`` revisits it), or a new place. Their probabilities are the summed masses of the listed
topologies giving each answer (the topologies share canonical labels, so a place is named by its first
visit),

.. math::
    P(j \\to i) = \\sum_T P(T)\\, [T_j = T_i,\\ i = \\min\\{k : T_k = T_j\\}],
    \\qquad P(j\\ \\text{new}) = \\sum_T P(T)\\, [j = \\min\\{k : T_k = T_j\\}],

renormalised over the listed topologies (a PTM lists its most probable ones). A visit is *in doubt* when
its most probable answer holds less than ``1 - threshold`` of that mass: the map then names every answer
above ``threshold`` with its probability instead of one loop closure. The MAP topology's own mass says
how much the map as a whole is in doubt.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from ptm_ros.errors import ModelError
from ptm_ros.model.ptm import Ptm

#: Default: answers below this probability are not named, visits whose best answer is above 1 - it
#: are not in doubt.
THRESHOLD = 0.05


@dataclass(frozen=True)
class Answer:
    """One answer to "where is visit ``visit``?": the place first seen at visit ``place_of`` (None: a new
    place) with ``probability``."""

    place_of: int | None
    probability: float


@dataclass(frozen=True)
class Doubt:
    """A visit whose place the map is unsure of: its answers above the threshold, most probable first."""

    visit: int
    stamp: float
    answers: tuple[Answer, ...]


@dataclass(frozen=True)
class Doubts:
    """How unsure a PTM is: the MAP topology's mass, the runner-up's and the visits in doubt."""

    map_probability: float
    runner_up_probability: float
    listed_mass: float
    visits: tuple[Doubt, ...]

    @property
    def sure(self) -> bool:
        """No visit in doubt."""
        return not self.visits


def first_visits(labels: Sequence[int]) -> list[int]:
    """For each visit, the first visit of its place (itself when it opens a new place)."""
    first: dict[int, int] = {}
    return [first.setdefault(int(lab), k) for k, lab in enumerate(labels)]


def find_doubts(ptm: Ptm, threshold: float = THRESHOLD) -> Doubts:
    """The visits in doubt of a PTM (module docstring), in visit order.

    Raises:
        ModelError: a threshold outside (0, 0.5), or a PTM without topologies.
    """
    if not 0.0 < threshold < 0.5:
        msg = f"the doubt threshold must lie in (0, 0.5), got {threshold}"
        raise ModelError(msg)
    tops = ptm.topologies
    mass = sum(t.probability for t in tops)
    if not tops or mass <= 0.0:
        msg = "a PTM without topologies has no answers"
        raise ModelError(msg)
    n = len(tops[0].labels)
    answers: list[dict[int | None, float]] = [{} for _ in range(n)]
    for t in tops:
        for j, i in enumerate(first_visits(t.labels)):
            key = None if i == j else i
            answers[j][key] = answers[j].get(key, 0.0) + t.probability / mass
    doubts = []
    for j, dist in enumerate(answers):
        ranked = sorted(dist.items(), key=lambda kv: (-kv[1], -1 if kv[0] is None else kv[0]))
        if ranked[0][1] < 1.0 - threshold:
            named = tuple(Answer(i, p) for i, p in ranked if p >= threshold)
            doubts.append(Doubt(j, float(ptm.landmarks[j].stamp), named))
    runner_up = tops[1].probability if len(tops) > 1 else 0.0
    return Doubts(tops[0].probability, runner_up, mass, tuple(doubts))


def _answer_words(a: Answer) -> str:
    where = "a new place" if a.place_of is None else f"the place of visit {a.place_of}"
    return f"{where} ({a.probability:.2f})"


def doubt_lines(doubts: Doubts, *, most: int = 10) -> list[str]:
    """Plain sentences for a report or a console: how sure the map is, and (at most ``most``) visits in
    doubt with their answers."""
    head = f"the most probable topology holds {doubts.map_probability:.2f} of the probability"
    if doubts.runner_up_probability > 0.0:
        head += f", the next one {doubts.runner_up_probability:.2f}"
    n = len(doubts.visits)
    if doubts.sure:
        lines = [f"the map is sure where every visit is: {head}"]
    else:
        lines = [f"the map is unsure where {n} visit{'s are' if n != 1 else ' is'}: {head}"]
    for d in doubts.visits[:most]:
        options = " or ".join(_answer_words(a) for a in d.answers)
        lines.append(f"visit {d.visit} (t = {d.stamp:.1f} s) is {options}")
    if n > most:
        lines.append(f"… and {n - most} more visits in doubt (ptm.json: doubts)")
    if doubts.listed_mass < 0.9:
        lines.append(
            f"(answers from the listed topologies, which hold {doubts.listed_mass:.2f} of the probability)"
        )
    return lines


def doubts_dict(doubts: Doubts) -> dict[str, object]:
    """:class:`Doubts` as JSON values (``ptm.json``'s ``extra.doubts``, the ``ptm_graph`` document's)."""
    return {
        "map_probability": doubts.map_probability,
        "runner_up_probability": doubts.runner_up_probability,
        "listed_mass": doubts.listed_mass,
        "visits": [
            {
                "visit": d.visit,
                "stamp": d.stamp,
                "answers": [{"place_of": a.place_of, "probability": a.probability} for a in d.answers],
            }
            for d in doubts.visits
        ],
    }
