"""Scoring a PTM against ground truth (CONTRACT.md, "Scoring against ground truth").

The thesis judges a PTM by the posterior mass it puts on the ground-truth topology (Ch. 5, Fig. 56–57).
Real runs rarely come with hand-labelled places, so we score the *pairs* of landmark visits instead,
using each visit's true position ``p_i`` (any frame: only distances matter):

.. math::
    \\text{same}(i, j) \\iff \\lVert p_i - p_j \\rVert < r_s, \\qquad
    \\text{different}(i, j) \\iff \\lVert p_i - p_j \\rVert > r_d, \\qquad r_s = 1.5, \\; r_d = 4.0 \\text{ m}

and pairs in between are *unscored* (ignored everywhere). A topology predicts ``i ~ j`` when both visits
carry the same label. Over the scored pairs this gives the counts ``TP`` (same, predicted same),
``FN`` (same, predicted different), ``FP`` (different, predicted same) and ``TN``, and

.. math::
    P = \\frac{TP}{TP + FP}, \\qquad R = \\frac{TP}{TP + FN}, \\qquad F_1 = \\frac{2\\,TP}{2\\,TP + FP + FN}.

Conventions for empty denominators (all tested): ``P = 1`` when nothing scored is predicted same (no
claim made, none wrong); ``R = 1`` when there is no true same pair (nothing to find); ``F1 = 1`` when
``TP + FP + FN = 0``. With these conventions ``F1`` is still the harmonic mean of ``P`` and ``R`` (e.g. no
true same pair but one predicted: ``P = 0, R = 1, F1 = 0``).

Posterior weighting. The listed topologies' masses ``p_k`` are renormalised over the listed mass,
``w_k = p_k / Σ_l p_l`` (a PTM truncated to its top topologies is scored as the posterior conditioned
on the listed set; the unlisted remainder is unknown and cannot be scored). The *headline* figures are
``P, R, F1`` of the expected counts ``E[TP] = Σ_k w_k TP_k`` (likewise FP, FN, TN). Since
``E[TP] = Σ_{same pairs} P(i ~ j)``, they score the posterior's pairwise co-location marginals, do not
hinge on the empty-denominator conventions of individual topologies, and do not change when mass is
split between near-identical topologies. The mass-weighted mean ``Σ_k w_k F1_k`` (the expected F1 of
one topology drawn from the PTM) is reported beside them.

Two masses are *not* renormalised (they are lower bounds of the true posterior mass): the consistent
mass, total probability of listed topologies with no scored pair wrong (``FP = FN = 0``), and, when
true place ids are given, the mass of the exactly-true topology (thesis Ch. 5's figure of merit).
The number of true places is the number of single-linkage clusters of the true positions at ``r_s``
(or the number of distinct true place ids when given).

Contradictory pairs. Pairs closer than ``r_s`` must share a place and sharing is transitive, so a
single-linkage cluster whose visits span more than ``r_d`` cannot be scored right by any topology: joined
it has a false merge, split it has a missed one. Its scored pairs are the *contradictory pairs*; the
*attainable consistent mass* is the mass of listed topologies with no wrong scored pair outside them
(equal to the consistent mass when there are none). Both are reported beside the headline figures, which
keep scoring every pair.

Visits without ground truth (e.g. before the ground-truth trajectory starts) have a NaN row in
``true_xy``: every pair involving them is unscored, they are left out of the true places, and the
exactly-true topology is then undefined. They are counted in ``n_visits_without_truth``.

Metric figure (not in the thesis, which scores topologies only): the *absolute trajectory error* of an
estimated path ``e_i`` against the true positions ``g_i`` at the same instants, after the rigid 2-D
motion ``(R_θ, t)`` that fits them best in least squares (Kabsch/Umeyama without scale):

.. math::
    \\text{ATE} = \\min_{\\theta, t} \\sqrt{\\tfrac{1}{n} \\textstyle\\sum_i
        \\lVert R_\\theta e_i + t - g_i \\rVert^2}, \\qquad
    t^* = \\bar g - R_\\theta \\bar e, \\qquad
    \\theta^* = \\operatorname{atan2}\\Bigl(\\sum_i \\tilde e_i \\times \\tilde g_i,\\;
        \\sum_i \\tilde e_i \\cdot \\tilde g_i\\Bigr)

with ``ẽ, g̃`` the centred points: for fixed θ the best ``t`` matches the centroids, and the remaining
cost is ``const − 2 (cos θ Σ ẽ·g̃ + sin θ Σ ẽ×g̃)``, largest at the ``θ*`` above (a rotation: the 2-D
Kabsch solution can never be a reflection).

Timeline (issue #25). The particle filter's PTM after each visit ``n`` (``ptm.inference["timeline"]``,
:class:`~ptm_ros.model.ptm.TimelineStep`: the posterior of thesis Algorithm 8 over the topologies of the first
``n`` visits) is judged against the true topology *of those visits*, the truth's labels cut to their
first ``n`` entries and made canonical (:func:`timeline_masses`): the mass moving onto or off it as the
visits arrive. A single-answer method whose decisions are final (the greedy baseline) goes wrong at the
first visit whose cut labels differ from the cut truth (:func:`first_wrong_visit`) and stays wrong.

Odometry fit (issue #25: is this ground truth this run's?). A ground truth of another run can overlap
this run's clock, and then scores it against the wrong trajectory. The visits' odometry positions
``o_i`` and the ground truth's positions ``g_i`` at the visits' stamps (its raw odometry when it has
one, CARMEN's ``x_raw …``, which is the same odometry; else its true poses) must then describe the same
motion, up to odometry drift. Drift grows with the distance travelled, so the fit is judged over short
stretches: for every visit ``i``, the window ``W_i = {i, …, j}`` is the shortest run of at least three
consecutive visits whose true path covers ``L`` metres,
``Σ_{k=i}^{j-1} ‖g_{k+1} - g_k‖ ≥ L`` (``L`` = :data:`ODOMETRY_FIT_WINDOW_M`); its *relative residual* is
the RMS distance left after the rigid alignment of the odometry onto the truth (the ATE above, over the
window alone) divided by the RMS spread of the true positions about their centroid,

.. math::
    r_i = \\frac{\\text{ATE}(o_{W_i}, g_{W_i})}{\\sqrt{\\tfrac{1}{|W_i|} \\sum_{k \\in W_i}
        \\lVert g_k - \\bar g_{W_i} \\rVert^2}} \\ge 0,

0 when the stretch moved exactly as the truth says, about 1 or more when the two are unrelated (the best
rigid motion then matches little more than the centroids). The statistic is the
:data:`ODOMETRY_FIT_QUANTILE` quantile of the ``r_i``, robust to a few stretches of bad odometry (wheel
slip) yet not blind to a wrong ground truth that is right on half the run (two routes that share their
straight corridors and differ at the corners).
A run with no window (fewer than three visits, or too little travel) cannot be judged. Above
:data:`ODOMETRY_FIT_LIMIT`, set between what a run's own ground truth and another run's give (measured
in ``README.md``, ``ptm-eval``), ``ptm-eval`` refuses the ground truth as another run's. ``ptm-run``
applies the same rule before any visit is known, to the bag's whole odometry at points one metre of
travel apart (:func:`path_samples`) instead of the visits
(:func:`ptm_ros.io.groundtruth.run_ground_truth_problem`).

Calibration (issue #23, "an honest posterior"). Over many runs ``r = 1..R`` with stated MAP probability
``p_r`` (the listed probability of the most probable topology) and outcome ``y_r = 1`` when the MAP
topology *is* the ground-truth topology (same partition of the visits as the true place ids), with
equal-width bins ``B_b = [b/M, (b+1)/M)`` (``M = 10`` by default, the last bin closed at 1):

.. math::
    \\text{ECE} = \\sum_b \\frac{|B_b|}{R} \\Bigl| \\bar y_{B_b} - \\bar p_{B_b} \\Bigr|, \\qquad
    \\text{Brier} = \\frac{1}{R} \\sum_r (p_r - y_r)^2 .

Even a perfectly calibrated mapper shows a positive ECE on finitely many runs; its *chance level* is
the mean ECE over redraws ``y_r^* \\sim \\text{Bernoulli}(p_r)`` of the outcomes on the same ``p_r``
(:func:`chance_calibration_errors`, with an explicit ``np.random.Generator``): an ECE well above it is
miscalibration, not bad luck. An *overconfident failure* is a run whose consistent mass (no scored pair
wrong) is below :data:`OVERCONFIDENT_MASS`: the posterior all but excludes the truth.

Pair calibration. On a real run the MAP topology is almost never exactly right (a true place is a
chain of visits, its borders a matter of metres), so the MAP calibration above needs simulated worlds
with exact places. The posterior's *pairwise* statement can be checked on any run with a trajectory:
each scored pair outside the contradictory ones (which no posterior can state right) has
``P(i ~ j) = Σ_k w_k [L_k(i) = L_k(j)]`` (the renormalised masses ``w_k`` of the listed topologies, as
for the expected counts) and an outcome, same or different place in truth. The
pairs are binned by that probability at :data:`PAIR_BIN_EDGES`: almost every pair sits in the end bins
(``P < 0.02``, ``P ≥ 0.98``), and the doubts in between are what the posterior's honesty is about. Per
bin the table gives the pairs, their mean stated probability and the share that is one place; the
*doubtful gap* is the ECE of the middle bins alone, ``Σ_{b mid} |Σ_{B_b} (y − p)| / Σ_{b mid} |B_b|``.
The confident errors are the different pairs stated ``P ≥ 0.98`` (confident false merges) and the same
pairs stated ``P < 0.02`` (confident misses). Bin sums add over runs (:class:`PairReliability`), so many
runs pool into one table; the pairs of one run are not independent outcomes (one merge decides many
pairs), so no Bernoulli chance level is given for them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial.distance import pdist

from ptm_ros.errors import ConfigError, DataError, ModelError
from ptm_ros.model.partitions import IntSequence, Labels, canonical, num_places
from ptm_ros.model.ptm import Ptm, TimelineStep

#: Schema tag of :meth:`Score.as_dict` (the JSON printed by ``ptm-eval``).
SCORE_SCHEMA = "ptm_ros.eval/1"

#: A run whose consistent mass is below this is an *overconfident failure* (module docstring).
OVERCONFIDENT_MASS = 0.05
#: Default number of equal-width probability bins of the calibration figures.
CALIBRATION_BINS = 10

#: Bin edges of the pair calibration (module docstring): the end bins hold the confident statements.
PAIR_BIN_EDGES = (0.0, 0.02, 0.1, 0.3, 0.5, 0.7, 0.9, 0.98, 1.0)

#: Upper bound on the number of booleans held at once when comparing topologies pairwise.
_CHUNK_ELEMENTS = 1 << 22


@dataclass(frozen=True)
class EvalConfig:
    """Thresholds of the pairwise ground-truth scoring.

    Attributes:
        same_radius: visits closer than this (m) are the same place.
        different_radius: visits farther than this (m) are different places; in between: unscored.
    """

    same_radius: float = 1.5
    different_radius: float = 4.0

    def __post_init__(self) -> None:
        values = (self.same_radius, self.different_radius)
        if not all(math.isfinite(v) for v in values):
            msg = f"EvalConfig values must be finite, got {values}"
            raise ConfigError(msg)
        if self.same_radius <= 0.0:
            msg = f"same_radius must be > 0, got {self.same_radius}"
            raise ConfigError(msg)
        if self.different_radius < self.same_radius:
            msg = f"different_radius ({self.different_radius}) must be >= same_radius ({self.same_radius})"
            raise ConfigError(msg)


@dataclass(frozen=True)
class PairCounts:
    """Confusion counts of "same place" over the scored pairs (floats: expectations allowed)."""

    tp: float
    fp: float
    fn: float
    tn: float

    @property
    def precision(self) -> float:
        """``TP / (TP + FP)``; 1 when nothing scored is predicted same."""
        den = self.tp + self.fp
        return 1.0 if den <= 0.0 else self.tp / den

    @property
    def recall(self) -> float:
        """``TP / (TP + FN)``; 1 when there is no true same pair."""
        den = self.tp + self.fn
        return 1.0 if den <= 0.0 else self.tp / den

    @property
    def f1(self) -> float:
        """``2 TP / (2 TP + FP + FN)`` (harmonic mean of P and R); 1 when ``TP + FP + FN = 0``."""
        den = 2.0 * self.tp + self.fp + self.fn
        return 1.0 if den <= 0.0 else 2.0 * self.tp / den

    @property
    def errors(self) -> float:
        """Number of scored pairs the topology gets wrong (``FP + FN``)."""
        return self.fp + self.fn


@dataclass(frozen=True)
class TopologyScore:
    """The score of one listed topology (rank 0 = the MAP topology)."""

    rank: int
    probability: float
    num_places: int
    counts: PairCounts

    @property
    def consistent(self) -> bool:
        """No scored pair wrong."""
        return self.counts.errors == 0


@dataclass(frozen=True)
class Score:
    """A PTM scored against ground truth; see the module docstring for every definition."""

    n_visits: int
    n_visits_without_truth: int
    n_true_places: int
    true_places_from: str  # "single-linkage" or "place-ids"
    n_scored_pairs: int
    n_same_pairs: int
    n_different_pairs: int
    listed_mass: float
    map: TopologyScore
    expected: PairCounts
    mean_f1: float
    consistent_mass: float
    true_topology_mass: float | None
    topologies: tuple[TopologyScore, ...] = field(repr=False)
    n_contradictory_pairs: int = 0
    attainable_consistent_mass: float = 0.0
    config: EvalConfig = field(default_factory=EvalConfig)
    true_labels: Labels | None = field(default=None, repr=False)  # the true topology, with place ids
    pairs: PairReliability | None = field(default=None, repr=False)  # the pair calibration

    @property
    def n_pairs(self) -> int:
        """All visit pairs ``N (N - 1) / 2``, scored or not."""
        return self.n_visits * (self.n_visits - 1) // 2

    def as_dict(self, *, per_topology: bool = True) -> dict[str, Any]:
        """Stable flat JSON form (schema :data:`SCORE_SCHEMA`), documented in ``ptm_ros.tools.evaluate``."""
        m, e = self.map.counts, self.expected
        doc: dict[str, Any] = {
            "schema": SCORE_SCHEMA,
            "same_radius_m": self.config.same_radius,
            "different_radius_m": self.config.different_radius,
            "n_visits": self.n_visits,
            "n_visits_without_truth": self.n_visits_without_truth,
            "n_topologies": len(self.topologies),
            "listed_mass": self.listed_mass,
            "n_true_places": self.n_true_places,
            "true_places_from": self.true_places_from,
            "n_pairs": self.n_pairs,
            "n_scored_pairs": self.n_scored_pairs,
            "n_same_pairs": self.n_same_pairs,
            "n_different_pairs": self.n_different_pairs,
            "map_probability": self.map.probability,
            "map_num_places": self.map.num_places,
            "map_tp": int(m.tp),
            "map_fp": int(m.fp),
            "map_fn": int(m.fn),
            "map_tn": int(m.tn),
            "map_precision": m.precision,
            "map_recall": m.recall,
            "map_f1": m.f1,
            "posterior_tp": e.tp,
            "posterior_fp": e.fp,
            "posterior_fn": e.fn,
            "posterior_tn": e.tn,
            "posterior_precision": e.precision,
            "posterior_recall": e.recall,
            "posterior_f1": e.f1,
            "posterior_mean_f1": self.mean_f1,
            "consistent_mass": self.consistent_mass,
            "true_topology_mass": self.true_topology_mass,
            "n_contradictory_pairs": self.n_contradictory_pairs,
            "attainable_consistent_mass": self.attainable_consistent_mass,
        }
        if self.pairs is not None:
            doc["pair_calibration"] = self.pairs.as_dict()
        if per_topology:
            doc["topologies"] = [
                {
                    "rank": t.rank,
                    "probability": t.probability,
                    "num_places": t.num_places,
                    "tp": int(t.counts.tp),
                    "fp": int(t.counts.fp),
                    "fn": int(t.counts.fn),
                    "tn": int(t.counts.tn),
                    "precision": t.counts.precision,
                    "recall": t.counts.recall,
                    "f1": t.counts.f1,
                    "consistent": t.consistent,
                }
                for t in self.topologies
            ]
        return doc


def _positions(true_xy: ArrayLike, n: int) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The ``(n, 2)`` positions and the mask of visits with ground truth (rows not all-NaN)."""
    xy = np.asarray(true_xy, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] != n:
        msg = f"true positions must have shape ({n}, 2) (one per landmark visit), got {xy.shape}"
        raise ModelError(msg)
    known = ~np.all(np.isnan(xy), axis=1)
    bad = known & ~np.all(np.isfinite(xy), axis=1)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        msg = f"true position of visit {k} is not finite: {xy[k].tolist()} (a whole NaN row = no truth)"
        raise ModelError(msg)
    return xy, known


def pair_truth(
    true_xy: ArrayLike, config: EvalConfig | None = None
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.bool_]]:
    """The scored pairs ``(i, j, same)`` with ``i < j`` (row-major order); unscored pairs left out.

    Pairs with a NaN position (a visit without ground truth) compare false both ways: unscored.
    """
    config = config or EvalConfig()
    xy = np.asarray(true_xy, dtype=float)
    n = xy.shape[0]
    d = pdist(xy) if n >= 2 else np.zeros(0)
    i, j = np.triu_indices(n, k=1)  # same order as pdist's condensed form
    same = d < config.same_radius
    scored = same | (d > config.different_radius)
    return i[scored], j[scored], same[scored]


def single_linkage_places(true_xy: ArrayLike, radius: float) -> NDArray[np.intp]:
    """Canonical labels of the single-linkage clusters: visits chained by gaps ``< radius`` share a place.

    (A visit with a NaN position is a cluster of its own.)
    """
    xy = np.asarray(true_xy, dtype=float)
    n = xy.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.intp)
    i, j = np.triu_indices(n, k=1)
    close = pdist(xy) < radius if n >= 2 else np.zeros(0, dtype=bool)
    graph = coo_matrix((np.ones(int(close.sum())), (i[close], j[close])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return np.asarray(canonical(labels.tolist()), dtype=np.intp)


def contradictory_pairs(
    true_xy: ArrayLike, i: NDArray[np.intp], j: NDArray[np.intp], config: EvalConfig | None = None
) -> NDArray[np.bool_]:
    """Which scored pairs ``(i, j)`` lie inside one single-linkage cluster (gaps ``< r_s``) spanning more
    than ``r_d``: no topology can score them all right (module docstring)."""
    config = config or EvalConfig()
    xy = np.asarray(true_xy, dtype=float)
    places = single_linkage_places(xy, config.same_radius)
    bad = np.zeros(int(np.max(places, initial=-1)) + 1, dtype=bool)
    for c in range(len(bad)):
        members = xy[places == c]
        if len(members) > 1 and np.nanmax(pdist(members)) > config.different_radius:
            bad[c] = True
    return (places[i] == places[j]) & bad[places[i]]


def topology_counts(
    labels: NDArray[np.integer], i: NDArray[np.intp], j: NDArray[np.intp], same: NDArray[np.bool_]
) -> NDArray[np.int64]:
    """``(K, 4)`` counts ``TP, FP, FN, TN`` of ``K`` label rows ``(K, N)`` over the scored pairs."""
    labels = np.atleast_2d(labels)
    out = np.zeros((labels.shape[0], 4), dtype=np.int64)
    n_same = int(same.sum())
    n_diff = same.size - n_same
    step = max(1, _CHUNK_ELEMENTS // max(1, same.size))
    for start in range(0, labels.shape[0], step):
        rows = labels[start : start + step]
        pred = rows[:, i] == rows[:, j]
        tp = np.count_nonzero(pred & same, axis=1)
        fp = np.count_nonzero(pred & ~same, axis=1)
        out[start : start + step] = np.stack([tp, fp, n_same - tp, n_diff - fp], axis=1)
    return out


def pair_probabilities(
    labels: NDArray[np.integer], weights: ArrayLike, i: NDArray[np.intp], j: NDArray[np.intp]
) -> NDArray[np.float64]:
    """``P(i ~ j)`` of each pair ``(i[m], j[m])``: the summed ``weights`` ``(K,)`` of the label rows
    ``(K, N)`` that put both visits in one place (weights summing to 1 give the posterior's marginal)."""
    labels = np.atleast_2d(labels)
    w = np.asarray(weights, dtype=float)
    if w.shape != (labels.shape[0],):
        msg = f"one weight per topology: {w.shape} weights for {labels.shape[0]} topologies"
        raise ModelError(msg)
    out = np.zeros(len(i))
    step = max(1, _CHUNK_ELEMENTS // max(1, len(i)))
    for start in range(0, labels.shape[0], step):
        rows = labels[start : start + step]
        out += w[start : start + step] @ (rows[:, i] == rows[:, j])
    return np.clip(out, 0.0, 1.0)  # rounding of weights summing to 1


@dataclass(frozen=True)
class PairReliability:
    """The pair calibration of one or more runs (module docstring): per bin of ``edges``, the scored
    pairs, the sum of their stated ``P(i ~ j)`` and how many are one place in truth. ``a + b`` pools two.
    """

    count: tuple[int, ...]
    probability_sum: tuple[float, ...]
    same: tuple[int, ...]
    edges: tuple[float, ...] = PAIR_BIN_EDGES

    def __post_init__(self) -> None:
        n = len(self.edges) - 1
        if n < 3 or any(b <= a for a, b in pairwise(self.edges)):
            msg = f"pair bin edges must increase and make at least 3 bins, got {self.edges}"
            raise ConfigError(msg)
        if not (len(self.count) == len(self.probability_sum) == len(self.same) == n):
            msg = f"pair calibration needs {n} bins of counts, probability sums and same pairs"
            raise ModelError(msg)
        if any(s < 0 or s > c for s, c in zip(self.same, self.count, strict=True)):
            msg = f"same pairs {self.same} must lie between 0 and the pairs of their bin {self.count}"
            raise ModelError(msg)

    @classmethod
    def of(
        cls, probabilities: ArrayLike, same: ArrayLike, edges: tuple[float, ...] = PAIR_BIN_EDGES
    ) -> PairReliability:
        """The table of pairs stated ``probabilities`` whose truth is ``same`` (booleans)."""
        p = np.asarray(probabilities, dtype=float)
        y = np.asarray(same)
        n_bins = len(edges) - 1
        if p.size:
            p, y = _calibration_inputs(p, y)
        b = np.clip(np.searchsorted(np.asarray(edges), p, side="right") - 1, 0, n_bins - 1)
        return cls(
            count=tuple(int(v) for v in np.bincount(b, minlength=n_bins)),
            probability_sum=tuple(float(v) for v in np.bincount(b, weights=p, minlength=n_bins)),
            same=tuple(round(v) for v in np.bincount(b, weights=y.astype(float), minlength=n_bins)),
            edges=tuple(edges),
        )

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> PairReliability:
        """The table of :meth:`as_dict` (a record of ``ptm-eval --calibration``)."""
        bins = doc["bins"]
        edges = (*(float(b["lo"]) for b in bins), float(bins[-1]["hi"]))
        return cls(
            count=tuple(int(b["count"]) for b in bins),
            probability_sum=tuple(float(b["probability_sum"]) for b in bins),
            same=tuple(int(b["same"]) for b in bins),
            edges=edges,
        )

    def __add__(self, other: PairReliability) -> PairReliability:
        if other.edges != self.edges:
            msg = f"cannot pool pair tables with different bins: {self.edges} and {other.edges}"
            raise ModelError(msg)
        return PairReliability(
            count=tuple(a + b for a, b in zip(self.count, other.count, strict=True)),
            probability_sum=tuple(
                a + b for a, b in zip(self.probability_sum, other.probability_sum, strict=True)
            ),
            same=tuple(a + b for a, b in zip(self.same, other.same, strict=True)),
            edges=self.edges,
        )

    @property
    def bins(self) -> tuple[ReliabilityBin, ...]:
        """Per bin: the pairs, their mean stated probability and the share one place (NaN when empty)."""
        nan = float("nan")
        return tuple(
            ReliabilityBin(lo, hi, c, ps / c if c else nan, s / c if c else nan)
            for (lo, hi), c, ps, s in zip(
                pairwise(self.edges), self.count, self.probability_sum, self.same, strict=True
            )
        )

    @property
    def confident_false_merges(self) -> int:
        """Different pairs stated at least ``edges[-2]`` (0.98) one place."""
        return self.count[-1] - self.same[-1]

    @property
    def confident_misses(self) -> int:
        """Same pairs stated below ``edges[1]`` (0.02) one place."""
        return self.same[0]

    @property
    def doubtful(self) -> int:
        """Pairs in the middle bins."""
        return sum(self.count[1:-1])

    @property
    def doubtful_gap(self) -> float:
        """The ECE of the middle bins alone (NaN without doubtful pairs)."""
        if not self.doubtful:
            return float("nan")
        gaps = (abs(s - ps) for s, ps in zip(self.same[1:-1], self.probability_sum[1:-1], strict=True))
        return float(sum(gaps) / self.doubtful)

    def summary(self) -> str:
        """One line: the doubtful pairs and their gap, the confident errors."""
        lo, hi = self.edges[1], self.edges[-2]
        gap = "" if not self.doubtful else f", gap {self.doubtful_gap:.2f}"
        return (
            f"pair calibration: {self.doubtful} of {sum(self.count)} pairs stated {lo:g}-{hi:g}{gap}; "
            f"confident false merges (different, stated >= {hi:g}) {self.confident_false_merges}, "
            f"confident misses (same, stated < {lo:g}) {self.confident_misses}"
        )

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON values: the summary figures and the bins (empty bins' means None)."""

        def num(v: float) -> float | None:
            return None if math.isnan(v) else v

        return {
            "pairs": sum(self.count),
            "doubtful_pairs": self.doubtful,
            "doubtful_gap": num(self.doubtful_gap),
            "confident_false_merges": self.confident_false_merges,
            "confident_misses": self.confident_misses,
            "bins": [
                {
                    "lo": b.lo,
                    "hi": b.hi,
                    "count": b.count,
                    "probability_sum": ps,
                    "same": s,
                    "mean_probability": num(b.mean_probability),
                    "share_same": num(b.accuracy),
                }
                for b, ps, s in zip(self.bins, self.probability_sum, self.same, strict=True)
            ],
        }


def score_ptm(
    ptm: Ptm,
    true_xy: ArrayLike,
    *,
    true_places: Sequence[int] | None = None,
    config: EvalConfig | None = None,
) -> Score:
    """Score ``ptm`` given each visit's true position ``true_xy`` ``(N, 2)`` (any frame).

    ``true_places`` (optional, ``(N,)`` ids of the physical place of each visit) sets the number of true
    places and enables the mass of the exactly-true topology. Pairs are always classified by distance.
    Raises :class:`ModelError` on mis-shaped inputs and :class:`DataError` on a PTM without mass.
    """
    config = config or EvalConfig()
    n = len(ptm.landmarks)
    xy, known = _positions(true_xy, n)
    if not ptm.topologies:
        msg = "the PTM holds no topology to score"
        raise DataError(msg)
    probs = np.array([t.probability for t in ptm.topologies], dtype=float)
    listed = float(probs.sum())
    if not listed > 0.0:
        msg = "the PTM's listed topologies carry zero total probability"
        raise DataError(msg)
    for k, t in enumerate(ptm.topologies):
        if len(t.labels) != n:
            msg = f"topology {k} labels {len(t.labels)} visits, the PTM has {n} landmarks"
            raise ModelError(msg)

    i, j, same = pair_truth(xy, config)
    labels = np.array([t.labels for t in ptm.topologies], dtype=np.intp).reshape(len(probs), n)
    counts = topology_counts(labels, i, j, same)
    scores = tuple(
        TopologyScore(
            rank=k,
            probability=float(probs[k]),
            num_places=num_places(t.labels),
            counts=PairCounts(*(int(c) for c in counts[k])),
        )
        for k, t in enumerate(ptm.topologies)
    )
    w = probs / listed
    expected = PairCounts(*(float(v) for v in w @ counts))
    mean_f1 = float(sum(wk * s.counts.f1 for wk, s in zip(w, scores, strict=True)))
    consistent_mass = float(sum(s.probability for s in scores if s.consistent))
    contra = contradictory_pairs(xy, i, j, config)
    keep = ~contra
    attainable = topology_counts(labels, i[keep], j[keep], same[keep])
    pairs = PairReliability.of(pair_probabilities(labels, w, i[keep], j[keep]), same[keep])
    attainable_mass = float(probs[(attainable[:, 1] + attainable[:, 2]) == 0].sum())

    true_mass: float | None = None
    truth: Labels | None = None
    if true_places is None:
        n_true = int(np.max(single_linkage_places(xy[known], config.same_radius), initial=-1)) + 1
        source = "single-linkage"
    else:
        if len(true_places) != n:
            msg = f"true place ids must have one entry per visit ({n}), got {len(true_places)}"
            raise ModelError(msg)
        truth = canonical([int(v) for v in true_places])
        n_true = num_places(truth)
        source = "place-ids"
        true_mass = float(sum(t.probability for t in ptm.topologies if canonical(t.labels) == truth))

    return Score(
        n_visits=n,
        n_visits_without_truth=int(n - known.sum()),
        n_true_places=n_true,
        true_places_from=source,
        n_scored_pairs=int(same.size),
        n_same_pairs=int(same.sum()),
        n_different_pairs=int(same.size - same.sum()),
        listed_mass=listed,
        map=scores[0],
        expected=expected,
        mean_f1=mean_f1,
        consistent_mass=consistent_mass,
        true_topology_mass=true_mass,
        topologies=scores,
        config=config,
        n_contradictory_pairs=int(contra.sum()),
        attainable_consistent_mass=attainable_mass,
        true_labels=truth,
        pairs=pairs,
    )


def cut(labels: IntSequence, visits: int) -> Labels:
    """The topology of the first ``visits`` visits under ``labels`` (canonical)."""
    return canonical([int(v) for v in labels[:visits]])


def timeline_masses(steps: Sequence[TimelineStep], labels: IntSequence) -> tuple[float | None, ...]:
    """After each visit, the mass the PTM then listed on ``labels`` cut to the visits so far (the truth's,
    a baseline's); None when it was not among the listed topologies (then it held at most
    :func:`unlisted_bound`). Raises :class:`ModelError` when ``labels`` covers fewer visits."""
    out: list[float | None] = []
    for st in steps:
        if len(labels) < st.visits:
            msg = f"labels of {len(labels)} visits cannot be cut to {st.visits}"
            raise ModelError(msg)
        want = cut(labels, st.visits)
        out.append(next((p for lab, p in st.topologies if lab == want), None))
    return tuple(out)


def unlisted_bound(step: TimelineStep) -> float:
    """The most mass a topology not listed in ``step`` can hold: the smallest listed mass, and no more
    than the mass left over by the listed ones."""
    listed = [p for _, p in step.topologies]
    if not listed:
        return 1.0
    return max(0.0, min(*listed, 1.0 - sum(listed)))


def first_wrong_visit(labels: IntSequence, true_labels: IntSequence) -> int | None:
    """The first visit ``k`` at which ``labels`` contradict the truth of the visits so far (the cut
    labels differ from the cut truth, :func:`cut`); None when they are the truth."""
    if len(labels) != len(true_labels):
        msg = f"labels of {len(labels)} visits against a truth of {len(true_labels)}"
        raise ModelError(msg)
    for k in range(len(labels)):
        if cut(labels, k + 1) != cut(true_labels, k + 1):
            return k
    return None


def place_ids_from_positions(
    true_xy: ArrayLike, place_xy: ArrayLike, radius: float
) -> NDArray[np.intp] | None:
    """True place id of each visit: the index of the nearest known place, if within ``radius`` (m).

    Returns None, the exactly-true topology being undefined, when a visit has no ground truth (NaN row),
    no place lies within ``radius`` of some visit, or there are no places.
    """
    xy = np.asarray(true_xy, dtype=float).reshape(-1, 2)
    places = np.asarray(place_xy, dtype=float).reshape(-1, 2)
    if places.shape[0] == 0 or not np.all(np.isfinite(xy)):
        return None
    if xy.shape[0] == 0:
        return np.zeros(0, dtype=np.intp)
    d = np.hypot(xy[:, None, 0] - places[None, :, 0], xy[:, None, 1] - places[None, :, 1])
    nearest = np.argmin(d, axis=1)
    if np.any(d[np.arange(len(xy)), nearest] > radius):
        return None
    return nearest.astype(np.intp)


def _xy(points: ArrayLike, name: str) -> NDArray[np.float64]:
    xy = np.asarray(points, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2:
        msg = f"{name} must be (n, 2) positions, got shape {xy.shape}"
        raise ModelError(msg)
    if not np.all(np.isfinite(xy)):
        msg = f"{name} must be finite"
        raise ModelError(msg)
    return xy


def rigid_alignment(est_xy: ArrayLike, true_xy: ArrayLike) -> tuple[float, NDArray[np.float64]]:
    """``(theta, t)`` of the rigid 2-D motion ``x ↦ R_theta x + t`` that maps the estimated positions
    ``est_xy (n, 2)`` onto ``true_xy (n, 2)`` with the least sum of squared distances (closed form in
    the module docstring). Raises :class:`ModelError` on mismatched, empty or non-finite input."""
    e = _xy(est_xy, "est_xy")
    g = _xy(true_xy, "true_xy")
    if len(e) != len(g) or len(e) == 0:
        msg = f"need the same non-zero number of estimated and true positions, got {len(e)} and {len(g)}"
        raise ModelError(msg)
    ce, cg = e.mean(axis=0), g.mean(axis=0)
    de, dg = e - ce, g - cg
    dot = float(np.sum(de * dg))
    cross = float(np.sum(de[:, 0] * dg[:, 1] - de[:, 1] * dg[:, 0]))
    theta = math.atan2(cross, dot)
    c, s = math.cos(theta), math.sin(theta)
    rot = np.array([[c, -s], [s, c]])
    return theta, cg - rot @ ce


def absolute_trajectory_error(est_xy: ArrayLike, true_xy: ArrayLike) -> float:
    """RMSE (m) of ``est_xy (n, 2)`` against ``true_xy (n, 2)`` (row ``i`` = the same instant) after the
    least-squares rigid alignment :func:`rigid_alignment` (module docstring: ATE). 0 for two paths that
    differ by a rigid motion; a single pair of points always aligns exactly."""
    theta, t = rigid_alignment(est_xy, true_xy)
    e = np.asarray(est_xy, dtype=float)
    g = np.asarray(true_xy, dtype=float)
    c, s = math.cos(theta), math.sin(theta)
    moved = e @ np.array([[c, s], [-s, c]]) + t
    return float(np.sqrt(np.mean(np.sum((moved - g) ** 2, axis=1))))


# --------------------------------------------------------------------------------------------------
# Odometry fit (module docstring: "Odometry fit")

#: Metres of true path each window of the odometry fit covers (module docstring).
ODOMETRY_FIT_WINDOW_M = 8.0
#: The quantile of the windows' relative residuals that is the odometry fit.
ODOMETRY_FIT_QUANTILE = 0.8
#: An odometry fit above this is another run's ground truth (measured: README.md, `ptm-eval`).
ODOMETRY_FIT_LIMIT = 0.28


@dataclass(frozen=True)
class OdometryFit:
    """How well the visits' odometry fits a ground truth (module docstring: "Odometry fit").

    ``statistic`` is the ``quantile`` of the ``windows`` relative residuals (None: no window, not
    judged); ``visits`` the visits with a ground-truth position; ``window_m``, ``limit`` the settings.
    """

    statistic: float | None
    windows: int
    visits: int
    window_m: float = ODOMETRY_FIT_WINDOW_M
    quantile: float = ODOMETRY_FIT_QUANTILE
    limit: float = ODOMETRY_FIT_LIMIT

    @property
    def fits(self) -> bool:
        """The odometry fits (or cannot be judged): at most ``limit``."""
        return self.statistic is None or self.statistic <= self.limit

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON values."""
        return {k: getattr(self, k) for k in self.__dataclass_fields__} | {"fits": self.fits}


def fit_windows(true_xy: ArrayLike, window_m: float = ODOMETRY_FIT_WINDOW_M) -> list[tuple[int, int]]:
    """The windows ``(i, j)`` (visits ``i..j`` inclusive) of the odometry fit over the true positions
    ``true_xy (n, 2)``: for each ``i`` the smallest ``j >= i + 2`` whose true path from ``i`` covers
    ``window_m`` metres; none for an ``i`` whose path to the last visit is shorter."""
    g = _xy(true_xy, "true_xy") if len(np.asarray(true_xy)) else np.zeros((0, 2))
    if not (math.isfinite(window_m) and window_m > 0.0):
        msg = f"window_m must be finite and > 0, got {window_m}"
        raise ConfigError(msg)
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(g, axis=0).T))]) if len(g) else np.zeros(0)
    ends = np.searchsorted(travel, travel + window_m, side="left")
    return [(i, max(int(j), i + 2)) for i, j in enumerate(ends) if max(int(j), i + 2) < len(g)]


def window_residuals(
    odom_xy: ArrayLike, true_xy: ArrayLike, window_m: float = ODOMETRY_FIT_WINDOW_M
) -> NDArray[np.float64]:
    """The relative residual ``r_i`` (module docstring) of every window of :func:`fit_windows`: the ATE of
    the window's odometry positions ``odom_xy (n, 2)`` against ``true_xy (n, 2)`` over the true positions'
    RMS spread. A window whose true positions all coincide (no spread) has residual 0 when the odometry's
    do too, else 1."""
    o = _xy(odom_xy, "odom_xy") if len(np.asarray(odom_xy)) else np.zeros((0, 2))
    g = _xy(true_xy, "true_xy") if len(np.asarray(true_xy)) else np.zeros((0, 2))
    if len(o) != len(g):
        msg = f"one odometry position per true position: {len(o)} and {len(g)}"
        raise ModelError(msg)
    out = []
    for i, j in fit_windows(g, window_m):
        a, b = o[i : j + 1], g[i : j + 1]
        spread = math.sqrt(float(np.mean(np.sum((b - b.mean(axis=0)) ** 2, axis=1))))
        ate = absolute_trajectory_error(a, b)
        out.append(ate / spread if spread > 0.0 else float(ate > 0.0))
    return np.asarray(out, dtype=float)


def odometry_fit(
    odom_xy: ArrayLike,
    true_xy: ArrayLike,
    *,
    window_m: float = ODOMETRY_FIT_WINDOW_M,
    quantile: float = ODOMETRY_FIT_QUANTILE,
    limit: float = ODOMETRY_FIT_LIMIT,
) -> OdometryFit:
    """How well the visits' odometry positions ``odom_xy (n, 2)`` fit the ground truth's ``true_xy (n, 2)``
    at the same stamps (rows in visit order; a NaN row of ``true_xy``, a visit without ground truth, is
    left out): the ``quantile`` of :func:`window_residuals` (module docstring: "Odometry fit")."""
    if not 0.0 <= quantile <= 1.0:
        msg = f"quantile must be in [0, 1], got {quantile}"
        raise ConfigError(msg)
    o = np.asarray(odom_xy, dtype=float).reshape(-1, 2)
    g = np.asarray(true_xy, dtype=float).reshape(-1, 2)
    if len(o) != len(g):
        msg = f"one odometry position per true position: {len(o)} and {len(g)}"
        raise ModelError(msg)
    known = ~np.all(np.isnan(g), axis=1)
    r = window_residuals(o[known], g[known], window_m)
    statistic = float(np.quantile(r, quantile)) if r.size else None
    return OdometryFit(statistic, int(r.size), int(known.sum()), window_m, quantile, limit)


def path_samples(xy: ArrayLike, spacing: float) -> NDArray[np.intp]:
    """Indices of the points of a path ``xy (n, 2)`` one every ``spacing`` metres of its travel (the first
    point, then the first to reach each further multiple of ``spacing`` along the path): the points at
    which a whole odometry stream is judged by :func:`odometry_fit` (``ptm-run``, before any visit is
    known), so that neither its rate nor a robot standing still weighs on the fit."""
    p = np.asarray(xy, dtype=float).reshape(-1, 2)
    if not (math.isfinite(spacing) and spacing > 0.0):
        msg = f"spacing must be finite and > 0, got {spacing}"
        raise ConfigError(msg)
    if not len(p):
        return np.zeros(0, dtype=np.intp)
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))])
    marks = spacing * np.arange(int(travel[-1] // spacing) + 1)
    return np.unique(np.minimum(np.searchsorted(travel, marks, side="left"), len(p) - 1)).astype(np.intp)


# --------------------------------------------------------------------------------------------------
# Calibration over many runs (module docstring: "Calibration")


def map_errors_against_truth(labels: IntSequence, true_places: IntSequence) -> tuple[int, int]:
    """``(false_merges, missed_merges)`` of one topology against true place ids: visit pairs it puts in
    one place that are different places, and pairs of one place it keeps apart. ``(0, 0)`` exactly when
    the topology is the true one."""
    lab = np.asarray(labels, dtype=np.intp)
    truth = np.asarray(true_places, dtype=np.intp)
    if lab.shape != truth.shape or lab.ndim != 1:
        msg = f"labels {lab.shape} and true place ids {truth.shape} must be equally long 1-D sequences"
        raise ModelError(msg)
    i, j = np.triu_indices(lab.size, k=1)
    pred, same = lab[i] == lab[j], truth[i] == truth[j]
    return int(np.count_nonzero(pred & ~same)), int(np.count_nonzero(~pred & same))


def _calibration_inputs(
    probabilities: ArrayLike, correct: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    p = np.asarray(probabilities, dtype=float)
    if p.ndim != 1 or p.size == 0:
        msg = f"need a non-empty 1-D array of probabilities, got shape {p.shape}"
        raise ModelError(msg)
    if not np.all(np.isfinite(p) & (p >= 0.0) & (p <= 1.0)):
        msg = "probabilities must be finite and in [0, 1]"
        raise ModelError(msg)
    if correct is None:
        return p, np.zeros(0)
    y = np.asarray(correct)
    if y.shape != p.shape:
        msg = f"one outcome per probability: {y.shape} outcomes for {p.shape} probabilities"
        raise ModelError(msg)
    if not np.all((y == 0) | (y == 1)):
        msg = "outcomes must be booleans (or 0/1)"
        raise ModelError(msg)
    return p, y.astype(float)


def _bin_index(p: NDArray[np.float64], n_bins: int) -> NDArray[np.intp]:
    if n_bins < 1:
        msg = f"n_bins must be >= 1, got {n_bins}"
        raise ConfigError(msg)
    return np.minimum(np.floor(p * n_bins).astype(np.intp), n_bins - 1)


@dataclass(frozen=True)
class ReliabilityBin:
    """One bin ``[lo, hi)`` of a reliability diagram: its runs, their mean stated probability and the
    fraction right (both NaN for an empty bin)."""

    lo: float
    hi: float
    count: int
    mean_probability: float
    accuracy: float


def reliability_bins(
    probabilities: ArrayLike, correct: ArrayLike, n_bins: int = CALIBRATION_BINS
) -> tuple[ReliabilityBin, ...]:
    """The ``n_bins`` equal-width bins of stated probability over [0, 1] (the last one closed at 1)."""
    p, y = _calibration_inputs(probabilities, correct)
    b = _bin_index(p, n_bins)
    count = np.bincount(b, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_p = np.bincount(b, weights=p, minlength=n_bins) / count
        acc = np.bincount(b, weights=y, minlength=n_bins) / count
    return tuple(
        ReliabilityBin(k / n_bins, (k + 1) / n_bins, int(count[k]), float(mean_p[k]), float(acc[k]))
        for k in range(n_bins)
    )


def expected_calibration_error(
    probabilities: ArrayLike, correct: ArrayLike, n_bins: int = CALIBRATION_BINS
) -> float:
    """ECE: the run-weighted mean over equal-width bins of |fraction right - mean stated probability|."""
    p, y = _calibration_inputs(probabilities, correct)
    return float(_ece_rows(p, y[None, :], n_bins)[0])


def _ece_rows(p: NDArray[np.float64], y: NDArray[np.float64], n_bins: int) -> NDArray[np.float64]:
    """ECE of each outcome row ``y (K, R)`` against the same probabilities ``p (R,)``."""
    b = _bin_index(p, n_bins)
    onehot = np.zeros((p.size, n_bins))
    onehot[np.arange(p.size), b] = 1.0
    gap = y @ onehot - p @ onehot  # (K, bins): Σ_bin (y - p), so |gap| / R = weight x |mean gap|
    return np.abs(gap).sum(axis=1) / p.size


def brier_score(probabilities: ArrayLike, correct: ArrayLike) -> float:
    """Mean squared difference between stated probability and outcome (0 best, 1 worst)."""
    p, y = _calibration_inputs(probabilities, correct)
    return float(np.mean((p - y) ** 2))


def chance_calibration_errors(
    probabilities: ArrayLike,
    rng: np.random.Generator,
    *,
    n_bins: int = CALIBRATION_BINS,
    redraws: int = 2000,
) -> NDArray[np.float64]:
    """ECEs ``(redraws,)`` of a perfectly calibrated mapper on the same runs: each outcome redrawn as
    ``Bernoulli(p_r)`` (``rng`` draws them), the ECE computed per redraw. Their mean is the chance level."""
    p, _ = _calibration_inputs(probabilities)
    if redraws < 1:
        msg = f"redraws must be >= 1, got {redraws}"
        raise ConfigError(msg)
    out = np.empty(redraws)
    step = max(1, _CHUNK_ELEMENTS // p.size)
    for lo in range(0, redraws, step):
        hi = min(redraws, lo + step)
        y = (rng.random((hi - lo, p.size)) < p).astype(float)
        out[lo:hi] = _ece_rows(p, y, n_bins)
    return out


@dataclass(frozen=True)
class CalibrationSummary:
    """Calibration of the MAP probability over ``n_runs`` runs (module docstring: "Calibration").

    ``chance_ece`` is the mean and ``chance_ece_p95`` the 95th percentile of a calibrated mapper's ECE on
    the same probabilities; ``overconfident_failures`` counts runs with consistent mass below
    :data:`OVERCONFIDENT_MASS` (None when no consistent masses were given).
    """

    n_runs: int
    n_bins: int
    ece: float
    chance_ece: float
    chance_ece_p95: float
    brier: float
    map_right_rate: float
    mean_map_probability: float
    overconfident_failures: int | None
    mean_true_topology_mass: float | None
    bins: tuple[ReliabilityBin, ...] = field(repr=False)

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON values (NaN bin means become None)."""

        def num(v: float) -> float | None:
            return None if math.isnan(v) else v

        doc = {k: getattr(self, k) for k in self.__dataclass_fields__ if k != "bins"}
        doc["bins"] = [
            {
                "lo": b.lo,
                "hi": b.hi,
                "count": b.count,
                "mean_probability": num(b.mean_probability),
                "accuracy": num(b.accuracy),
            }
            for b in self.bins
        ]
        return doc


def _per_run(values: ArrayLike, p: NDArray[np.float64], what: str) -> NDArray[np.float64]:
    """``values`` as floats, one per run of ``p`` (:class:`ModelError` otherwise)."""
    v = np.asarray(values, dtype=float)
    if v.shape != p.shape:
        msg = f"one {what} per run: got {v.shape} for {p.shape} runs"
        raise ModelError(msg)
    return v


def calibration_summary(
    probabilities: ArrayLike,
    correct: ArrayLike,
    rng: np.random.Generator,
    *,
    consistent_mass: ArrayLike | None = None,
    true_topology_mass: ArrayLike | None = None,
    n_bins: int = CALIBRATION_BINS,
    redraws: int = 2000,
) -> CalibrationSummary:
    """ECE, its chance level, Brier score, right-rate vs mean stated probability and, given the runs'
    consistent masses, the overconfident failures; ``true_topology_mass`` adds its mean."""
    p, y = _calibration_inputs(probabilities, correct)
    chance = chance_calibration_errors(p, rng, n_bins=n_bins, redraws=redraws)
    failures = None
    if consistent_mass is not None:
        c = _per_run(consistent_mass, p, "consistent mass")
        failures = int(np.count_nonzero(c < OVERCONFIDENT_MASS))
    mean_true = None
    if true_topology_mass is not None:
        mean_true = float(_per_run(true_topology_mass, p, "true-topology mass").mean())
    return CalibrationSummary(
        n_runs=int(p.size),
        n_bins=n_bins,
        ece=float(_ece_rows(p, y[None, :], n_bins)[0]),
        chance_ece=float(chance.mean()),
        chance_ece_p95=float(np.quantile(chance, 0.95)),
        brier=float(np.mean((p - y) ** 2)),
        map_right_rate=float(y.mean()),
        mean_map_probability=float(p.mean()),
        overconfident_failures=failures,
        mean_true_topology_mass=mean_true,
        bins=reliability_bins(p, y, n_bins),
    )
