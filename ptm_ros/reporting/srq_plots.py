"""The SRQ figure of the report: the scaled regeneration quantile plot of MCMC chains (thesis Ch. 3.6,
Fig. 42; :mod:`ptm_ros.inference.convergence`), every chain at one atom, the state most visited over all
chains (:func:`ptm_ros.reporting.chain_trace.chain_srq`): :func:`srq_figure`, :func:`draw_srq`.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ptm_ros.errors import DataError
from ptm_ros.inference.convergence import srq_deviation
from ptm_ros.reporting.chain_trace import SrqPoints
from ptm_ros.reporting.plots import ReportConfig, _new_figure

if TYPE_CHECKING:
    from matplotlib.figure import Figure


def srq_figure(points_by_chain: Mapping[str, SrqPoints], *, note: str = "") -> Figure:
    """The SRQ plot (thesis Fig. 42) of several chains, not yet saved.

    ``points_by_chain``: chain name → ``(x, y)`` from :func:`ptm_ros.inference.convergence.srq_points`. Each
    chain is a line from the origin through its points (``gid`` = the chain's name), the unit-slope
    line is dashed (``gid`` ``"diagonal"``); ``note`` is added to the title.
    """
    if not points_by_chain:
        msg = "the SRQ plot needs at least one chain"
        raise DataError(msg)
    fig = _new_figure(6.0, 6.0)
    ax = fig.add_subplot()
    ax.plot([0.0, 1.0], [0.0, 1.0], color="black", ls="--", lw=0.8, label="unit slope", gid="diagonal")
    for name, (x, y) in points_by_chain.items():
        dev = srq_deviation(x, y)
        xs = np.concatenate([[0.0], np.asarray(x, dtype=float)])
        ys = np.concatenate([[0.0], np.asarray(y, dtype=float)])
        marker = "." if len(xs) <= 200 else None
        ax.plot(
            xs,
            ys,
            lw=1.0,
            marker=marker,
            ms=3,
            label=f"{name}: R = {len(xs) - 1}, max |y − x| = {dev:.3f}",
            gid=name,
        )
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.set_aspect("equal")
    ax.set_xlabel(r"regeneration count  $i\,/\,R$")
    ax.set_ylabel(r"regeneration time  $T_i\,/\,T_R$")
    ax.legend(loc="upper left", fontsize=8)
    title = "Scaled regeneration quantiles (thesis Fig. 42)\nnear the unit slope: the chain mixes"
    ax.set_title(title + (f"\n{note}" if note else ""), fontsize=9)
    return fig


def draw_srq(
    points_by_chain: Mapping[str, SrqPoints], path: Path, *, config: ReportConfig, note: str = ""
) -> Path:
    """Write the SRQ plot (:func:`srq_figure`) of several chains to ``path``."""
    fig = srq_figure(points_by_chain, note=note)
    fig.savefig(path, dpi=config.dpi)
    return path
