"""What every figure of the report (:mod:`ptm_ros.reporting.report`) shares: its sizes
(:class:`ReportConfig`), a topology's compact label string (:func:`label_string`, for ticks and tables) and
a new figure (:func:`_new_figure`).

Matplotlib is imported lazily and drawn through its Agg canvas (no display, no pyplot state); large
PTMs stay quick because bars, tables and panels are capped and points/lines are drawn as collections.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

from ptm_ros.errors import ConfigError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_DIGITS = "0123456789abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ"


@dataclass(frozen=True)
class ReportConfig:
    """Sizes of the report.

    Attributes:
        top_k: topologies drawn over the trajectory.
        max_bars: topologies in the histogram.
        max_rows: topologies in the markdown/HTML table.
        max_label_chars: longest label string shown before it is shortened with "…".
        dpi: resolution of the PNGs.
        surprise_log_scale: draw the surprise on a log axis (it spans orders of magnitude: the band
            sits near the predicted mean while a change of place can be 10-100 times above it).
    """

    top_k: int = 4
    max_bars: int = 20
    max_rows: int = 20
    max_label_chars: int = 40
    dpi: int = 100
    surprise_log_scale: bool = True

    def __post_init__(self) -> None:
        for name in ("top_k", "max_bars", "max_rows", "dpi"):
            if getattr(self, name) < 1:
                msg = f"ReportConfig.{name} must be >= 1, got {getattr(self, name)}"
                raise ConfigError(msg)
        if self.max_label_chars < 4:
            msg = f"ReportConfig.max_label_chars must be >= 4, got {self.max_label_chars}"
            raise ConfigError(msg)


def label_string(labels: Sequence[int], max_chars: int | None = None) -> str:
    """Compact label string: one character per visit (``0-9a-zA-Z``) up to 62 places, else dotted.

    ``(0, 1, 2, 0)`` → ``"0120"``; shortened to ``max_chars`` with a middle "…" when given.
    """
    if not labels:
        text = "∅"
    elif max(labels) < len(_DIGITS):
        text = "".join(_DIGITS[v] for v in labels)
    else:
        text = ".".join(str(v) for v in labels)
    if max_chars is not None and len(text) > max_chars:
        head = (max_chars - 1) // 2
        text = text[:head] + "…" + text[len(text) - (max_chars - 1 - head) :]
    return text


def _new_figure(width: float, height: float) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), layout="constrained")
    FigureCanvasAgg(fig)
    return fig
