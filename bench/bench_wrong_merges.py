"""Why the most probable topology merges places that are different in truth (issue #23), merge by merge.

For each shared real run under each perturbation of ``bench_perturbed_runs.py`` (``--perturbations``,
default all; seed 0), ``ptm-run`` at the defaults keeps its filter's state. Each place of the MAP topology
that holds a pair of visits ``ptm-eval`` scores as different places (more than 4 m apart in truth) is a
*wrong merge*. Its visits are split into the groups they form in truth (:func:`truth_groups`: chains of
visits scored as one place kept whole), and the batch model (:class:`ptm_ros.model.posterior.PosteriorModel`,
at the heading-noise scale the run learned, with the run's own registrations) scores the MAP against the MAP
with that place split. The difference of the two log posteriors, merge minus split, is decomposed into

* **prior**: the topology prior (Ch. 1.3; the Dirichlet process favours fewer places);
* **geometry**: the metric likelihood without the laser fitness evidence: odometry, place coincidences,
  the registrations used as pose constraints (eq. 17–18);
* **laser**: the fitness evidence of the laser outcomes the two topologies chain (eq. 47–49: each visit
  against the previous visit of its place; a failed match counts against one place by its ``log_bayes``).

Beside them: how far apart the groups are in truth and in the laser-corrected odometry (the closest pair of
visits across groups), the PTM's probability that the farthest pair is one place, and the laser outcomes
between the groups (valid matches; failed ones with their mean ``log_bayes``).

Beside the merges, whether the laser's fitness densities (fitted on the logs as logged) still hold under
the perturbation: the fitness evidence (``log_bayes``) of up to ``FITNESS_PAIRS`` pairs of visits more than
``FAR_M`` apart in truth and of up to as many less than 1.5 m apart (at least
``bench_heading_noise.REVISIT_GAP`` visits apart), registered as the filter registers them
(:func:`fitness_by_truth`); and among the pairs the filter itself asked the registrar about, how often
each truth class gives a match that slides along a corridor (:func:`slides_by_truth`) and the fitness
evidence those failed matches carry.

Writes ``bench/wrong_merges.json`` and ``bench/wrong_merges.md``.

    PYTHONPATH=. .venv/bin/python bench/bench_wrong_merges.py [--work out/wrong_merges]
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from bench_heading_noise import REVISIT_GAP
from bench_perturbed_runs import PERTURBATIONS, perturbed_logs
from run_all import ptm_run_scored, shared_data_ready, when_and_where, write_bench

if TYPE_CHECKING:
    from ptm_ros.model.geometry import NoMatch, RelativePose
    from ptm_ros.model.ptm import Ptm
    from ptm_ros.model.visits import Visit
    from ptm_ros.perception.laser import LaserConfig

BENCH = Path(__file__).resolve().parent


#: Pairs of each truth class whose fitness evidence is measured per run.
FITNESS_PAIRS = 40
#: Visits farther apart than this in truth are surely different places (far beyond ptm-eval's 4 m).
FAR_M = 8.0


def truth_groups(block: Sequence[int], positions: np.ndarray) -> list[list[int]]:
    """The visits of ``block`` in the groups they form in truth (``positions`` ``(N, 2)``), as ``ptm-eval``
    scores them (:class:`~ptm_ros.scoring.evaluation.EvalConfig`): visits chained by gaps below the
    same-place radius stay together (:func:`~ptm_ros.scoring.evaluation.single_linkage_places`); those chains,
    in the order of their first visits, then join the first group none of whose visits lies beyond the
    different-place radius of theirs, else open a group."""
    from ptm_ros.scoring.evaluation import EvalConfig, single_linkage_places

    cfg = EvalConfig()
    members = np.asarray(block, dtype=np.intp)
    chains = single_linkage_places(positions[members], cfg.same_radius)
    groups: list[list[int]] = []
    for k in range(int(chains.max()) + 1 if len(members) else 0):
        chain = [int(v) for v in members[chains == k]]
        for g in groups:
            if all(
                np.hypot(*(positions[v] - positions[u])) <= cfg.different_radius for u in g for v in chain
            ):
                g.extend(chain)
                break
        else:
            groups.append(chain)
    return [sorted(g) for g in groups]


def split_labels(labels: Sequence[int], groups: Sequence[Sequence[int]]) -> tuple[int, ...]:
    """``labels`` with every group but the first of one place given a new place of its own, canonical."""
    from ptm_ros.model.partitions import canonical

    out = list(labels)
    top = max(out)
    for k, g in enumerate(groups[1:], start=1):
        for v in g:
            out[v] = top + k
    return tuple(canonical(out))


def closest(groups: Sequence[Sequence[int]], positions: np.ndarray) -> float:
    """The smallest distance between two visits of different ``groups`` (``positions`` ``(N, 2)``)."""
    return float(
        min(
            np.hypot(*(positions[i] - positions[j]))
            for k, a in enumerate(groups)
            for b in groups[k + 1 :]
            for i in a
            for j in b
        )
    )


def outcomes_between(
    groups: Sequence[Sequence[int]], registrations: Mapping[tuple[int, int], RelativePose | NoMatch | None]
) -> dict[str, float]:
    """Laser outcomes registered between visits of different groups: valid matches, failed ones and the
    failed ones' mean ``log_bayes`` (nan without any)."""
    from ptm_ros.model.geometry import NoMatch, RelativePose

    member = {v: k for k, g in enumerate(groups) for v in g}
    valid, failed = 0, []
    for (i, j), z in registrations.items():
        if i in member and j in member and member[i] != member[j]:
            if isinstance(z, RelativePose):
                valid += 1
            elif isinstance(z, NoMatch):
                failed.append(z.log_bayes)
    return {
        "valid": valid,
        "failed": len(failed),
        "failed_log_bayes": float(np.mean(failed)) if failed else np.nan,
    }


def fitness_by_truth(
    registrar: Callable[[int, int], RelativePose | NoMatch | None],
    true_xy: np.ndarray,
    inside: np.ndarray,
    rng: np.random.Generator,
) -> dict[str, dict[str, float]]:
    """The fitness evidence of ``registrar``'s outcomes on up to :data:`FITNESS_PAIRS` random pairs of visits
    more than :data:`FAR_M` apart in truth (``different``) and up to as many less than ``ptm-eval``'s
    same-place radius apart and at least :data:`~bench_heading_noise.REVISIT_GAP` visits apart (``same``):
    per class, the pairs registered, the mean ``log_bayes`` and the share above 0 (evidence for one
    place)."""
    from ptm_ros.scoring.evaluation import EvalConfig

    i, j = np.triu_indices(len(true_xy), k=1)
    ok = inside[i] & inside[j]
    d = np.hypot(*(true_xy[i] - true_xy[j]).T)
    classes = {
        "different": ok & (d > FAR_M),
        "same": ok & (d < EvalConfig().same_radius) & (j - i >= REVISIT_GAP),
    }
    out = {}
    for name, mask in classes.items():
        idx = np.flatnonzero(mask)
        pick = np.sort(rng.choice(idx, size=min(FITNESS_PAIRS, len(idx)), replace=False))
        zs = [registrar(int(i[k]), int(j[k])) for k in pick]
        lb = np.array([z.log_bayes for z in zs if z is not None])
        out[name] = {
            "pairs": len(lb),
            "mean_log_bayes": float(lb.mean()) if len(lb) else np.nan,
            "share_positive": float(np.mean(lb > 0)) if len(lb) else np.nan,
        }
    return out


def slides_by_truth(
    visits: Sequence[Visit],
    asked: Sequence[tuple[int, int]],
    true_xy: np.ndarray,
    inside: np.ndarray,
    laser: LaserConfig,
) -> dict[str, dict[str, float]]:
    """Among the ``asked`` pairs that ``ptm-eval`` scores (:func:`~ptm_ros.scoring.evaluation.pair_truth`;
    visits outside the truth, ``inside`` false, unscored), registered again to read why a match
    failed: per class, the pairs registered, how many slide (:data:`~ptm_ros.perception.laser.FLAT_OPTIMUM`)
    and the fitness evidence they carry (their summed ``log_bayes``)."""
    from ptm_ros.perception.laser import FLAT_OPTIMUM, fitness_log_bayes, register_patch_pair
    from ptm_ros.scoring.evaluation import pair_truth

    scored = np.where(inside[:, None], true_xy, np.nan)  # no truth: unscored
    truth_class = {
        (int(i), int(j)): "same" if s else "different" for i, j, s in zip(*pair_truth(scored), strict=True)
    }
    out = {name: {"pairs": 0, "slides": 0, "slides_log_bayes": 0.0} for name in ("same", "different")}
    for i, j in asked:
        a, b, name = visits[i].patch, visits[j].patch, truth_class.get((i, j))
        reg = None if name is None or a is None or b is None else register_patch_pair(a, b, laser)
        if name is None or reg is None:
            continue
        out[name]["pairs"] += 1
        if not reg.valid and reg.reason.startswith(FLAT_OPTIMUM):
            out[name]["slides"] += 1
            out[name]["slides_log_bayes"] += fitness_log_bayes(reg.inlier_fraction, laser)
    return out


def analyse(ptm: Ptm, out: Path, truth_path: Path, seed: int) -> dict[str, Any]:
    """The wrong merges of ``ptm``'s MAP (what ``ptm-run`` wrote to ``out``, its ``filter_state.npz`` kept),
    decomposed (``merges``), and the fitness evidence by truth class (``fitness``, pairs drawn with ``seed``;
    module docstring). True positions as ``ptm-eval`` takes them
    (:func:`~ptm_ros.tools.evaluate.true_positions_for`)."""
    from dataclasses import replace

    from ptm_ros.config import PtmConfig
    from ptm_ros.inference.persistence import load_filter_state
    from ptm_ros.io.groundtruth import load_ground_truth
    from ptm_ros.model.partitions import blocks
    from ptm_ros.model.posterior import PosteriorModel, same_place_probabilities
    from ptm_ros.session import FilterSession
    from ptm_ros.tools.evaluate import true_positions_for

    state, _ = load_filter_state(out / "filter_state.npz")
    config = PtmConfig()
    session = FilterSession(config)
    session.load_state(state)
    visits = session.visits
    true_xy = true_positions_for(ptm, load_ground_truth(truth_path))
    inside = np.all(np.isfinite(true_xy), axis=1)
    odom_xy = np.array([v.pose[:2] for v in visits])
    model = PosteriorModel(
        visits,
        replace(config.model, odometry=session.odometry_config(), use_appearance=False),
        registrar=session.registrar,
    )
    labels = ptm.topologies[0].labels
    marginals = {t.labels: t.probability for t in ptm.topologies}
    same = same_place_probabilities(marginals, len(labels))
    found = []
    for block in blocks(labels):
        groups = truth_groups([v for v in block if inside[v]], true_xy)
        if len(groups) < 2:
            continue
        apart = split_labels(labels, groups)
        merged, split = model.terms(labels), model.terms(apart)
        laser = model.laser_evidence(labels) - model.laser_evidence(apart)
        far = max(
            ((i, j) for a in groups for b in groups if a is not b for i in a for j in b if i < j),
            key=lambda p: np.hypot(*(true_xy[p[0]] - true_xy[p[1]])),
        )
        found.append(
            {
                "groups": [list(map(int, g)) for g in groups],
                "true_apart_m": closest(groups, true_xy),
                "odometry_apart_m": closest(groups, odom_xy),
                "farthest_pair": [int(far[0]), int(far[1])],
                "farthest_true_m": float(np.hypot(*(true_xy[far[0]] - true_xy[far[1]]))),
                "p_same": float(same[far]),
                "delta_total": merged.total - split.total,
                "delta_prior": merged.prior - split.prior,
                "delta_geometry": (merged.metric - split.metric) - laser,
                "delta_laser": laser,
                **outcomes_between(groups, session.pairs),
            }
        )
    slides = slides_by_truth(visits, sorted(session.pairs), true_xy, inside, config.laser)
    # after the merges: these registrations join the session's cache, which outcomes_between reads
    registrar = session.registrar
    fitness = (
        {} if registrar is None else fitness_by_truth(registrar, true_xy, inside, np.random.default_rng(seed))
    )
    return {"merges": found, "fitness": fitness, "slides": slides}


def write_md(doc: dict[str, Any], path: Path) -> None:
    lines = [
        "# Wrong merges, decomposed by the batch model (issue #23)",
        "",
        f"Generated {doc['generated']} by `bench/bench_wrong_merges.py` ({doc['minutes']:.0f} min, seed "
        f"{doc['seed']}). Each place of the MAP topology holding visits that `ptm-eval` scores as different "
        "places (more than 4 m apart in truth), split into its groups in truth (`truth_groups`: chains of "
        "visits closer than 1.5 m kept whole), scored by the batch model (at the run's learned heading-noise "
        "scale) against the MAP: the log posterior of the merge minus the split [nats] and its parts, the "
        "prior, the geometry (odometry, coincidences, pose constraints) and the laser fitness evidence of "
        "the chained outcomes. *Apart*: the closest pair of visits across the groups in truth and in the "
        "laser-corrected odometry [m]. *P(same)*: the PTM's probability that the farthest pair is one place. "
        "*Between*: laser outcomes registered across the groups, valid / failed "
        "(mean log Bayes factor of the failed).",
        "",
        "| run | log | MAP F1 | groups | apart truth / odometry | farthest | P(same) | Δ total | Δ prior "
        "| Δ geometry | Δ laser | between |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        if "error" in r:
            lines.append(f"| {r['run']} | {r['log']} | failed | | | | | | | | | |")
            continue
        if not r["merges"]:
            lines.append(f"| {r['run']} | {r['log']} | {r['map_f1']:.3f} | none | | | | | | | | |")
        for m in r["merges"]:
            groups = " / ".join(",".join(map(str, g)) for g in m["groups"])
            fail = f"{m['failed']} ({m['failed_log_bayes']:+.1f})" if m["failed"] else "0"
            lines.append(
                f"| {r['run']} | {r['log']} | {r['map_f1']:.3f} | {groups} | {m['true_apart_m']:.1f} / "
                f"{m['odometry_apart_m']:.1f} | {m['farthest_true_m']:.1f} | {m['p_same']:.2f} | "
                f"{m['delta_total']:+.1f} | {m['delta_prior']:+.1f} | {m['delta_geometry']:+.1f} | "
                f"{m['delta_laser']:+.1f} | {m['valid']} / {fail} |"
            )
    lines += [
        "",
        "## The laser's fitness evidence by truth class",
        "",
        f"Up to {FITNESS_PAIRS} random pairs of visits more than {FAR_M:.0f} m apart in truth (*different*) "
        f"and as many less than 1.5 m apart and at least {REVISIT_GAP} visits apart (*same*), registered as "
        "the filter registers them: the mean fitness evidence (log Bayes factor for one place, "
        "`laser.fitness_*`, fitted on the logs as logged) and the share of pairs with evidence for one "
        "place.",
        "",
        "| run | log | different: pairs | mean log Bayes | share > 0 | same: pairs | mean log Bayes "
        "| share > 0 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        f = r.get("fitness") or {}
        if not f:
            continue
        d, s = f["different"], f["same"]
        lines.append(
            f"| {r['run']} | {r['log']} | {d['pairs']} | {d['mean_log_bayes']:+.2f} | "
            f"{d['share_positive']:.2f} | {s['pairs']} | {s['mean_log_bayes']:+.2f} | "
            f"{s['share_positive']:.2f} |"
        )
    lines += [
        "",
        "## Matches that slide, among the pairs the filter asked about",
        "",
        "The pairs the filter asked the registrar about, scored by `ptm-eval`'s radii (*same* < 1.5 m, "
        "*different* > 4 m in truth): how many failed only because the match slides along a corridor (a "
        "flat optimum), and the fitness evidence they carry for one place (summed log Bayes factors).",
        "",
        "| run | log | same: pairs | slide | share | their evidence | different: pairs | slide | share "
        "| their evidence |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in doc["runs"]:
        f = r.get("slides") or {}
        if not f:
            continue
        cells = []
        for name in ("same", "different"):
            c = f[name]
            share = c["slides"] / c["pairs"] if c["pairs"] else float("nan")
            cells.append(f"{c['pairs']} | {c['slides']} | {share:.3f} | {c['slides_log_bayes']:+.1f}")
        lines.append(f"| {r['run']} | {r['log']} | " + " | ".join(cells) + " |")
    path.write_text("\n".join(lines) + "\n")


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--perturbations", nargs="+", default=list(PERTURBATIONS), choices=list(PERTURBATIONS)
    )
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--work", type=Path, default=BENCH.parent / "out" / "wrong_merges")
    parser.add_argument("--out", type=Path, default=BENCH / "wrong_merges.json")
    args = parser.parse_args(argv)
    if not shared_data_ready("wrong-merges", args.work):
        return 0
    t0 = time.perf_counter()
    runs = []
    for name, label, bag, truth in perturbed_logs(args.work):
        if label not in args.perturbations:
            continue
        out = args.work / f"{name}-{label.replace(' ', '-')}"
        options = ("--seed", str(args.seed), "--force", "--no-report", "--no-map", "--autosave", "1000000")
        res = ptm_run_scored(bag, truth, out, *options)
        if isinstance(res, str):
            runs.append({"run": name, "log": label, "error": res})
            continue
        ptm, score = res
        runs.append(
            {"run": name, "log": label, "map_f1": score["map_f1"], **analyse(ptm, out, truth, args.seed)}
        )
        print(f"[wrong-merges] {name} {label}: {runs[-1]}", flush=True)
    doc = {"benchmark": "wrong_merges", "seed": args.seed, **when_and_where(t0), "runs": runs}
    write_bench(doc, args.out, write_md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
