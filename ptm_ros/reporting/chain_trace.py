"""MCMC's cold chains in a PTM and in their trace file beside ptm.json, and the SRQ data drawn from them.

``ptm.inference["cold_chain_states"]`` (:data:`SRQ_KEY`): one list per independent chain of the cold
(``β = 1``) replica's state after each sweep, thinned by a fixed stride (every ``k``-th sweep, ``k`` in
``ptm.inference["cold_chain_thin"]`` when known), states as integers (ids of topologies, the same id
for the same topology in every chain) or label lists. A thinned chain is again a Markov chain with the
same atoms, so its SRQ plot (thesis Ch. 3.6, Fig. 42; :mod:`ptm_ros.reporting.srq_plots`) is valid.

``ptm-run`` keeps in ptm.json only the chains' summary (:data:`CHAINS_KEY`, :func:`split_chain_trace`) and
with ``--trace`` writes their states to :data:`TRACE` (:func:`save_chain_trace`), which the report reads back
(:func:`find_chain_trace`, :func:`load_chain_trace`); :func:`chain_srq` gives the SRQ points of the chains.
"""

from __future__ import annotations

import json
from collections.abc import Hashable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from ptm_ros.errors import DataError
from ptm_ros.inference.convergence import most_visited, srq_deviation, srq_points
from ptm_ros.model.ptm import Ptm

#: Key of ``Ptm.inference`` holding the MCMC cold-chain states drawn as the SRQ plot (module docstring):
#: in memory, and in a ptm.json written before issue #25; ``ptm-run`` moves them to :data:`TRACE`.
SRQ_KEY = "cold_chain_states"
#: Key of ``Ptm.inference`` holding the thinning stride of those states (sweeps per kept state).
SRQ_THIN_KEY = "cold_chain_thin"
#: Key of ``Ptm.inference`` holding the topology (labels) of each state id in :data:`SRQ_KEY` (in memory).
SRQ_LABELS_KEY = "cold_chain_labels"
#: Key of ``Ptm.inference`` holding the summary of the cold chains that ptm.json keeps
#: (:func:`split_chain_trace`).
CHAINS_KEY = "cold_chains"
#: The file of the full cold-chain states beside ptm.json (``ptm-run --trace``) and its schema tag.
TRACE = "mcmc_trace.json"
TRACE_SCHEMA = "ptm_ros.mcmc_trace/1"


SrqPoints = tuple[ArrayLike, ArrayLike]


def _hashable(state: Any) -> Hashable:
    if isinstance(state, np.ndarray):
        return tuple(state.tolist())
    return tuple(state) if isinstance(state, list) else state


def chain_states(ptm: Ptm, trace: Mapping[str, Any] | None = None) -> list[list[Hashable]] | None:
    """The MCMC cold-chain states (one list per chain) of ``trace`` (:func:`load_chain_trace`) when given,
    else of ``ptm.inference[SRQ_KEY]``; None if absent.

    Label lists become tuples (hashable); numpy arrays are accepted as from an in-memory result.

    Raises:
        DataError: the states are something other than non-empty sequences of states, one per chain.
    """
    raw = trace["chains"] if trace is not None else ptm.inference.get(SRQ_KEY)
    if raw is None:
        return None
    rows = raw.tolist() if isinstance(raw, np.ndarray) else raw
    if isinstance(rows, str | bytes) or not isinstance(rows, Sequence) or not rows:
        msg = f"ptm.inference[{SRQ_KEY!r}] must be a non-empty list with one state list per chain"
        raise DataError(msg)
    chains = []
    for k, row in enumerate(rows):
        seq = row.tolist() if isinstance(row, np.ndarray) else row
        if isinstance(seq, str | bytes) or not isinstance(seq, Sequence) or not seq:
            got = type(seq).__name__
            msg = f"ptm.inference[{SRQ_KEY!r}][{k}] must be a non-empty list of states, got {got}"
            raise DataError(msg)
        chains.append([_hashable(s) for s in seq])
    return chains


def chain_srq(chains: Sequence[Sequence[Hashable]]) -> tuple[dict[str, SrqPoints], list[int]]:
    """SRQ points (``"chain k"`` → ``(x, y)``) of every chain at one atom, the state most visited over
    all chains, and the chains that never visit it (trapped away from the mode: no points)."""
    atom = most_visited([s for chain in chains for s in chain])
    points: dict[str, SrqPoints] = {}
    missing = []
    for k, chain in enumerate(chains):
        if atom in set(chain):
            points[f"chain {k}"] = srq_points(chain, atom)
        else:
            missing.append(k)
    return points, missing


def split_chain_trace(ptm: Ptm, *, trace_file: str | None = None) -> tuple[Ptm, dict[str, Any] | None]:
    """``(ptm, trace)``: the PTM whose ``inference`` keeps only a summary of MCMC's cold chains, and the
    chains' full states as a trace document (None when ``ptm`` holds none).

    The summary (:data:`CHAINS_KEY`) holds ``chains``, ``states`` (kept per chain), ``thin`` (sweeps per
    kept state), ``srq_max_deviation`` (per chain, the SRQ plot's ``max |y − x|`` at the atom most
    visited over all chains; null for a chain that never visits it) and ``trace`` (``trace_file``: where
    the caller writes the trace, null when nowhere). The trace (:data:`TRACE_SCHEMA`) holds ``thin``,
    ``chains`` (the states, one list per chain: topology ids, or label lists) and ``topologies`` (the
    labels of each id, when known).

    Raises:
        DataError: malformed states (:func:`chain_states`).
    """
    inf = dict(ptm.inference)
    chains = chain_states(ptm)
    if chains is None:
        return ptm, None
    raw = inf.pop(SRQ_KEY)
    rows = raw.tolist() if isinstance(raw, np.ndarray) else [list(np.asarray(c).tolist()) for c in raw]
    thin = int(inf.pop(SRQ_THIN_KEY, 1))
    labels = inf.pop(SRQ_LABELS_KEY, None)
    points, _ = chain_srq(chains)
    devs = [points.get(f"chain {k}") for k in range(len(chains))]
    inf[CHAINS_KEY] = {
        "chains": len(chains),
        "states": [len(c) for c in chains],
        "thin": thin,
        "srq_max_deviation": [None if p is None else srq_deviation(*p) for p in devs],
        "trace": trace_file,
    }
    trace = {"schema": TRACE_SCHEMA, "thin": thin, "chains": rows, "topologies": labels}
    return replace(ptm, inference=inf), trace


def save_chain_trace(trace: Mapping[str, Any], path: str | Path) -> Path:
    """Write a trace document (:func:`split_chain_trace`) as compact JSON; returns the path."""
    path = Path(path)
    path.write_text(json.dumps(trace, separators=(",", ":")), encoding="utf-8")
    return path


def load_chain_trace(path: str | Path, ptm: Ptm) -> dict[str, Any]:
    """The trace document at ``path``, checked against ``ptm``'s chain summary (:data:`CHAINS_KEY`: the
    same number of chains, states per chain and thinning).

    Raises:
        DataError: not a trace, malformed, or the trace of another run.
        OSError: the file cannot be read.
    """
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        msg = f"{path} is not a JSON document: {err}"
        raise DataError(msg) from err
    if not isinstance(doc, dict) or doc.get("schema") != TRACE_SCHEMA:
        msg = f"{path} is not an MCMC trace (schema {TRACE_SCHEMA})"
        raise DataError(msg)
    summary = ptm.inference.get(CHAINS_KEY)
    chains = chain_states(ptm, doc)
    got = {"states": [len(c) for c in chains or ()], "thin": doc.get("thin")}
    if not isinstance(summary, Mapping) or {k: summary.get(k) for k in got} != got:
        msg = f"{path} is the trace of another run (its chains do not match the PTM's {CHAINS_KEY})"
        raise DataError(msg)
    return doc


def find_chain_trace(ptm: Ptm, directory: str | Path) -> dict[str, Any] | None:
    """The trace that ``ptm``'s chain summary names (``trace``, a file in ``directory``, the directory of
    its ptm.json), loaded and checked (:func:`load_chain_trace`); None when it names none or the file is
    missing."""
    summary = ptm.inference.get(CHAINS_KEY)
    name = summary.get("trace") if isinstance(summary, Mapping) else None
    if not isinstance(name, str) or not (Path(directory) / name).is_file():
        return None
    return load_chain_trace(Path(directory) / name, ptm)
