r"""Batch PTMs by Markov chain Monte Carlo over set partitions (thesis Ch. 2.1, 3.1–3.6, App. C).

The target is the posterior over topologies ``π(T) ∝ P(T | Z)`` of a
:class:`~ptm_ros.model.posterior.PosteriorModel` (``ℓ(T) = log π(T)`` unnormalised, cached).
Metropolis–Hastings (Algorithm 1, eq. 13) accepts a proposed ``T'`` with probability

.. math::
    a = \min\Big(1,\ \Big(\frac{π(T')}{π(T)}\Big)^{β}\ \frac{q(T' → T)}{q(T → T')}\Big),

``β = 1`` except in the heated chains of MC³.

The proposals — plain, odometry- and appearance-driven split–merge moves, single-visit reassignment and
their mixture — and their proposal ratios are derived in :mod:`ptm_ros.inference.proposals`.

Proposal chaining and MC³
-------------------------
**Chaining** (Algorithm 4): draw ``C ~ U\{1..C_{max}\}`` and apply ``C`` base proposals
``T = T_0 → … → T_C = T'``; the acceptance uses the path probabilities
``\prod q(T_{c-1} → T_c)`` and ``\prod q(T_c → T_{c-1})`` (the ``1/C_{max}`` cancels). This is MH on the
path, whose reversal is an involution, hence exact for ``π`` (the printed algorithm is right).

**MC³** (Algorithm 5, Geyer): replicas at inverse temperatures ``1 = β_1 > β_2 > … > 0`` (thesis ladder
``β_i = 1/(1 + (i-1)t)``, :func:`thesis_ladder`) each make one MH step per sweep on ``π^{β_i}``; then,
hottest pair first, adjacent replicas swap states with probability
``\min(1, \exp((β_{i-1} - β_i)(ℓ(T_i) - ℓ(T_{i-1}))))`` (the printed ratio, correct). Only the
``β = 1`` replica is sampled.

Estimates and convergence
-------------------------
Two PTMs are kept: (a) the **histogram** of the cold states (after a burn-in fraction), and (b) the
**visited-set** estimate: every topology the sampler evaluated (states and proposals, at any temperature)
with mass ``∝ \exp ℓ(T)`` renormalised over that set. (b) is the default: each mass is the exact
posterior ratio, so its only error is the mass never evaluated (its TV to the truth is exactly
``1 - π(\text{visited})``), while (a) carries Monte Carlo noise ``O(n^{-1/2})`` on every topology and
needs far longer runs for the same TV when many topologies share the mass.

Convergence (Ch. 3.6, sample doubling): the chains run in rounds ``n_0, 2n_0, 4n_0, …`` sweeps; after each
round the estimate from the first half of the sweeps is compared with the estimate from all (TV), and
independent chains (their own seeds) are compared pairwise (max TV). The sampler stops when both are
below :attr:`McmcConfig.tolerance`, or at :attr:`McmcConfig.max_iterations` sweeps or
:attr:`McmcConfig.max_seconds`. Independent chains may run in worker processes
(:attr:`McmcConfig.processes`, fork start method). Results are deterministic under a seed unless the
time cap ends the run.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing as mp
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from itertools import combinations, pairwise
from typing import Any, cast

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import ConfigError, ModelError
from ptm_ros.inference.proposals import (
    ProposalKernel,
    RandomSource,
    UniformStream,
    make_proposal,
)
from ptm_ros.model.geometry import FloatArray
from ptm_ros.model.partitions import Labels, is_canonical, random_partition
from ptm_ros.model.posterior import PosteriorModel, normalize_log, same_place_probabilities, total_variation
from ptm_ros.settings import Settings, setting

#: Proposal kinds :class:`McmcConfig` accepts ("auto": every data-driven proposal the model supports).
PROPOSALS = ("auto", "split-merge", "odometry", "appearance", "reassign")
#: Estimates of the PTM :func:`run_mcmc` can return.
ESTIMATES = ("visited", "histogram")
#: Initial topologies of the chains.
INITIAL_STATES = ("auto", "singletons", "one-place", "random", "rbpf")

#: Largest block whose splits are ever enumerated (2^19 splits).
_MAX_SPLIT_ENUMERATION = 20
#: Sweeps a chain runs before the next chain sharing its process takes a turn.
_CHUNK = 64


# ---------------------------------------------------------------------------------------------------
# Configuration and results
# ---------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class McmcConfig(Settings):
    """Settings of the MCMC sampler (see the module docstring for the maths)."""

    proposal: str = setting(
        "auto",
        choices=PROPOSALS,
        doc=(
            'the proposal: "split-merge" (Alg. 2), "odometry" (Alg. 3), "appearance" (Alg. 10), "reassign" '
            '(one visit moved, not in the thesis) or "auto" = an equal mixture of the data-driven proposals '
            "the model supports (odometry with reassign, appearance; plain split–merge when none)."
        ),
    )
    odometry_scale: float = setting(
        1.0,
        gt=0,
        doc=(
            "s [m] of the odometry merge weights ``exp(-d²/2s²)``: about 2 σ_T, so that merges stay among "
            "visits a place could hold and chains are trapped less often (``bench/mcmc.json``)."
        ),
    )
    appearance_strength: float = setting(10.0, ge=0, doc="λ of the appearance weights ``exp(∓λ sep)``.")
    new_place_distance: float = setting(
        2.0,
        gt=0,
        doc=(
            "the reassign proposal opens a new place for a visit as readily as it joins a place this far "
            "from the visit [m] (weights ``exp(-d²/2s²)``, ``s`` = ``odometry_scale``)."
        ),
    )
    proposal_mix: float = setting(
        0.05,
        ge=0,
        lt=1,
        doc="ε, weight of the uniform distribution mixed into data-driven merges and splits.",
    )
    max_split_enumeration: int = setting(
        12,
        ge=2,
        le=_MAX_SPLIT_ENUMERATION,
        doc="largest block whose splits the appearance proposal scores (2^{k-1}-1 each).",
    )
    max_chaining: int = setting(1, ge=1, doc="C_max of proposal chaining (Alg. 4); 1 = no chaining.")
    betas: tuple[float, ...] = setting(
        (1.0, 0.5),
        gt=0,
        le=1,
        doc=(
            "inverse temperatures of MC³ (Alg. 5), ``1.0`` first, strictly decreasing; ``(1.0,)`` = one plain"
            ' chain. A single chain can stay trapped for thousands of sweeps in a "shifted loop" mode; one '
            "replica at β = ½ lets it out, for about twice the evaluations (``bench/mcmc.json``)."
        ),
    )
    chains: int = setting(
        2, ge=1, doc="independent chains (each an MC³ ladder) with their own seeds, compared for convergence."
    )
    processes: int = setting(
        1,
        ge=1,
        doc=(
            "worker processes running the chains (1 = in this process, where the chains also share the "
            "model's posterior cache; forking is also unwelcome inside a multi-threaded node)."
        ),
    )
    initial: str = setting(
        "auto",
        choices=INITIAL_STATES,
        doc=(
            'the chains\' starting topologies: "singletons" (thesis), "one-place", "random" (uniform over '
            'topologies, per chain), "rbpf": the particle filter\'s most probable topologies, chain ``c`` '
            "from the ``c``-th (a data-driven start for long runs, where chains from singletons stay "
            "trapped; ``ptm-run`` runs the filter first, :func:`ptm_ros.session.infer`; :func:`run_mcmc` "
            'needs them as ``initial``), or "auto" (default): "singletons" up to ``auto_filter_visits`` '
            'visits, "rbpf" beyond (:func:`starts_from_filter`): on the long real runs chains from '
            "singletons stay far below the filter's best topology, chains from the filter's end at or above "
            "it (``bench/mcmc.json``)."
        ),
    )
    auto_filter_visits: int = setting(
        40,
        ge=1,
        doc=(
            'most visits for which "auto" starts from singletons (short runs converge from there; longer '
            "ones start from the particle filter's topologies)."
        ),
    )
    estimate: str = setting(
        "visited",
        choices=ESTIMATES,
        doc='the PTM returned as ``probabilities``: "visited" (default) or "histogram".',
    )
    tolerance: float = setting(
        0.02, gt=0, lt=1, doc="TV below which sample doubling and chain agreement declare convergence."
    )
    burn_in: float = setting(
        0.1, ge=0, le=0.5, doc="fraction of each chain's sweeps left out of the histogram estimate."
    )
    min_iterations: int = setting(500, ge=1, doc="sweeps of the first round (rounds then double).")
    max_iterations: int = setting(200_000, ge=1, doc="cap on sweeps per chain.")
    max_seconds: float = setting(
        60.0,
        gt=0,
        doc=(
            "cap on the sampling's wall time [s], checked after every sweep; the particle filter run for the "
            'starts (``initial`` "rbpf") and the report after sampling come on top.'
        ),
    )
    trace_samples: int = setting(
        4000,
        ge=1,
        doc=(
            "most cold-chain states kept per chain in :attr:`McmcResult.cold_states` (the trace is thinned by"
            " a common stride to fit; for SRQ plots, thesis Ch. 3.6)."
        ),
    )

    def __post_init__(self) -> None:
        super().__post_init__()
        # a list (YAML, callers) becomes a tuple, its numbers floats
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))

    def check(self) -> None:
        """``max_iterations >= min_iterations``; ``betas`` a ladder from 1.0, strictly decreasing."""
        if self.max_iterations < self.min_iterations:
            msg = (
                f"McmcConfig.max_iterations ({self.max_iterations}) < min_iterations ({self.min_iterations})"
            )
            raise ConfigError(msg)
        betas = tuple(self.betas)
        if not betas or betas[0] != 1.0 or any(b >= a for a, b in pairwise(betas)):
            msg = f"McmcConfig.betas must start at 1.0 and decrease strictly to > 0, got {betas}"
            raise ConfigError(msg)


def thesis_ladder(n: int, step: float) -> tuple[float, ...]:
    """MC³ inverse temperatures ``β_i = 1 / (1 + (i-1) t)``, i = 1..n (Algorithm 5)."""
    if n < 1 or not (math.isfinite(step) and step > 0.0):
        msg = f"thesis_ladder needs n >= 1 and step > 0, got {n}, {step}"
        raise ConfigError(msg)
    return tuple(1.0 / (1.0 + i * step) for i in range(n))


@dataclass(frozen=True)
class McmcCheck:
    """Convergence figures after one sample-doubling round (TVs of the configured estimate).

    ``doubling_pair`` / ``chain_pair``: the same comparisons on the visit pairs' same-place
    probabilities (:func:`pair_marginal_change`; never above the TV, as a pair's marginal is the
    probability of an event). Over many visits the posterior spreads over so many near-equal topologies
    that the TV between two finite samples can stay large while the map's answer to "are visits i and j
    one place?" has settled; these say whether it has. They are reported, not part of
    :meth:`converged` (the thesis' test is on the PTM, Ch. 3.6).
    """

    iterations: int
    wall_s: float
    doubling_tv: float
    chain_tv: float | None
    n_evaluated: int
    doubling_pair: float = 0.0
    chain_pair: float | None = None

    def converged(self, tolerance: float) -> bool:
        """Sample doubling and (with several chains) chain agreement both within ``tolerance``."""
        return self.doubling_tv <= tolerance and (self.chain_tv is None or self.chain_tv <= tolerance)


@dataclass(frozen=True)
class McmcDiagnostics:
    """How the run went.

    Attributes:
        iterations: sweeps per chain (one MH step per replica, then swaps).
        chains: independent chains; ``betas``: their MC³ ladder.
        doubling_tv: TV between the estimate from the first half of the sweeps and from all of them.
        chain_tv: largest TV between two independent chains' estimates (None with one chain).
        doubling_pair, chain_pair: the same two comparisons on the visit pairs' same-place
            probabilities, largest absolute difference (:class:`McmcCheck`; reported only).
        converged: both TVs at or below the tolerance after at least ``min_iterations`` sweeps;
            ``stop_reason``: "converged", "max_iterations" or "max_seconds".
        acceptance: accepted / proposed per move kind of the cold replicas ("merge", "split", "chain";
            re-proposals of ``T`` are counted in ``proposals["stay"]`` only) and per swap pair
            ("swap i-j").
        proposals: number of proposals per kind (cold replicas) and swap attempts per pair.
        n_evaluated: distinct topologies whose posterior was evaluated.
        history: one :class:`McmcCheck` per round.
    """

    iterations: int
    chains: int
    betas: tuple[float, ...]
    doubling_tv: float
    chain_tv: float | None
    converged: bool
    stop_reason: str
    acceptance: dict[str, float]
    proposals: dict[str, int]
    n_evaluated: int
    history: tuple[McmcCheck, ...]
    doubling_pair: float = 0.0
    chain_pair: float | None = None


@dataclass(frozen=True)
class McmcResult:
    """A PTM computed by MCMC.

    Attributes:
        probabilities: the configured estimate, most probable first.
        histogram: the cold-chain sample histogram (burn-in removed), pooled over chains.
        visited: every evaluated topology with mass ∝ exp(log posterior), renormalised over them.
        log_posteriors: unnormalised log P(T | Z) of every evaluated topology.
        samples: cold-chain samples drawn (sweeps × chains).
        wall_s: wall time (s).
        cold_states: per independent chain, the cold (β = 1) replica's state after every
            ``cold_thin``-th sweep from the first (burn-in included), as ids into ``state_labels``; at most
            :attr:`McmcConfig.trace_samples` per chain. The input of an SRQ plot
            (:mod:`ptm_ros.inference.convergence`).
        state_labels: the topology of each id (ids shared by all chains, numbered in order of first
            appearance); only the states in ``cold_states``.
        cold_thin: sweeps per kept state (the common thinning stride of all chains).
    """

    probabilities: dict[Labels, float]
    histogram: dict[Labels, float]
    visited: dict[Labels, float]
    log_posteriors: dict[Labels, float]
    samples: int
    wall_s: float
    diagnostics: McmcDiagnostics
    config: McmcConfig
    cold_states: tuple[tuple[int, ...], ...] = ()
    state_labels: tuple[Labels, ...] = ()
    cold_thin: int = 1


# ---------------------------------------------------------------------------------------------------
# Chains
# ---------------------------------------------------------------------------------------------------


def _accept(log_a: float, rng: RandomSource) -> bool:
    """Metropolis test ``U < a``; NaN (−inf against −inf) rejects."""
    if log_a >= 0.0:
        return True
    return rng.random() < math.exp(log_a)


def _log_target_ratio(beta: float, new: float, old: float) -> float:
    if old == -math.inf:  # leaving a zero-probability state: any state is as good
        return math.inf if new > -math.inf else 0.0
    return beta * (new - old)


@dataclass
class _Segment:
    """What one chain produced since its last report (sent between processes)."""

    new_labels: list[Labels]
    trace: NDArray[np.int64]
    visited: list[tuple[Labels, float, int]]
    proposed: dict[str, int]
    accepted: dict[str, int]
    iteration: int


class _Ladder:
    """One independent chain: an MC³ ladder of replicas (one replica = a plain Metropolis–Hastings chain)."""

    def __init__(
        self,
        model: PosteriorModel,
        proposal: ProposalKernel,
        config: McmcConfig,
        initial: Labels,
        rng: np.random.Generator,
    ) -> None:
        self.model = model
        self.proposal = proposal
        self.betas = config.betas
        self.max_chaining = config.max_chaining
        self.rng = UniformStream(rng)
        self.iteration = 0
        self._logp: dict[Labels, float] = {}
        self._ids: dict[Labels, int] = {}
        self._labels: list[Labels] = []
        self._reported_labels = 0
        self._new_visits: list[tuple[Labels, float, int]] = []
        self._trace: list[int] = []
        self.proposed: dict[str, int] = {}
        self.accepted: dict[str, int] = {}
        lp = self._evaluate(initial)
        self.states = [initial] * len(self.betas)
        self.logps = [lp] * len(self.betas)

    def _evaluate(self, labels: Labels) -> float:
        lp = self._logp.get(labels)
        if lp is None:
            lp = self.model.log_posterior(labels)
            self._logp[labels] = lp
            self._new_visits.append((labels, lp, self.iteration))
        return lp

    def _id(self, labels: Labels) -> int:
        idx = self._ids.get(labels)
        if idx is None:
            idx = len(self._labels)
            self._ids[labels] = idx
            self._labels.append(labels)
        return idx

    def _count(self, table: dict[str, int], key: str) -> None:
        table[key] = table.get(key, 0) + 1

    def _mh_step(self, r: int) -> None:
        current = self.states[r]
        c_max = self.max_chaining
        links = 1 if c_max == 1 else self.rng.integers(1, c_max + 1)
        if links == 1:
            move = self.proposal.propose(current, self.rng)
            new, log_ratio, kind = move.labels, move.log_ratio, move.kind
        else:
            new, log_ratio, kind = current, 0.0, "chain"
            for _ in range(links):
                move = self.proposal.propose(new, self.rng)
                new, log_ratio = move.labels, log_ratio + move.log_ratio
        cold = r == 0
        if kind == "stay" or new == current:
            if cold:
                self._count(self.proposed, "stay")
            return
        lp = self._evaluate(new)
        log_a = _log_target_ratio(self.betas[r], lp, self.logps[r]) + log_ratio
        accepted = _accept(log_a, self.rng)
        if cold:
            self._count(self.proposed, kind)
            if accepted:
                self._count(self.accepted, kind)
        if accepted:
            self.states[r] = new
            self.logps[r] = lp

    def _swaps(self) -> None:
        for i in range(len(self.betas) - 1, 0, -1):
            key = f"swap {i - 1}-{i}"
            self._count(self.proposed, key)
            log_r = (self.betas[i - 1] - self.betas[i]) * (self.logps[i] - self.logps[i - 1])
            if _accept(log_r, self.rng):
                self._count(self.accepted, key)
                self.states[i - 1], self.states[i] = self.states[i], self.states[i - 1]
                self.logps[i - 1], self.logps[i] = self.logps[i], self.logps[i - 1]

    def sweep(self) -> None:
        """One MH step per replica, then swaps between adjacent temperatures; records the cold state."""
        for r in range(len(self.betas)):
            self._mh_step(r)
        if len(self.betas) > 1:
            self._swaps()
        self._trace.append(self._id(self.states[0]))
        self.iteration += 1

    def run(self, until: int, deadline: float | None) -> None:
        """Sweep up to ``until`` sweeps in all, or until ``deadline`` (``time.monotonic``), checked after
        every sweep: one sweep on a long run can take a second while its registrations are computed."""
        while self.iteration < until:
            self.sweep()
            if deadline is not None and time.monotonic() >= deadline:
                return

    def report(self) -> _Segment:
        """Everything new since the last report."""
        seg = _Segment(
            new_labels=self._labels[self._reported_labels :],
            trace=np.asarray(self._trace, dtype=np.int64),
            visited=self._new_visits,
            proposed=dict(self.proposed),
            accepted=dict(self.accepted),
            iteration=self.iteration,
        )
        self._reported_labels = len(self._labels)
        self._trace = []
        self._new_visits = []
        return seg


@dataclass
class _Record:
    """The main process's copy of one chain's output."""

    labels: list[Labels] = field(default_factory=list)
    traces: list[NDArray[np.int64]] = field(default_factory=list)
    visited: dict[Labels, tuple[float, int]] = field(default_factory=dict)
    proposed: dict[str, int] = field(default_factory=dict)
    accepted: dict[str, int] = field(default_factory=dict)
    iteration: int = 0

    def apply(self, seg: _Segment) -> None:
        self.labels.extend(seg.new_labels)
        if seg.trace.size:
            self.traces.append(seg.trace)
        for lab, lp, it in seg.visited:
            self.visited.setdefault(lab, (lp, it))
        self.proposed, self.accepted, self.iteration = seg.proposed, seg.accepted, seg.iteration

    def trace(self) -> NDArray[np.int64]:
        if len(self.traces) > 1:
            self.traces = [np.concatenate(self.traces)]
        return self.traces[0] if self.traces else np.zeros(0, dtype=np.int64)


class _InlineRunner:
    """Chains advanced in this process, interleaved in chunks so a time cap treats them alike."""

    def __init__(self, ladders: list[_Ladder]) -> None:
        self.ladders = ladders

    def advance(self, until: int, seconds: float) -> list[_Segment]:
        deadline = time.monotonic() + seconds
        while any(lad.iteration < until for lad in self.ladders) and time.monotonic() < deadline:
            for lad in self.ladders:
                lad.run(min(until, lad.iteration + _CHUNK), deadline)
        return [lad.report() for lad in self.ladders]

    def close(self) -> None:
        return


def _worker(conn: Any, ladders: list[_Ladder]) -> None:
    """Worker process: advance its chains on request, send back their segments."""
    runner = _InlineRunner(ladders)
    try:
        while True:
            msg = conn.recv()
            if msg is None:
                break
            until, seconds = msg
            conn.send(("ok", runner.advance(until, seconds)))
    except EOFError:
        pass
    except Exception:  # reported to the parent, which raises
        conn.send(("error", traceback.format_exc()))
    finally:
        conn.close()


class _ProcessRunner:
    """Chains spread round-robin over worker processes (fork: the model is inherited, not pickled)."""

    def __init__(self, ladders: list[_Ladder], processes: int) -> None:
        try:
            ctx = mp.get_context("fork")
        except ValueError as err:
            msg = "McmcConfig.processes > 1 needs the 'fork' start method (Linux)"
            raise ConfigError(msg) from err
        n_workers = min(processes, len(ladders))
        self.assign = [list(range(w, len(ladders), n_workers)) for w in range(n_workers)]
        self.n = len(ladders)
        self.conns = []
        self.procs = []
        for idx in self.assign:
            parent, child = ctx.Pipe()
            proc = ctx.Process(target=_worker, args=(child, [ladders[i] for i in idx]), daemon=True)
            proc.start()
            child.close()
            self.conns.append(parent)
            self.procs.append(proc)

    def advance(self, until: int, seconds: float) -> list[_Segment]:
        for conn in self.conns:
            conn.send((until, seconds))
        out: list[_Segment | None] = [None] * self.n
        for conn, idx in zip(self.conns, self.assign, strict=True):
            status, payload = conn.recv()
            if status != "ok":
                msg = f"an MCMC worker process failed:\n{payload}"
                raise ModelError(msg)
            for i, seg in zip(idx, payload, strict=True):
                out[i] = seg
        return [seg for seg in out if seg is not None]

    def close(self) -> None:
        for conn in self.conns:
            with contextlib.suppress(BrokenPipeError, OSError):
                conn.send(None)
        for proc in self.procs:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.terminate()
                proc.join()
        for conn in self.conns:
            conn.close()


# ---------------------------------------------------------------------------------------------------
# Estimates
# ---------------------------------------------------------------------------------------------------


def _histogram(records: Sequence[_Record], stop: int, burn_in: float) -> dict[Labels, float]:
    counts: dict[Labels, float] = {}
    for rec in records:
        trace = rec.trace()[:stop]
        start = int(burn_in * len(trace))
        ids = trace[start:]
        if ids.size == 0:
            continue
        c = np.bincount(ids)
        for i in np.flatnonzero(c).tolist():
            lab = rec.labels[i]
            counts[lab] = counts.get(lab, 0.0) + float(c[i])
    total = math.fsum(counts.values())
    if total == 0.0:  # no sweep yet: the initial states
        for rec in records:
            counts[next(iter(rec.visited))] = 1.0  # the first evaluated topology is the initial state
        total = float(len(counts))
    return {lab: c / total for lab, c in counts.items()}


def _visited(records: Sequence[_Record], stop: int) -> dict[Labels, float]:
    logp: dict[Labels, float] = {}
    for rec in records:
        for lab, (lp, it) in rec.visited.items():
            if it < stop or it == 0:
                logp[lab] = lp
    return normalize_log(logp)


#: Probability mass left out of :func:`pair_marginal_change` (the least probable topologies).
_PAIR_MASS_TAIL = 1e-6


def pair_marginal_change(p: dict[Labels, float], q: dict[Labels, float], n: int) -> float:
    """Largest absolute difference between two PTMs' same-place probabilities of a visit pair
    (:func:`ptm_ros.model.posterior.same_place_probabilities`), each PTM cut to its most probable topologies
    holding all but ``1e-6`` of its mass (the cut moves a marginal by at most that)."""
    return _largest_pair_change(_pair_marginals(p, n), _pair_marginals(q, n))


def _pair_marginals(probs: dict[Labels, float], n: int) -> FloatArray:
    """Same-place probabilities ``(n, n)`` of a PTM cut to all but ``_PAIR_MASS_TAIL`` of its mass."""
    return same_place_probabilities(_head(probs, 1.0 - _PAIR_MASS_TAIL), n)


def _largest_pair_change(a: FloatArray, b: FloatArray) -> float:
    n = a.shape[0]
    return 0.0 if n < 2 else float(np.max(np.abs(a - b)[np.triu_indices(n, 1)]))


def _head(probs: dict[Labels, float], mass: float) -> dict[Labels, float]:
    out: dict[Labels, float] = {}
    total = 0.0
    for lab, pr in sorted(probs.items(), key=lambda kv: -kv[1]):
        if total >= mass:
            break
        out[lab] = pr
        total += pr
    return out


def _sort(probs: dict[Labels, float]) -> dict[Labels, float]:
    return dict(sorted(probs.items(), key=lambda kv: (-kv[1], kv[0])))


def initial_kind(config: McmcConfig, n: int) -> str:
    """The start ``config.initial`` means over ``n`` visits: "auto" resolved to "rbpf" beyond
    ``auto_filter_visits`` visits, else to "singletons"; any other setting as it is."""
    if config.initial != "auto":
        return config.initial
    return "rbpf" if n > config.auto_filter_visits else "singletons"


def starts_from_filter(config: McmcConfig, n: int) -> bool:
    """Whether the chains over ``n`` visits start from the particle filter's topologies."""
    return initial_kind(config, n) == "rbpf"


def _initial_state(kind: str, n: int, rng: np.random.Generator) -> Labels:
    if kind == "singletons":
        return tuple(range(n))
    if kind == "one-place":
        return (0,) * n
    return random_partition(n, rng)


def _given_starts(initial: Sequence[int] | Sequence[Sequence[int]] | None, n: int) -> list[Labels] | None:
    """The chains' initial topologies from one label sequence or a sequence of them (None: not given)."""
    if initial is None:
        return None
    items = list(initial)
    many = bool(items) and all(isinstance(v, Sequence) and not isinstance(v, str) for v in items)
    # many: every item is a label sequence (checked just above); else the items are the labels themselves
    states = cast("list[Sequence[int]]", items) if many else [cast("list[int]", items)]
    out: list[Labels] = []
    for state in states:
        start = tuple(int(v) for v in state)
        if len(start) != n or not is_canonical(start):
            msg = f"initial topology must be a canonical label sequence of {n} visits, got {start}"
            raise ModelError(msg)
        out.append(start)
    return out


def _generators(rng: np.random.Generator | int | None, n: int) -> list[np.random.Generator]:
    if isinstance(rng, np.random.Generator):
        return list(rng.spawn(n))
    return [np.random.default_rng(s) for s in np.random.SeedSequence(rng).spawn(n)]


class McmcSampler:
    """The MCMC driver: independent MC³ chains advanced together, with their estimates and diagnostics.

    :func:`run_mcmc` is the usual entry point; use this class directly to follow a run sweep by sweep
    (benchmarks). Close it (or use it as a context manager) to stop worker processes.
    """

    def __init__(
        self,
        model: PosteriorModel,
        config: McmcConfig | None = None,
        rng: np.random.Generator | int | None = None,
        *,
        initial: Sequence[int] | Sequence[Sequence[int]] | None = None,
        proposal: ProposalKernel | None = None,
    ) -> None:
        self.model = model
        self.config = config or McmcConfig()
        self.proposal = proposal if proposal is not None else make_proposal(model, self.config)
        gens = _generators(rng, self.config.chains)
        starts = _given_starts(initial, model.n)
        if starts is None and starts_from_filter(self.config, model.n):
            msg = (
                f"McmcConfig.initial = {self.config.initial!r} over {model.n} visits needs the filter's "
                'topologies as the initial argument (or initial = "singletons")'
            )
            raise ConfigError(msg)
        ladders = []
        for c, gen in enumerate(gens):
            state = (
                _initial_state(initial_kind(self.config, model.n), model.n, gen)
                if starts is None
                else starts[c % len(starts)]
            )
            ladders.append(_Ladder(model, self.proposal, self.config, state, gen))
        self.records = [_Record() for _ in ladders]
        for rec, lad in zip(self.records, ladders, strict=True):
            rec.apply(lad.report())
        self._runner: _InlineRunner | _ProcessRunner
        if self.config.processes > 1 and len(ladders) > 1:
            self._runner = _ProcessRunner(ladders, self.config.processes)
        else:
            self._runner = _InlineRunner(ladders)
        self._start = time.monotonic()

    def __enter__(self) -> McmcSampler:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the worker processes (if any)."""
        self._runner.close()

    @property
    def iterations(self) -> int:
        """Sweeps completed by every chain."""
        return min(rec.iteration for rec in self.records)

    @property
    def wall_s(self) -> float:
        """Seconds since the sampler was built."""
        return time.monotonic() - self._start

    def advance(self, until: int, seconds: float = math.inf) -> int:
        """Run every chain to ``until`` sweeps in all (or for ``seconds``); returns :attr:`iterations`."""
        for rec, seg in zip(self.records, self._runner.advance(until, seconds), strict=True):
            rec.apply(seg)
        return self.iterations

    def estimate(
        self, kind: str | None = None, *, stop: int | None = None, chain: int | None = None
    ) -> dict[Labels, float]:
        """The PTM from sweeps ``[0, stop)`` (default all) of every chain, or of chain ``chain`` only."""
        kind = kind or self.config.estimate
        if kind not in ESTIMATES:
            msg = f"estimate kind must be one of {ESTIMATES}, got {kind!r}"
            raise ConfigError(msg)
        stop = self.iterations if stop is None else stop
        recs = self.records if chain is None else [self.records[chain]]
        if kind == "visited":
            return _sort(_visited(recs, stop))
        return _sort(_histogram(recs, stop, self.config.burn_in))

    def check(self, kind: str | None = None) -> McmcCheck:
        """Sample doubling TV and chain agreement TV of the estimate now."""
        n = self.iterations
        full = self.estimate(kind, stop=n)
        half = self.estimate(kind, stop=n // 2)
        doubling = total_variation(half, full)
        nv = self.model.n
        pair = _largest_pair_change(_pair_marginals(half, nv), _pair_marginals(full, nv))
        chain_tv = chain_pair = None
        if len(self.records) > 1:
            per = [self.estimate(kind, stop=n, chain=c) for c in range(len(self.records))]
            chain_tv = max(total_variation(p, q) for p, q in combinations(per, 2))
            marginals = [_pair_marginals(p, nv) for p in per]  # once per chain, not once per pair of chains
            chain_pair = max(_largest_pair_change(a, b) for a, b in combinations(marginals, 2))
        n_eval = len(set().union(*(rec.visited for rec in self.records)))
        return McmcCheck(n, self.wall_s, doubling, chain_tv, n_eval, pair, chain_pair)

    def cold_chain(self, max_samples: int) -> tuple[tuple[tuple[int, ...], ...], tuple[Labels, ...], int]:
        """Every chain's cold-state trace thinned to at most ``max_samples`` states by one common stride.

        Returns ``(states, labels, thin)``: per chain the ids of its state after sweeps
        ``0, thin, 2 thin, …`` (0-based, the first sweep included), the topology of each id (shared by all
        chains, numbered in order of first appearance, chain 0's kept states first) and the stride
        ``thin = ⌈longest trace / max_samples⌉``.
        """
        if max_samples < 1:
            msg = f"max_samples must be >= 1, got {max_samples}"
            raise ConfigError(msg)
        traces = [rec.trace() for rec in self.records]
        thin = max(1, -(-max(len(t) for t in traces) // max_samples))
        ids: dict[Labels, int] = {}
        states = []
        for rec, trace in zip(self.records, traces, strict=True):
            kept = trace[::thin].tolist()  # this chain's own ids
            remap = {i: ids.setdefault(rec.labels[i], len(ids)) for i in dict.fromkeys(kept)}
            states.append(tuple(remap[i] for i in kept))
        return tuple(states), tuple(ids), thin

    def acceptance(self) -> tuple[dict[str, float], dict[str, int]]:
        """Acceptance rate and proposal count per move kind, pooled over chains."""
        proposed: dict[str, int] = {}
        accepted: dict[str, int] = {}
        for rec in self.records:
            for k, v in rec.proposed.items():
                proposed[k] = proposed.get(k, 0) + v
            for k, v in rec.accepted.items():
                accepted[k] = accepted.get(k, 0) + v
        rates = {k: accepted.get(k, 0) / v for k, v in sorted(proposed.items()) if k != "stay" and v > 0}
        return rates, dict(sorted(proposed.items()))

    def result(self, history: Sequence[McmcCheck] = (), stop_reason: str = "") -> McmcResult:
        """The estimates and diagnostics as they stand."""
        cfg = self.config
        last = self.check()
        hist = tuple(history) or (last,)
        converged = last.converged(cfg.tolerance) and last.iterations >= cfg.min_iterations
        rates, counts = self.acceptance()
        logp: dict[Labels, float] = {}
        for rec in self.records:
            logp.update({lab: lp for lab, (lp, _) in rec.visited.items()})
        diag = McmcDiagnostics(
            iterations=last.iterations,
            chains=len(self.records),
            betas=cfg.betas,
            doubling_tv=last.doubling_tv,
            chain_tv=last.chain_tv,
            converged=converged,
            stop_reason=stop_reason or ("converged" if converged else "stopped"),
            acceptance=rates,
            proposals=counts,
            n_evaluated=last.n_evaluated,
            history=hist,
            doubling_pair=last.doubling_pair,
            chain_pair=last.chain_pair,
        )
        histogram = self.estimate("histogram")
        visited = self.estimate("visited")
        states, labels, thin = self.cold_chain(cfg.trace_samples)
        return McmcResult(
            probabilities=visited if cfg.estimate == "visited" else histogram,
            histogram=histogram,
            visited=visited,
            log_posteriors=logp,
            samples=sum(rec.iteration for rec in self.records),
            wall_s=self.wall_s,
            diagnostics=diag,
            config=cfg,
            cold_states=states,
            state_labels=labels,
            cold_thin=thin,
        )


def _advance(
    sampler: McmcSampler, target: int, max_seconds: float, progress: Callable[[int, int], None] | None
) -> int:
    """Every chain to ``target`` sweeps within ``max_seconds`` of the sampler's time (in tenths of the way
    when ``progress`` hears of each); the sweeps every chain has done."""
    if progress is None:
        remaining = max_seconds - sampler.wall_s
        return sampler.advance(target, remaining) if remaining > 0.0 else sampler.iterations
    reached = sampler.iterations
    step = max(1, -(-(target - reached) // 10))
    while reached < target:
        remaining = max_seconds - sampler.wall_s
        if remaining <= 0.0:
            break
        goal = min(target, reached + step)
        reached = sampler.advance(goal, remaining)
        progress(reached, target)
        if reached < goal:  # the time cap
            break
    return reached


def run_mcmc(
    model: PosteriorModel,
    config: McmcConfig | None = None,
    rng: np.random.Generator | int | None = None,
    *,
    initial: Sequence[int] | Sequence[Sequence[int]] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> McmcResult:
    """The PTM of ``model`` by MCMC with sample doubling until converged or capped (module docstring).

    ``rng``: a generator or an integer seed (each chain gets an independent child stream); the result
    is a function of the seed unless ``config.max_seconds`` ends the run. ``initial`` overrides
    ``config.initial``: one topology for every chain, or a sequence of topologies (chain ``c`` starts
    from the ``c``-th, cycled). ``progress(sweeps, target)`` (e.g. a progress bar) hears of the sweeps
    every chain has done and of the round's target, ten times a round: the chains then advance in
    tenths of a round, which changes nothing in the result (each chain has its own random stream).
    """
    cfg = config or McmcConfig()
    with McmcSampler(model, cfg, rng, initial=initial) as sampler:
        history: list[McmcCheck] = []
        target = cfg.min_iterations
        reason = "max_iterations"
        while True:
            reached = _advance(sampler, target, cfg.max_seconds, progress)
            check = sampler.check()
            history.append(check)
            if check.converged(cfg.tolerance) and reached >= cfg.min_iterations:
                reason = "converged"
                break
            if reached < target or sampler.wall_s >= cfg.max_seconds:
                reason = "max_seconds"
                break
            if target >= cfg.max_iterations:
                break
            target = min(2 * target, cfg.max_iterations)
        return sampler.result(history, reason)
