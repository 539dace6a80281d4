"""The one-page report of a PTM (after the thesis' Fig. 56–57): its figures, its text and tables.

:func:`write_report` writes into ``out_dir``, always under the same file names:

* ``ptm_histogram.png`` and ``ptm_topologies.png`` — the PTM as a histogram and its ``top_k`` most probable
  topologies drawn over the trajectory (:mod:`ptm_ros.reporting.topology_plots`).
* ``ptm_scores.png`` (only with a score) — precision / recall / F1 of the MAP topology and of the
  posterior, and the masses (:func:`ptm_ros.reporting.topology_plots.draw_scores`).
* ``ptm_surprise.png`` (only with a surprise trace) — the landmark detector's Bayesian surprise (thesis
  Ch. 4.7.3, Fig. 62; :mod:`ptm_ros.reporting.surprise_plots`).
* ``ptm_timeline.png`` (only when ``ptm.inference`` holds the particle filter's timeline,
  :func:`ptm_ros.model.ptm.ptm_timeline`) — how the mass moved as the visits arrived
  (:mod:`ptm_ros.reporting.timeline_plots`).
* ``ptm_srq.png`` (only with MCMC cold-chain states: ``chain_trace``, else ``ptm.inference[SRQ_KEY]``,
  :mod:`ptm_ros.reporting.chain_trace`) — the scaled regeneration quantile plot of every chain (thesis
  Ch. 3.6, Fig. 42; :mod:`ptm_ros.reporting.srq_plots`).
* the occupancy map (only when ``occupancy_map`` is given: ``ptm-run`` passes its ``map.png``, the grid
  of the scans placed along the smoothed trajectory of the MAP topology, :mod:`ptm_ros.maps.occupancy`).
* ``map_comparison.png`` (only with a :class:`~ptm_ros.reporting.map_plots.MapComparison`) — the map side
  by side with its reference, or with the MAP topology's route graph (:mod:`ptm_ros.reporting.map_plots`).
* ``report.md`` and ``report.html`` — the summary (plus the caller's ``notes``, e.g. trajectory errors),
  the score table, the figures (relative links, the map and extra figures copied beside them unless
  already there) and the top topologies as a table.

The summary's lines (:func:`inference_line`, :data:`CONSISTENT_MASS_MEANING`) are also ``ptm-run``'s.
"""

from __future__ import annotations

import html
import shutil
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from ptm_ros.errors import DataError, ModelError
from ptm_ros.inference.convergence import srq_deviation
from ptm_ros.model.partitions import num_places
from ptm_ros.model.ptm import Ptm, ptm_timeline
from ptm_ros.model.translation_noise import TRANSLATION_KEY, WEAK_GEOMETRY_SCALE
from ptm_ros.perception.laser import WorkerPool
from ptm_ros.reporting.chain_trace import CHAINS_KEY, SRQ_THIN_KEY, TRACE, chain_srq, chain_states
from ptm_ros.reporting.figures import ess_fraction, sig
from ptm_ros.reporting.map_plots import MapComparison, draw_map_comparison
from ptm_ros.reporting.plots import ReportConfig, label_string
from ptm_ros.reporting.srq_plots import draw_srq
from ptm_ros.reporting.surprise_plots import draw_surprise
from ptm_ros.reporting.timeline_plots import draw_timeline
from ptm_ros.reporting.topology_plots import draw_histogram, draw_scores, draw_topologies
from ptm_ros.scoring.evaluation import Score

if TYPE_CHECKING:
    from ptm_ros.perception.surprise import SurpriseTrace

HISTOGRAM = "ptm_histogram.png"
TOPOLOGIES = "ptm_topologies.png"
SCORES = "ptm_scores.png"
SURPRISE = "ptm_surprise.png"
SRQ = "ptm_srq.png"
MAP_COMPARISON = "map_comparison.png"
TIMELINE = "ptm_timeline.png"
#: Caption of the timeline figure.
TIMELINE_CAPTION = "How the mass moved as the visits arrived (the particle filter's PTM after each visit)"
REPORT_MD = "report.md"
REPORT_HTML = "report.html"
#: Caption of the occupancy map figure.
MAP_CAPTION = "Occupancy grid of the scans along the smoothed trajectory of the most probable topology"
#: Captions of the side-by-side map figure, with a reference and without one.
REFERENCE_CAPTION = (
    "The map (aligned as for the ATE; red: free cells more than 0.3 m from anything the reference saw) "
    "next to the reference: the same scans at the ground-truth poses"
)
ROUTES_CAPTION = "The map next to the most probable topology's route graph drawn over it"


def srq_summary_line(summary: Mapping[str, Any]) -> str:
    """The report line of a chain summary (:data:`CHAINS_KEY`) without the states: the SRQ figures, and
    that the plot needs the trace."""
    devs = summary.get("srq_max_deviation") or []
    shown = [f"chain {k} {'–' if d is None else f'{d:.3f}'}" for k, d in enumerate(devs)]
    trapped = [str(k) for k, d in enumerate(devs) if d is None]
    line = f"SRQ max |y − x| (0 = ideal mixing): {', '.join(shown)}" if shown else "SRQ"
    if trapped:
        line += f"; atom never visited by chain {', '.join(trapped)}"
    return line + f"; the SRQ plot needs the chains' states: run ptm-run with --trace (they go to {TRACE})"


def _fmt(v: float | None) -> str:
    return "—" if v is None else f"{v:.3f}"


#: The scalar figures of ``ptm.inference`` that :func:`inference_line` shows, per method, in words:
#: key -> (label, unit). MCMC's convergence figures have their own line (``ptm-run``'s inference notes).
INFERENCE_WORDS: dict[str, dict[str, tuple[str, str]]] = {
    "rbpf": {
        "particles": ("particles", ""),
        "particles_peak": ("most held", ""),
        "seed": ("seed", ""),
        "resample": ("resampling", ""),
        "n_topologies": ("distinct topologies held", ""),
        "ess": ("ESS", ""),
        "log_evidence": ("log evidence", " nats"),
        "update_ms_median": ("update time median", " ms"),
        "update_ms_p95": ("95th percentile", " ms"),
    },
    "exact": {"n_topologies_evaluated": ("topologies enumerated", "")},
    "mcmc": {"seed": ("seed", ""), "estimate": ("estimate", ""), "samples": ("samples", "")},
}
#: One sentence on the consistent mass, wherever it is shown.
CONSISTENT_MASS_MEANING = (
    "consistent mass = the posterior mass of the topologies that put no scored visit pair wrong; on long "
    "real runs it is often 0, because every listed topology gets at least one of hundreds of pairs wrong, "
    "even at an F1 of 0.98"
)


def _value(value: Any) -> str:
    """A scalar for a reader: yes/no, whole numbers as they are, other numbers to 3 significant digits."""
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return sig(float(value))
    return str(value)


def inference_line(inference: Mapping[str, Any]) -> str:
    """``method: rbpf (particles 100, seed 0, …, ESS 1.00/100, log evidence 278.9 nats, …)``: the estimator
    with its scalar figures (:data:`INFERENCE_WORDS` for the known methods, every scalar for others),
    rounded for reading (:func:`ptm_ros.reporting.figures.sig`; the ESS as a share of the topologies held)."""
    inf = dict(inference)
    method = str(inf.pop("method", "unknown"))
    words = INFERENCE_WORDS.get(method)
    if words is None:
        words = {
            k: (k.replace("_", " "), "") for k, v in inf.items() if isinstance(v, int | float | str | bool)
        }
    parts = []
    for key, (label, unit) in words.items():
        v = inf.get(key)
        if v is None or not isinstance(v, int | float | str | bool):
            continue
        if key == "ess" and isinstance(inf.get("n_topologies"), int):
            text = ess_fraction(float(v), inf["n_topologies"])
        elif key == "log_evidence":
            text = f"{float(v):.1f}"
        else:
            text = _value(v)
        parts.append(f"{label} {text}{unit}")
    return f"method: {method}" + (f" ({', '.join(parts)})" if parts else "")


def visits_line(ptm: Ptm, declared: int | None = None) -> str:
    """``visits: 10; topologies listed: 50, listed mass 1.000``, and how the visits reconcile with the
    landmarks the detector declared (``declared``, else the drops counted in ``diagnostics.skipped``:
    :func:`ptm_ros.perception.landmarks.landmark_accounting`)."""
    from ptm_ros.perception.landmarks import landmark_accounting

    line = (
        f"visits: {len(ptm.landmarks)}; topologies listed: {len(ptm.topologies)}, "
        f"listed mass {sum(t.probability for t in ptm.topologies):.3f}"
    )
    diag = ptm.extra.get("diagnostics")
    skipped = diag.get("skipped") if isinstance(diag, Mapping) else None
    accounting = landmark_accounting(
        len(ptm.landmarks), skipped if isinstance(skipped, Mapping) else {}, declared
    )
    return line + (f" ({accounting})" if accounting else "")


def _summary(ptm: Ptm, notes: Sequence[str] = (), declared: int | None = None) -> list[str]:
    top = ptm.topologies[0] if ptm.topologies else None
    lines = [inference_line(ptm.inference), visits_line(ptm, declared)]
    if top is not None:
        lines.append(f"most probable topology: p = {top.probability:.3f}, {num_places(top.labels)} places")
    check = translation_check_line(ptm.inference.get(TRANSLATION_KEY))
    if check:
        lines.append(check)
    wall = ptm.timing.get("wall_s")
    if isinstance(wall, (int, float)):
        lines.append(f"wall time: {wall:.2f} s")
    return lines + list(notes)


def translation_check_line(noise: object) -> str | None:
    """``odometry check: …``, the translation-noise scale the registrations suggest
    (:mod:`ptm_ros.model.translation_noise`), with a warning from :data:`WEAK_GEOMETRY_SCALE` up; None
    without one."""
    if not isinstance(noise, Mapping) or not noise.get("registrations"):
        return None
    scale = float(noise["scale"])
    line = (
        f"odometry check: the translation noise (variance) that {noise['registrations']} laser registrations "
        f"suggest is {sig(scale)}x the model's"
    )
    if scale >= WEAK_GEOMETRY_SCALE:
        line += (
            " (the odometry is worse than its noise model: the metric evidence is weaker than the posterior "
            "assumes, and its probabilities of places may be overconfident where they rest on it)"
        )
    return line


def _score_rows(score: Score) -> list[tuple[str, str, str]]:
    m, e = score.map.counts, score.expected
    return [
        ("precision", _fmt(m.precision), _fmt(e.precision)),
        ("recall", _fmt(m.recall), _fmt(e.recall)),
        ("F1", _fmt(m.f1), _fmt(e.f1)),
        ("TP / FP / FN", f"{m.tp:.0f} / {m.fp:.0f} / {m.fn:.0f}", f"{e.tp:.2f} / {e.fp:.2f} / {e.fn:.2f}"),
        ("places", str(score.map.num_places), f"true: {score.n_true_places} ({score.true_places_from})"),
    ]


def _score_notes(score: Score) -> list[str]:
    notes = [
        f"consistent mass: {score.consistent_mass:.3f} ({CONSISTENT_MASS_MEANING.split(' = ', 1)[1]})",
        f"mass of the exactly-true topology: {_fmt(score.true_topology_mass)}",
        f"mass-weighted mean F1: {score.mean_f1:.3f}",
        f"scored pairs: {score.n_scored_pairs} of {score.n_pairs} ({score.n_same_pairs} same, "
        f"{score.n_different_pairs} different; same < {score.config.same_radius} m, "
        f"different > {score.config.different_radius} m)",
    ]
    if score.n_visits_without_truth:
        notes.append(f"visits without ground truth (unscored): {score.n_visits_without_truth}")
    if score.pairs is not None:
        notes.append(score.pairs.summary())
    return notes


def _topology_rows(ptm: Ptm, score: Score | None, config: ReportConfig) -> list[tuple[str, ...]]:
    rows: list[tuple[str, ...]] = []
    for k, t in enumerate(ptm.topologies[: config.max_rows]):
        row: tuple[str, ...] = (str(k + 1), f"{t.probability:.4f}", str(num_places(t.labels)))
        if score is not None:
            row += (f"{score.topologies[k].counts.f1:.3f}", "yes" if score.topologies[k].consistent else "no")
        rows.append((*row, label_string(t.labels, config.max_label_chars)))
    return rows


def _table_head(score: Score | None) -> list[str]:
    scored = ["F1", "consistent"] if score is not None else []
    return ["rank", "probability", "places", *scored, "labels"]


def _table_title(ptm: Ptm, config: ReportConfig) -> str:
    return f"Top topologies ({min(config.max_rows, len(ptm.topologies))} of {len(ptm.topologies)})"


def _markdown(
    title: str,
    ptm: Ptm,
    score: Score | None,
    figures: list[tuple[str, str]],
    config: ReportConfig,
    *,
    notes: Sequence[str] = (),
    declared: int | None = None,
) -> str:
    out = [f"# {title}", ""]
    out += [f"- {line}" for line in _summary(ptm, notes, declared)]
    if score is not None:
        out += ["", "## Ground truth", "", "| | MAP topology | posterior |", "|---|---|---|"]
        out += [f"| {a} | {b} | {c} |" for a, b, c in _score_rows(score)]
        out += [""] + [f"- {line}" for line in _score_notes(score)]
    out += ["", "## Figures", ""]
    out += [f"![{caption}]({name})" + "\n" for caption, name in figures]
    head = _table_head(score)
    out += [f"## {_table_title(ptm, config)}", ""]
    out += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    out += ["| " + " | ".join(r[:-1]) + f" | `{r[-1]}` |" for r in _topology_rows(ptm, score, config)]
    return "\n".join(out) + "\n"


def _html(
    title: str,
    ptm: Ptm,
    score: Score | None,
    figures: list[tuple[str, str]],
    config: ReportConfig,
    *,
    notes: Sequence[str] = (),
    declared: int | None = None,
) -> str:
    e = html.escape
    out = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{e(title)}</title>",
        "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
        "table{border-collapse:collapse}td,th{border:1px solid #999;padding:2px 8px}"
        "img{max-width:100%}code{font-size:90%}</style></head><body>",
        f"<h1>{e(title)}</h1>",
        "<ul>" + "".join(f"<li>{e(line)}</li>" for line in _summary(ptm, notes, declared)) + "</ul>",
    ]
    if score is not None:
        out.append("<h2>Ground truth</h2><table><tr><th></th><th>MAP topology</th><th>posterior</th></tr>")
        out += [f"<tr><td>{e(a)}</td><td>{e(b)}</td><td>{e(c)}</td></tr>" for a, b, c in _score_rows(score)]
        out.append("</table><ul>" + "".join(f"<li>{e(line)}</li>" for line in _score_notes(score)) + "</ul>")
    out.append("<h2>Figures</h2>")
    out += [
        f'<p><a href="{e(name)}"><img src="{e(name)}" alt="{e(caption)}"></a><br>{e(caption)}</p>'
        for caption, name in figures
    ]
    head = _table_head(score)
    out.append(f"<h2>{e(_table_title(ptm, config))}</h2>")
    out.append("<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>")
    for r in _topology_rows(ptm, score, config):
        cells = "".join(f"<td>{e(c)}</td>" for c in r[:-1])
        out.append(f"<tr>{cells}<td><code>{e(r[-1])}</code></td></tr>")
    out.append("</table></body></html>")
    return "\n".join(out) + "\n"


def _place_extra(src: str | Path, out_dir: Path, taken: set[str], prefix: str) -> str:
    """Copy a figure into ``out_dir`` (unless it is there already) under a name not yet ``taken``."""
    src = Path(src)
    if not src.is_file():
        msg = f"figure {src} does not exist"
        raise DataError(msg)
    name = src.name if src.name not in taken else f"{prefix}_{src.name}"
    if src.resolve() != (out_dir / name).resolve():
        shutil.copyfile(src, out_dir / name)
    taken.add(name)
    return name


def write_report(
    out_dir: str | Path,
    ptm: Ptm,
    *,
    trajectory: ArrayLike | None = None,
    score: Score | None = None,
    surprise_trace: SurpriseTrace | None = None,
    occupancy_map: str | Path | None = None,
    map_comparison: MapComparison | None = None,
    extra_figures: Sequence[str | Path] = (),
    notes: Sequence[str] = (),
    title: str = "Probabilistic topological map",
    config: ReportConfig | None = None,
    chain_trace: Mapping[str, Any] | None = None,
    workers: WorkerPool | None = None,
) -> Path:
    """Write the figures, ``report.md`` and ``report.html`` into ``out_dir``; returns the HTML path.

    ``trajectory`` ``(T, 3)`` (or ``(T, 2)``) odometry or smoothed poses drawn under the topologies;
    ``score`` from :func:`ptm_ros.scoring.evaluation.score_ptm` on this PTM; ``surprise_trace`` the landmark
    detector's :attr:`~ptm_ros.perception.laser_surprise.LaserSurpriseDetector.trace` (drawn unless empty);
    the SRQ plot is drawn from ``chain_trace`` (:func:`load_chain_trace`) or, without it, from the states in
    ``ptm.inference[SRQ_KEY]``; a PTM with only the chains' summary (:data:`CHAINS_KEY`) gets its SRQ
    figures as a line and a note that the plot needs ``ptm-run --trace``; ``occupancy_map`` an image of
    the metric map (shown with :data:`MAP_CAPTION`) and ``extra_figures`` image files to include (both
    copied into ``out_dir`` unless already there); ``map_comparison`` the map side by side with its
    reference or its route graph (:func:`draw_map_comparison`); ``notes`` extra summary lines;
    ``workers`` (optional) draws the figures while the pages are written.
    """
    config = config or ReportConfig()
    if not ptm.topologies:
        msg = "cannot report a PTM without topologies"
        raise DataError(msg)
    traj = None
    if trajectory is not None:
        traj = np.asarray(trajectory, dtype=float)
        if traj.ndim != 2 or traj.shape[1] not in (2, 3) or not np.all(np.isfinite(traj)):
            msg = f"trajectory must be finite (T, 3) or (T, 2) poses, got shape {traj.shape}"
            raise ModelError(msg)
    if score is not None and (
        len(score.topologies) != len(ptm.topologies) or score.n_visits != len(ptm.landmarks)
    ):
        msg = (
            f"the score is of another PTM ({score.n_visits} visits, {len(score.topologies)} topologies; "
            f"this PTM has {len(ptm.landmarks)} and {len(ptm.topologies)})"
        )
        raise DataError(msg)
    chains = chain_states(ptm, chain_trace)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    drawn: list[Future[Path]] = []

    def draw(fn: Callable[..., Path], *args: Any, **kwargs: Any) -> None:
        if workers is None:
            fn(*args, **kwargs)
        else:
            drawn.append(workers.submit(fn, *args, **kwargs))

    draw(draw_histogram, ptm, out / HISTOGRAM, score=score, config=config)
    draw(draw_topologies, ptm, out / TOPOLOGIES, trajectory=traj, score=score, config=config)
    figures = [
        ("PTM histogram", HISTOGRAM),
        (f"Top {min(config.top_k, len(ptm.topologies))} topologies", TOPOLOGIES),
    ]
    if score is not None:
        draw(draw_scores, score, out / SCORES, config=config)
        figures.append(("Scores against ground truth", SCORES))
    if ptm_timeline(ptm):
        truth = score.true_labels if score is not None else None
        draw(draw_timeline, ptm, out / TIMELINE, truth=truth, config=config)
        figures.append((TIMELINE_CAPTION, TIMELINE))
    notes = list(notes)
    declared = None
    if surprise_trace is not None and len(surprise_trace.stamps):
        declared = len(surprise_trace.landmarks)
        draw(draw_surprise, surprise_trace, out / SURPRISE, config=config)
        figures.append(("Bayesian surprise of the landmark detector (thesis Fig. 62)", SURPRISE))
        notes.append(
            f"landmark detector: {len(surprise_trace.stamps)} measurements, "
            f"{len(surprise_trace.landmarks)} landmarks declared by surprise"
        )
    if chains is not None:
        points, missing = chain_srq(chains)
        trapped = f"never visited by chain {', '.join(map(str, missing))}" if missing else ""
        thin = ptm.inference.get(SRQ_THIN_KEY)
        every = f"states, one per {thin} sweeps" if isinstance(thin, int) and thin > 1 else "states"
        note = f"atom: the state most visited over all chains ({sum(map(len, chains))} {every})"
        draw(draw_srq, points, out / SRQ, config=config, note=note + (f"; {trapped}" if trapped else ""))
        figures.append(("Scaled regeneration quantiles of the MCMC chains (thesis Fig. 42)", SRQ))
        devs = ", ".join(f"{name} {srq_deviation(x, y):.3f}" for name, (x, y) in points.items())
        notes.append(f"SRQ max |y − x| (0 = ideal mixing): {devs}" + (f"; atom {trapped}" if trapped else ""))
    elif isinstance(summary := ptm.inference.get(CHAINS_KEY), Mapping):
        notes.append(srq_summary_line(summary))
    taken = {HISTOGRAM, TOPOLOGIES, SCORES, SURPRISE, SRQ, TIMELINE, MAP_COMPARISON, REPORT_MD, REPORT_HTML}
    if occupancy_map is not None:
        figures.append((MAP_CAPTION, _place_extra(occupancy_map, out, taken, "map")))
    if map_comparison is not None:
        caption = REFERENCE_CAPTION if map_comparison.reference is not None else ROUTES_CAPTION
        draw(draw_map_comparison, map_comparison, out / MAP_COMPARISON, config=config)
        figures.append((caption, MAP_COMPARISON))
    figures += [(Path(f).stem, _place_extra(f, out, taken, f"extra{k}")) for k, f in enumerate(extra_figures)]
    md = _markdown(title, ptm, score, figures, config, notes=notes, declared=declared)
    (out / REPORT_MD).write_text(md, encoding="utf-8")
    html_path = out / REPORT_HTML
    page = _html(title, ptm, score, figures, config, notes=notes, declared=declared)
    html_path.write_text(page, encoding="utf-8")
    for future in drawn:
        future.result()  # a figure's error is the report's
    return html_path
