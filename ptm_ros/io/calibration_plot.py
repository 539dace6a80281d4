"""Reliability diagrams of the MAP probability (issue #23): a PNG drawn through matplotlib's Agg canvas.

Top panel: the fraction of runs whose MAP topology is the true one against the mean stated MAP
probability, per equal-width bin (:class:`ptm_ros.scoring.evaluation.CalibrationSummary`), one curve per group
(e.g. per world family), marker area proportional to the bin's runs; the diagonal is perfect calibration.
Bottom panel: the number of runs per bin.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np

from ptm_ros.scoring.evaluation import CalibrationSummary


def write_reliability_diagram(
    path: str | Path, summaries: Mapping[str, CalibrationSummary], *, title: str = "MAP calibration"
) -> Path:
    """Write the reliability diagram of ``summaries`` (label -> summary, drawn in order) to ``path``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6.4, 7.0), layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, height_ratios=(3, 1), sharex=True)
    top.plot([0, 1], [0, 1], color="0.6", linestyle="--", linewidth=1, label="calibrated")
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
    top.set_xlim(0, 1)
    top.set_ylim(-0.02, 1.02)
    top.set_ylabel("fraction of runs whose MAP topology is the true one")
    top.set_title(title)
    top.legend(loc="upper left", fontsize=7)
    top.grid(alpha=0.3)
    bottom.set_xlabel("stated MAP probability")
    bottom.set_ylabel("runs")
    bottom.grid(alpha=0.3)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    return out
