"""Reliability diagrams (issue #23): PNGs drawn through matplotlib's Agg canvas.

MAP calibration: top panel, the fraction of runs whose MAP topology is the true one against the mean
stated MAP probability, per equal-width bin (:class:`ptm_ros.scoring.evaluation.CalibrationSummary`), one
curve per group (e.g. per world family), marker area proportional to the bin's runs; the diagonal is
perfect calibration. Bottom panel: the number of runs per bin.

Pair calibration (:class:`ptm_ros.scoring.evaluation.PairReliability`, any run with a trajectory): the
share of visit pairs that are one place in truth against their mean stated ``P(i ~ j)``, per bin; the
bottom panel counts the pairs on a log scale (the end bins hold nearly all of them).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ptm_ros.scoring.evaluation import CalibrationSummary, PairReliability

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure


def _panels() -> tuple[Figure, Axes, Axes]:
    """A figure with the reliability panel above the counts panel, the diagonal drawn."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 7.0), layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, height_ratios=(3, 1), sharex=True)
    top.plot([0, 1], [0, 1], color="0.6", linestyle="--", linewidth=1, label="calibrated")
    top.set_xlim(0, 1)
    top.set_ylim(-0.02, 1.02)
    top.grid(alpha=0.3)
    bottom.grid(alpha=0.3)
    return fig, top, bottom


def _save(fig: Figure, path: str | Path) -> Path:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    return out


def write_reliability_diagram(
    path: str | Path, summaries: Mapping[str, CalibrationSummary], *, title: str = "MAP calibration"
) -> Path:
    """Write the reliability diagram of ``summaries`` (label -> summary, drawn in order) to ``path``."""
    fig, top, bottom = _panels()
    n_groups = max(1, len(summaries))
    for g, (label, s) in enumerate(summaries.items()):
        bins = [b for b in s.bins if b.count > 0]
        x = np.array([b.mean_probability for b in bins])
        y = np.array([b.accuracy for b in bins])
        size = 12.0 + 300.0 * np.array([b.count for b in bins]) / max(1, s.n_runs)
        line = top.plot(x, y, marker="", linewidth=1.2)[0]
        top.scatter(x, y, s=size, color=line.get_color(), alpha=0.8, zorder=3)
        line.set_label(f"{label}: ECE {s.ece:.2f} (chance {s.chance_ece:.2f}), n={s.n_runs}")
        width = 1.0 / s.n_bins / (n_groups + 1)
        lefts = np.array([b.lo for b in s.bins]) + width * (g + 0.5)
        bottom.bar(lefts, [b.count for b in s.bins], width=width, align="edge", color=line.get_color())
    top.set_ylabel("fraction of runs whose MAP topology is the true one")
    top.set_title(title)
    top.legend(loc="upper left", fontsize=7)
    bottom.set_xlabel("stated MAP probability")
    bottom.set_ylabel("runs")
    return _save(fig, path)


def write_pair_reliability_diagram(
    path: str | Path, tables: Mapping[str, PairReliability], *, title: str = "Pair calibration"
) -> Path:
    """Write the pair reliability diagram of ``tables`` (label -> pooled table, in order) to ``path``."""
    fig, top, bottom = _panels()
    n_groups = max(1, len(tables))
    for g, (label, t) in enumerate(tables.items()):
        bins = [b for b in t.bins if b.count > 0]
        x = np.array([b.mean_probability for b in bins])
        y = np.array([b.accuracy for b in bins])
        size = 12.0 + 40.0 * np.log10(np.array([b.count for b in bins], dtype=float))
        line = top.plot(x, y, marker="", linewidth=1.2)[0]
        top.scatter(x, y, s=size, color=line.get_color(), alpha=0.8, zorder=3)
        gap = "none doubtful" if not t.doubtful else f"doubtful gap {t.doubtful_gap:.2f} over {t.doubtful}"
        line.set_label(f"{label}: {sum(t.count)} pairs, {gap}")
        widths = np.diff(t.edges) / (n_groups + 1)
        lefts = np.array(t.edges[:-1]) + widths * (g + 0.5)
        bottom.bar(lefts, np.asarray(t.count), width=widths, align="edge", color=line.get_color())
    top.set_ylabel("share of visit pairs that are one place in truth")
    top.set_title(title)
    top.legend(loc="upper left", fontsize=7)
    bottom.set_yscale("log")
    bottom.set_xlabel("stated P(same place)")
    bottom.set_ylabel("pairs")
    return _save(fig, path)
