"""The surprise figure of the report: the landmark detector's Bayesian surprise (thesis Ch. 4.7.3, Fig. 62).

Actual surprise per measurement against time, the predicted surprise mean with its band ``mean ± k·std``
shaded (the upper edge is the detector's threshold), the surprise maxima that fired a landmark ringed (above
the band, by the detector's rule) and the landmarks as declared (dotted lines: a laser detector places each
at the most open scan near its maximum): :func:`surprise_figure`, :func:`draw_surprise`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ptm_ros.errors import DataError
from ptm_ros.reporting.plots import ReportConfig, _new_figure

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from ptm_ros.perception.surprise import SurpriseTrace


def fired_indices(trace: SurpriseTrace) -> NDArray[np.intp]:
    """``(L,)`` indices of the trace's measurements at which its landmarks were declared.

    Among measurements sharing a landmark's stamp the most surprising one is taken.

    Raises:
        DataError: a landmark stamp that is not the stamp of any measurement of the trace.
    """
    return _indices(trace, trace.landmarks, "landmark")


def trigger_indices(trace: SurpriseTrace) -> NDArray[np.intp]:
    """Indices of the trace's measurements whose surprise fired a landmark: the maxima above the band
    (:class:`ptm_ros.perception.surprise.BandTrigger`, ``trace.triggers``); the landmarks' own measurements
    for a trace without triggers. Raises :class:`DataError` as :func:`fired_indices` does."""
    if trace.triggers is None:
        return fired_indices(trace)
    return _indices(trace, trace.triggers, "trigger")


def _indices(trace: SurpriseTrace, at: ArrayLike, what: str) -> NDArray[np.intp]:
    stamps = np.asarray(trace.stamps, dtype=float)
    surprise = np.asarray(trace.surprise, dtype=float)
    wanted = np.asarray(at, dtype=float).reshape(-1)
    out = np.empty(len(wanted), dtype=np.intp)
    for k, stamp in enumerate(wanted.tolist()):
        tol = 1e-9 * max(1.0, abs(stamp))
        lo = int(np.searchsorted(stamps, stamp - tol, side="left"))
        hi = int(np.searchsorted(stamps, stamp + tol, side="right"))
        if hi <= lo:
            msg = f"{what} stamp {stamp:.9f} is not the stamp of a measurement of the surprise trace"
            raise DataError(msg)
        out[k] = lo + int(np.argmax(surprise[lo:hi]))
    return out


def _check_trace(trace: SurpriseTrace) -> None:
    n = len(trace.stamps)
    if n == 0:
        msg = "the surprise trace is empty"
        raise DataError(msg)
    fields = ("surprise", "predicted_mean", "predicted_std", "upper")
    shapes = {name: np.shape(getattr(trace, name)) for name in ("stamps", *fields)}
    if any(shape != (n,) for shape in shapes.values()):
        msg = f"surprise trace fields must all be (T,) arrays, got shapes {shapes}"
        raise DataError(msg)
    stamps = np.asarray(trace.stamps, dtype=float)
    if not np.all(np.isfinite(stamps)) or np.any(np.diff(stamps) < 0.0):
        msg = "surprise trace stamps must be finite and non-decreasing"
        raise DataError(msg)


def _band_sigmas(trace: SurpriseTrace) -> float | None:
    """``k`` of the band ``upper = mean + k·std`` (median over measurements with ``std > 0``)."""
    std = np.asarray(trace.predicted_std, dtype=float)
    ok = std > 0.0
    if not ok.any():
        return None
    width = np.asarray(trace.upper, dtype=float) - np.asarray(trace.predicted_mean, dtype=float)
    return float(np.median(width[ok] / std[ok]))


def surprise_figure(trace: SurpriseTrace, *, config: ReportConfig) -> Figure:
    """The surprise figure (thesis Fig. 62) of a detector's trace, not yet saved.

    Time runs from the first measurement. The band is ``[max(0, mean - k·std), mean + k·std]``; its top
    (dashed) is the detector's threshold. The detector's rule
    (:class:`ptm_ros.perception.surprise.BandTrigger`): a landmark fires at the first maximum of each run of
    measurements above the band; these maxima are ringed (so every ring lies above the band). A laser detector
    then places the landmark at the most open scan within ``localize_distance`` of travel (usually inside the
    band): dotted vertical lines at the declared landmarks (through the rings when nothing was moved). On a
    log axis (:attr:`ReportConfig.surprise_log_scale`) values are floored at half the smallest positive one.
    Artists carry ids for inspection (``gid``): ``"surprise"`` (actual), ``"predicted_mean"``,
    ``"upper"``, ``"band"``, ``"triggers"`` (a scatter at ``(time, surprise)`` of
    :func:`trigger_indices`) and ``"landmarks"`` (vertical lines at the times of :func:`fired_indices`).
    """
    _check_trace(trace)
    stamps = np.asarray(trace.stamps, dtype=float)
    surprise = np.asarray(trace.surprise, dtype=float)
    mean = np.asarray(trace.predicted_mean, dtype=float)
    upper = np.asarray(trace.upper, dtype=float)
    lower = 2.0 * mean - upper  # mean - k·std
    placed = fired_indices(trace)
    fired = trigger_indices(trace)
    moved = placed.shape != fired.shape or bool(np.any(stamps[placed] != stamps[fired]))
    t = stamps - stamps[0]
    positive = np.concatenate([surprise, mean, upper])
    positive = positive[np.isfinite(positive) & (positive > 0.0)]
    log_scale = config.surprise_log_scale and positive.size > 0
    floor = 0.5 * float(positive.min()) if log_scale else -math.inf

    def shown(v: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.maximum(v, floor)

    fig = _new_figure(10.0, 4.4)
    ax = fig.add_subplot()
    k = _band_sigmas(trace)
    band = "band: predicted mean ± " + (f"{k:.3g}σ" if k is not None else "k·σ")
    ax.fill_between(
        t,
        shown(np.maximum(lower, 0.0)),
        shown(upper),
        color="tab:orange",
        alpha=0.25,
        lw=0,
        label=band,
        gid="band",
    )
    ax.plot(t, shown(upper), color="tab:orange", lw=0.6, ls="--", label="threshold (band top)", gid="upper")
    ax.plot(
        t, shown(mean), color="tab:orange", lw=1.0, label="predicted surprise (mean)", gid="predicted_mean"
    )
    ax.plot(t, shown(surprise), color="tab:blue", lw=0.8, label="actual surprise", gid="surprise")
    top = float(shown(np.concatenate([surprise, upper])).max())
    ax.vlines(
        t[placed],
        floor if log_scale else 0.0,
        top,
        color="tab:red",
        lw=0.8,
        ls=":",
        label=f"landmarks ({placed.size})" + (": where placed" if moved else ""),
        gid="landmarks",
    )
    ax.scatter(
        t[fired],
        shown(surprise[fired]),
        s=30,
        marker="o",
        facecolors="none",
        edgecolors="tab:red",
        linewidths=1.2,
        zorder=5,
        label=f"surprise maxima that fired ({fired.size})",
        gid="triggers",
    )
    if log_scale:
        ax.set_yscale("log")
        ax.set_ylim(bottom=floor)
    else:
        ax.set_ylim(bottom=0.0)
    ax.set_xlim(float(t[0]), float(t[-1]) if t[-1] > t[0] else float(t[0]) + 1.0)
    ax.set_xlabel(f"time [s] since the first measurement (stamp {stamps[0]:.3f})")
    ax.set_ylabel("surprise KL(after ‖ before) [nats]")
    fig.legend(loc="outside lower center", ncols=3, fontsize=8)
    rule = "a landmark fires at the first maximum of each run above the band (rings)"
    if moved:
        rule += ",\nthen is placed at the most open scan nearby (dotted lines: the landmarks)"
    ax.set_title(
        f"Bayesian surprise (thesis Fig. 62): {len(t)} measurements, {placed.size} landmarks\n{rule}",
        fontsize=9,
    )
    return fig


def draw_surprise(trace: SurpriseTrace, path: Path, *, config: ReportConfig) -> Path:
    """Write the surprise figure (:func:`surprise_figure`) of a detector's trace to ``path``."""
    fig = surprise_figure(trace, config=config)
    fig.savefig(path, dpi=config.dpi)
    return path
