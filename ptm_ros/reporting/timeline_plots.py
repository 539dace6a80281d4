"""The timeline figure of the report: how the mass moved as the visits arrived (issue #25).

Drawn when ``ptm.inference`` holds the particle filter's timeline (:func:`ptm_ros.model.ptm.ptm_timeline`):
after each visit the mass of the most probable topology (bars), of the true topology of the visits so far
(with a ground truth) and of the greedy baseline's answer (when ptm.json has one), each cut to the visits so
far (:func:`ptm_ros.scoring.evaluation.timeline_masses`); without a truth, the two most probable
(:func:`timeline_figure`, :func:`draw_timeline`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from ptm_ros.errors import DataError
from ptm_ros.model.partitions import IntSequence, Labels
from ptm_ros.model.ptm import Ptm, TimelineStep, ptm_greedy, ptm_timeline
from ptm_ros.reporting.plots import ReportConfig, _new_figure
from ptm_ros.scoring.evaluation import first_wrong_visit, timeline_masses, unlisted_bound

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def _mass_track(
    steps: Sequence[TimelineStep], labels: IntSequence
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Per visit the listed mass of ``labels`` cut to the visits so far, and whether it was listed (an
    unlisted one is drawn at :func:`ptm_ros.scoring.evaluation.unlisted_bound`, the most it can hold)."""
    masses = timeline_masses(steps, labels)
    listed = np.array([m is not None for m in masses])
    values = np.array([unlisted_bound(st) if m is None else m for st, m in zip(steps, masses, strict=True)])
    return values, listed


def timeline_figure(
    steps: Sequence[TimelineStep], *, truth: Labels | None = None, greedy: Labels | None = None
) -> Figure:
    """The timeline figure (module docstring), not yet saved: x = the newest visit's index. Artists carry
    ids (``gid``): ``"top"`` (the bars), ``"truth"``, ``"greedy"`` or ``"second"`` (lines), ``"commit"``
    (the greedy baseline's first wrong decision)."""
    if not steps:
        msg = "the timeline figure needs at least one step"
        raise DataError(msg)
    fig = _new_figure(max(6.0, 0.35 * len(steps) + 3.0), 4.2)
    ax = fig.add_subplot()
    x = np.array([st.visits - 1 for st in steps])
    top = np.array([st.topologies[0][1] if st.topologies else 0.0 for st in steps])
    ax.bar(
        x,
        top,
        width=0.8,
        color="0.85",
        edgecolor="0.6",
        linewidth=0.5,
        label="most probable topology",
        gid="top",
    )
    tracks: list[tuple[str, IntSequence, str, str, str]] = []
    if greedy is not None:
        tracks.append(("greedy baseline's answer so far", greedy, "tab:red", "s", "greedy"))
    if truth is not None:
        tracks.append(("true topology of the visits so far", truth, "tab:green", "o", "truth"))
    else:
        second = [st.topologies[1][1] if len(st.topologies) > 1 else 0.0 for st in steps]
        ax.plot(
            x, second, color="tab:blue", marker="o", linewidth=1.2, label="second most probable", gid="second"
        )
    unlisted = False
    for z, (name, labels, color, marker, gid) in enumerate(tracks, start=2):
        values, listed = _mass_track(steps, labels)
        ax.plot(x, values, color=color, linewidth=1.5, label=name, zorder=z, gid=gid)
        ax.scatter(x[listed], values[listed], color=color, marker=marker, zorder=z)
        ax.scatter(x[~listed], values[~listed], facecolors="white", edgecolors=color, marker=marker, zorder=z)
        unlisted |= not listed.all()
    if greedy is not None and truth is not None:
        wrong = first_wrong_visit(greedy, truth)
        if wrong is not None:
            ax.axvline(wrong, color="tab:red", linestyle=":", linewidth=1.0, gid="commit")
            ax.annotate(
                f" greedy commits, wrongly (visit {wrong})", (wrong, 0.02), fontsize=7, color="tab:red"
            )
    ax.set_xticks(x)
    ax.tick_params(labelsize=7)
    ax.set_xlim(x[0] - 0.6, x[-1] + 0.6)
    ax.set_ylim(0.0, 1.05)
    ax.set_xlabel("visit (the newest one)")
    ax.set_ylabel("posterior probability")
    hollow = "\n(hollow marker: not among the listed topologies, at most this)" if unlisted else ""
    ax.set_title(f"How the mass moved as the visits arrived{hollow}", fontsize=9)
    ax.legend(loc="center left", fontsize=7)
    return fig


def draw_timeline(ptm: Ptm, path: Path, *, truth: Labels | None, config: ReportConfig) -> Path:
    """Write the timeline figure (:func:`timeline_figure`) of a PTM's timeline to ``path``, with the
    greedy baseline's answer when ptm.json has one."""
    fig = timeline_figure(ptm_timeline(ptm), truth=truth, greedy=ptm_greedy(ptm))
    fig.savefig(path, dpi=config.dpi)
    return path
