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

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ptm_ros.scoring.evaluation import CalibrationSummary, PairReliability, ReliabilityBin

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure
    from numpy.typing import NDArray


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


def _group(  # noqa: PLR0917 - one curve's parts
    top: Axes,
    bottom: Axes,
    bins: Sequence[ReliabilityBin],
    sizes: NDArray[np.float64],
    label: str,
    slot: tuple[int, int],
) -> None:
    """One group's curve over its non-empty ``bins`` (marker areas ``sizes``, one per bin) above, and its
    bars of counts below, in bar slot ``slot = (group, groups)`` of each bin."""
    shown = np.array([b.count > 0 for b in bins])
    x = np.array([b.mean_probability for b in bins])[shown]
    y = np.array([b.accuracy for b in bins])[shown]
    line = top.plot(x, y, marker="", linewidth=1.2, label=label)[0]
    top.scatter(x, y, s=sizes[shown], color=line.get_color(), alpha=0.8, zorder=3)
    widths = np.array([b.hi - b.lo for b in bins]) / (slot[1] + 1)
    lefts = np.array([b.lo for b in bins]) + widths * (slot[0] + 0.5)
    bottom.bar(lefts, [b.count for b in bins], width=widths, align="edge", color=line.get_color())


def write_reliability_diagram(
    path: str | Path, summaries: Mapping[str, CalibrationSummary], *, title: str = "MAP calibration"
) -> Path:
    """Write the reliability diagram of ``summaries`` (label -> summary, drawn in order) to ``path``."""
    fig, top, bottom = _panels()
    for g, (label, s) in enumerate(summaries.items()):
        _group(
            top,
            bottom,
            s.bins,
            12.0 + 300.0 * np.array([b.count for b in s.bins]) / max(1, s.n_runs),
            f"{label}: ECE {s.ece:.2f} (chance {s.chance_ece:.2f}), n={s.n_runs}",
            (g, len(summaries)),
        )
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
    for g, (label, t) in enumerate(tables.items()):
        gap = "none doubtful" if not t.doubtful else f"doubtful gap {t.doubtful_gap:.2f} over {t.doubtful}"
        size = 12.0 + 40.0 * np.log10(np.maximum(np.array(t.count, dtype=float), 1.0))
        _group(top, bottom, t.bins, size, f"{label}: {sum(t.count)} pairs, {gap}", (g, len(tables)))
    top.set_ylabel("share of visit pairs that are one place in truth")
    top.set_title(title)
    top.legend(loc="upper left", fontsize=7)
    bottom.set_yscale("log")
    bottom.set_xlabel("stated P(same place)")
    bottom.set_ylabel("pairs")
    return _save(fig, path)
