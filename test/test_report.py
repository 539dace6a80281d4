"""Tests of ptm_ros.reporting.report and the modules it draws with (plots, topology_plots, map_plots,
surprise_plots, timeline_plots, srq_plots, chain_trace): figures, report.md and report.html of a PTM."""

from __future__ import annotations

import re
from dataclasses import replace
from functools import cache
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.image import imread

from ptm_ros.errors import ConfigError, DataError, ModelError
from ptm_ros.inference.convergence import srq_deviation, srq_points
from ptm_ros.model.ptm import Landmark, Ptm, Topology, load_ptm, make_ptm, save_ptm
from ptm_ros.perception.laser_surprise import LaserSurpriseConfig, LaserSurpriseDetector
from ptm_ros.perception.surprise import SurpriseTrace
from ptm_ros.reporting.chain_trace import (
    CHAINS_KEY,
    SRQ_KEY,
    SRQ_LABELS_KEY,
    SRQ_THIN_KEY,
    TRACE,
    TRACE_SCHEMA,
    chain_srq,
    chain_states,
    find_chain_trace,
    load_chain_trace,
    save_chain_trace,
    split_chain_trace,
)
from ptm_ros.reporting.map_plots import MapComparison, draw_map_comparison, draw_route_graph
from ptm_ros.reporting.plots import ReportConfig, label_string
from ptm_ros.reporting.report import (
    CONSISTENT_MASS_MEANING,
    HISTOGRAM,
    MAP_CAPTION,
    MAP_COMPARISON,
    REFERENCE_CAPTION,
    REPORT_HTML,
    REPORT_MD,
    ROUTES_CAPTION,
    SCORES,
    SRQ,
    SURPRISE,
    TOPOLOGIES,
    inference_line,
    write_report,
)
from ptm_ros.reporting.srq_plots import draw_srq, srq_figure
from ptm_ros.reporting.surprise_plots import fired_indices, surprise_figure, trigger_indices
from ptm_ros.reporting.topology_plots import place_edges, place_positions
from ptm_ros.scoring.evaluation import score_ptm

# A square loop driven twice: corners A B C D A B C D (odometry drifts a little).
TRUE_XY = np.array([[0, 0], [10, 0], [10, 10], [0, 10]] * 2, dtype=float)
ODOM_XY = TRUE_XY + np.linspace(0, 1, 8)[:, None] * [0.6, -0.4]
TRUTH = (0, 1, 2, 3, 0, 1, 2, 3)


def loop_ptm() -> Ptm:
    landmarks = [Landmark(i, 2.0 * i, (float(x), float(y), 0.0)) for i, (x, y) in enumerate(ODOM_XY)]
    weighted = {
        TRUTH: 0.6,
        (0, 1, 2, 3, 4, 5, 6, 7): 0.2,
        (0, 1, 2, 3, 0, 1, 2, 4): 0.1,
        (0, 1, 0, 1, 0, 1, 0, 1): 0.05,
    }
    positions = {TRUTH: [[0.1, 0.0], [10.2, -0.1], [10.3, 9.9], [0.2, 10.1]]}
    return make_ptm(landmarks, weighted, positions=positions, inference={"method": "exact"})


class _Links(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.links: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.links += [v for k, v in attrs if k in ("href", "src") and v is not None]


def html_links(path: Path) -> list[str]:
    parser = _Links()
    parser.feed(path.read_text(encoding="utf-8"))
    return parser.links


def test_report_files_exist_are_valid_and_links_resolve(tmp_path: Path) -> None:
    ptm = loop_ptm()
    score = score_ptm(ptm, TRUE_XY, true_places=TRUTH)
    extra = tmp_path / "elsewhere" / "surprise.png"
    extra.parent.mkdir()
    Figure(figsize=(2, 2), facecolor="red").savefig(extra)
    out = tmp_path / "report"
    traj = np.column_stack([ODOM_XY, np.zeros(8)])
    html_path = write_report(out, ptm, trajectory=traj, score=score, extra_figures=[extra], title="loop <x>")
    assert html_path == out / REPORT_HTML
    for name in (HISTOGRAM, TOPOLOGIES, SCORES, "surprise.png"):
        img = imread(out / name)
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
        assert float(img[..., :3].std()) > 0.0  # not a blank canvas
    links = html_links(html_path)
    assert {HISTOGRAM, TOPOLOGIES, SCORES, "surprise.png"} <= set(links)
    for link in links:
        assert not Path(link).is_absolute() and (out / link).is_file()
    md = (out / REPORT_MD).read_text(encoding="utf-8")
    md_links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert set(md_links) == {HISTOGRAM, TOPOLOGIES, SCORES, "surprise.png"}
    assert all((out / link).is_file() for link in md_links)
    # the tables: topologies ranked by mass, scores of the MAP topology
    assert "| 1 | 0.6000 | 4 | 1.000 | yes | `01230123` |" in md
    assert "| 2 | 0.2000 | 8 | 0.000 | no | `01234567` |" in md
    assert "| precision | 1.000 |" in md
    assert "loop &lt;x&gt;" in html_path.read_text(encoding="utf-8")  # title escaped in HTML


#: A filter's ptm.json ``inference`` as it was written before issue #25.
RBPF_INFERENCE = {
    "method": "rbpf",
    "particles": 100,
    "seed": 0,
    "resample": "optimal",
    "n_topologies": 100,
    "ess": 13.306258008956153,
    "log_evidence": 278.8545398789153,
    "update_ms_median": 175.50218549999386,
    "update_ms_p95": 200.7758070496491,
}


@pytest.mark.slow
def test_the_report_speaks_plainly(tmp_path: Path) -> None:
    """Issue #25: rounded figures (no "ess 13.306258008956153"), the consistent mass explained where it is
    shown, and the visits reconciled with the landmarks the detector declared."""
    assert inference_line(RBPF_INFERENCE) == (
        "method: rbpf (particles 100, seed 0, resampling optimal, distinct topologies held 100, "
        "ESS 13.3/100, log evidence 278.9 nats, update time median 176 ms, 95th percentile 201 ms)"
    )
    adaptive = inference_line({**RBPF_INFERENCE, "particles_peak": 840})  # with inference.particles_max
    assert adaptive.startswith("method: rbpf (particles 100, most held 840, seed 0,")
    mcmc = {"method": "mcmc", "seed": 3, "estimate": "visited", "samples": 8000, "doubling_tv": 0.00123456}
    assert inference_line(mcmc) == "method: mcmc (seed 3, estimate visited, samples 8000)"  # TVs: own line
    other = {"method": "magic", "tv": 0.123456789, "done": True, "states": [1, 2]}
    assert inference_line(other) == "method: magic (tv 0.123, done yes)"
    base = loop_ptm()
    skipped = {"landmark-at-same-odometry-sample": 2, "scan-malformed": 5}
    ptm = replace(base, inference=RBPF_INFERENCE, extra={"diagnostics": {"skipped": skipped}})
    score = score_ptm(ptm, TRUE_XY, true_places=TRUTH)
    write_report(tmp_path, ptm, score=score)
    md = (tmp_path / REPORT_MD).read_text(encoding="utf-8")
    assert re.findall(r"\d\.\d{5,}", md) == []  # no float printed in full
    assert "ESS 13.3/100" in md and "update time median 176 ms" in md
    assert (
        "- visits: 8; topologies listed: 4, listed mass 0.950 (the detector declared 10 landmarks and 8 "
        "became visits: 2 dropped (2 fell on the odometry sample of the visit before"
    ) in md
    assert (
        f"consistent mass: {score.consistent_mass:.3f} (the posterior mass of the topologies that put no "
        in md
    )
    assert CONSISTENT_MASS_MEANING.split(" = ", 1)[1] in md
    assert score.pairs is not None and f"- {score.pairs.summary()}" in md
    assert "pair calibration: " in md and "confident misses (same, stated < 0.02)" in md
    trace = step_trace()  # two landmarks declared by surprise, fewer than the 8 visits: no accounting
    write_report(tmp_path / "t", base, surprise_trace=trace)
    md = (tmp_path / "t" / REPORT_MD).read_text(encoding="utf-8")
    assert "the detector declared 8 landmarks" not in md  # 2 declared < 8 visits: another run's trace
    assert "- visits: 8; topologies listed: 4, listed mass 0.950\n" in md


def test_without_score_no_score_figure_and_deterministic(tmp_path: Path) -> None:
    ptm = loop_ptm()
    write_report(tmp_path / "a", ptm)
    write_report(tmp_path / "b", ptm)
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == sorted([HISTOGRAM, TOPOLOGIES, REPORT_MD, REPORT_HTML])
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    md = (tmp_path / "a" / REPORT_MD).read_text(encoding="utf-8")
    assert "consistent" not in md and "Ground truth" not in md
    assert "| 1 | 0.6000 | 4 | `01230123` |" in md


def test_large_ptm_renders_with_capped_tables(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    n, m = 300, 60
    xy = rng.uniform(0, 50, size=(m, 2))[np.arange(n) % m] + rng.normal(0, 0.3, size=(n, 2))
    landmarks = [Landmark(i, float(i), (float(x), float(y), 0.0)) for i, (x, y) in enumerate(xy)]
    base = np.arange(n) % m
    weighted = []
    for _ in range(200):
        lab = base.copy()
        lab[rng.integers(0, n, size=3)] = rng.integers(0, m + 5, size=3)
        weighted.append((tuple(lab.tolist()), rng.uniform()))
    total = sum(p for _, p in weighted)
    ptm = make_ptm(landmarks, [(lab, p / total) for lab, p in weighted])
    score = score_ptm(ptm, xy)
    cfg = ReportConfig(max_rows=7, max_bars=15, top_k=2, dpi=60)
    write_report(tmp_path, ptm, score=score, config=cfg)
    md = (tmp_path / REPORT_MD).read_text(encoding="utf-8")
    rows = [line for line in md.splitlines() if re.match(r"\| \d+ \|", line)]
    assert len(rows) == 7
    assert f"Top topologies (7 of {len(ptm.topologies)})" in md
    assert all(len(row.split("`")[1]) <= cfg.max_label_chars for row in rows)
    assert imread(tmp_path / TOPOLOGIES).shape[0] > 100


def test_label_string() -> None:
    assert label_string((0, 1, 2, 0)) == "0120"
    assert label_string(tuple(range(12))) == "0123456789ab"
    assert label_string(()) == "∅"
    wide = tuple(range(70))
    assert label_string(wide).startswith("0.1.2.") and label_string(wide).endswith(".69")
    short = label_string(tuple(range(40)), max_chars=10)
    assert short == "0123…" + label_string(tuple(range(35, 40)))  # 4 + "…" + 5 characters


def test_place_positions_and_edges() -> None:
    visit_xy = np.array([[0.0, 0.0], [4.0, 0.0], [2.0, 2.0], [4.0, 4.0]])
    mean = place_positions(Topology((0, 1, 0, 1), 1.0), visit_xy)
    assert mean == pytest.approx(np.array([[1.0, 1.0], [4.0, 2.0]]))
    given = place_positions(Topology((0, 1, 0, 1), 1.0, positions=((9.0, 9.0), (8.0, 8.0))), visit_xy)
    assert given == pytest.approx(np.array([[9.0, 9.0], [8.0, 8.0]]))
    wrong_count = Topology((0, 1, 0, 1), 1.0, positions=((9.0, 9.0),))
    assert place_positions(wrong_count, visit_xy) == pytest.approx(mean)
    assert place_edges((0, 1, 2, 1, 0, 0, 3)).tolist() == [[0, 1], [0, 3], [1, 2]]
    assert place_edges((0,)).shape == (0, 2)


def test_extra_figure_name_clash_and_missing(tmp_path: Path) -> None:
    ptm = loop_ptm()
    src = tmp_path / "in" / HISTOGRAM  # clashes with the PTM histogram's name
    src.parent.mkdir()
    src.write_bytes(b"\x89PNG fake")
    out = tmp_path / "out"
    write_report(out, ptm, extra_figures=[src])
    assert (out / f"extra0_{HISTOGRAM}").read_bytes() == b"\x89PNG fake"
    assert f"extra0_{HISTOGRAM}" in html_links(out / REPORT_HTML)
    with pytest.raises(DataError, match="does not exist"):
        write_report(out, ptm, extra_figures=[tmp_path / "missing.png"])


def test_errors(tmp_path: Path) -> None:
    ptm = loop_ptm()
    with pytest.raises(ModelError, match="trajectory must be"):
        write_report(tmp_path, ptm, trajectory=np.zeros((5, 4)))
    other = score_ptm(make_ptm(ptm.landmarks, {TRUTH: 1.0}), TRUE_XY)
    with pytest.raises(DataError, match="score is of another PTM"):
        write_report(tmp_path, ptm, score=other)
    with pytest.raises(DataError, match="without topologies"):
        write_report(tmp_path, Ptm(landmarks=ptm.landmarks, topologies=()))
    with pytest.raises(ConfigError, match="top_k"):
        ReportConfig(top_k=0)
    with pytest.raises(ConfigError, match="max_label_chars"):
        ReportConfig(max_label_chars=2)


# ---------------------------------------------------------------------------------------------------
# Surprise figure (thesis Fig. 62) and SRQ plot (Fig. 42)
# ---------------------------------------------------------------------------------------------------


@cache
def step_trace() -> SurpriseTrace:
    """A laser surprise detector fed a 3-D statistic with two steps (scans 200 and 400, 10 Hz)."""
    rng = np.random.default_rng(0)
    z = rng.normal(0.0, 0.01, (600, 3))
    z[200:] += 0.2
    z[400:, 0] -= 0.3
    detector = LaserSurpriseDetector(LaserSurpriseConfig(samples=200))
    for i, zi in enumerate(z):
        detector.on_statistic(1000.0 + 0.1 * i, zi)
    return detector.trace


def artist(ax: Axes, gid: str) -> Any:
    """The one artist of ``ax`` with this ``gid``."""
    found = [a for a in ax.get_children() if a.get_gid() == gid]
    assert len(found) == 1, gid
    return found[0]


def test_fired_indices() -> None:
    trace = step_trace()
    assert trace.landmarks.tolist() == pytest.approx([1020.0, 1040.0])  # the detector fired at both steps
    assert fired_indices(trace).tolist() == [200, 400]
    # equal stamps: the most surprising measurement of that stamp
    dup = SurpriseTrace(
        stamps=np.array([0.0, 1.0, 1.0, 2.0]),
        surprise=np.array([0.1, 0.5, 3.0, 0.2]),
        predicted_mean=np.full(4, 0.3),
        predicted_std=np.full(4, 0.1),
        upper=np.full(4, 0.8),
        landmarks=np.array([1.0]),
    )
    assert fired_indices(dup).tolist() == [2] == trigger_indices(dup).tolist()  # no triggers: the landmarks
    bad = SurpriseTrace(
        dup.stamps, dup.surprise, dup.predicted_mean, dup.predicted_std, dup.upper, np.array([1.5])
    )
    with pytest.raises(DataError, match=r"landmark stamp 1\.5"):
        fired_indices(bad)


def test_surprise_figure_draws_the_trace_band_and_landmarks() -> None:
    trace = step_trace()
    fig = surprise_figure(trace, config=ReportConfig())
    (ax,) = fig.axes
    t = trace.stamps - trace.stamps[0]
    assert ax.get_yscale() == "log"
    line = artist(ax, "surprise")
    assert line.get_xdata() == pytest.approx(t)
    assert line.get_ydata() == pytest.approx(trace.surprise)
    assert artist(ax, "predicted_mean").get_ydata() == pytest.approx(trace.predicted_mean)
    assert artist(ax, "upper").get_ydata() == pytest.approx(trace.upper)
    # the rings sit on the surprise at the maxima that fired; unlocalised, the landmarks are those maxima
    idx = np.flatnonzero(np.isin(trace.stamps, trace.landmarks))
    assert idx.tolist() == [200, 400] == trigger_indices(trace).tolist()
    offsets = np.asarray(artist(ax, "triggers").get_offsets())
    assert offsets == pytest.approx(np.column_stack([t[idx], trace.surprise[idx]]))
    assert np.all(trace.surprise[idx] > trace.upper[idx])  # they fired above the band
    assert landmark_times(ax) == pytest.approx(t[idx])
    assert "placed" not in ax.get_title()
    # the band: top = the detector's threshold, bottom = max(0, mean - k·std) floored on the log axis
    band = np.concatenate([p.vertices for p in artist(ax, "band").get_paths()])
    assert band[:, 1].max() == pytest.approx(trace.upper.max())
    k = (trace.upper - trace.predicted_mean) / trace.predicted_std
    assert k == pytest.approx(np.full(k.shape, 5.0))  # LaserSurpriseConfig.band_sigmas
    assert "5σ" in artist(ax, "band").get_label()
    linear = surprise_figure(trace, config=ReportConfig(surprise_log_scale=False))
    assert linear.axes[0].get_yscale() == "linear"


def landmark_times(ax: Axes) -> list[float]:
    """The times of the dotted landmark lines of a surprise figure."""
    return [float(seg[0, 0]) for seg in artist(ax, "landmarks").get_segments()]


@cache
def localised_trace() -> SurpriseTrace:
    """A laser surprise detector that localises its landmarks (the default ``localize_distance``): driving
    0.1 m per scan, a step of the statistic at scan 200, the most open scans 8-10 scans (~1 m) later."""
    rng = np.random.default_rng(1)
    detector = LaserSurpriseDetector(LaserSurpriseConfig(samples=200))
    for i in range(400):
        stamp = 1000.0 + 0.1 * i
        detector.on_odometry(stamp, [0.1 * i, 0.0, 0.0])
        z = rng.normal(0.0, 0.01, 3) + (0.2 if i >= 200 else 0.0)
        detector.on_statistic(stamp, z, openness=1.0 if 208 <= i <= 210 else 0.0)
    detector.flush()
    return detector.trace


def test_surprise_figure_rings_the_maxima_above_the_band_and_marks_where_landmarks_were_placed() -> None:
    """Issue #25: the landmarks of a localising detector lie inside the band, where the caption's rule
    (fire at the first maximum above the band) does not put them. The rings mark the maxima that fired,
    above the band as the rule says; dotted lines mark where the landmarks were placed."""
    trace = localised_trace()
    assert trace.triggers is not None and trace.triggers.tolist() == pytest.approx([1020.0])
    assert trace.landmarks.tolist() == pytest.approx([1020.9])  # the middle of the most open scans
    placed, fired = fired_indices(trace), trigger_indices(trace)
    assert placed.tolist() == [209] and fired.tolist() == [200]
    assert trace.surprise[placed[0]] < trace.upper[placed[0]]  # the landmark's own scan: inside the band
    fig = surprise_figure(trace, config=ReportConfig())
    (ax,) = fig.axes
    t = trace.stamps - trace.stamps[0]
    rings = np.asarray(artist(ax, "triggers").get_offsets())
    assert rings == pytest.approx(np.column_stack([t[fired], trace.surprise[fired]]))
    assert np.all(rings[:, 1] > trace.upper[fired])  # every ring above the band, as the caption says
    assert landmark_times(ax) == pytest.approx(t[placed])
    title = ax.get_title()
    assert "first maximum of each run above the band (rings)" in title and "placed at the most open" in title
    assert "where placed" in artist(ax, "landmarks").get_label()


@pytest.mark.slow
def test_report_with_surprise_trace(tmp_path: Path) -> None:
    trace = step_trace()
    html_path = write_report(tmp_path, loop_ptm(), surprise_trace=trace)
    img = imread(tmp_path / SURPRISE)
    assert img.shape[0] > 200 and img.shape[1] > 500
    # the red landmark rings are in the picture (tab:red = #d62728)
    red = (np.abs(img[..., 0] - 0xD6 / 255) < 0.05) & (np.abs(img[..., 1] - 0x27 / 255) < 0.05)
    assert red.sum() > 20
    assert SURPRISE in html_links(html_path)
    md = (tmp_path / REPORT_MD).read_text(encoding="utf-8")
    assert f"]({SURPRISE})" in md
    assert "landmark detector: 600 measurements, 2 landmarks declared by surprise" in md
    empty = SurpriseTrace(*(np.zeros(0) for _ in range(6)))
    write_report(tmp_path / "empty", loop_ptm(), surprise_trace=empty)  # nothing to draw: no figure
    assert not (tmp_path / "empty" / SURPRISE).exists()
    with pytest.raises(DataError, match="empty"):
        surprise_figure(empty, config=ReportConfig())
    ragged = SurpriseTrace(
        trace.stamps,
        trace.surprise[:-1],
        *(getattr(trace, f) for f in ("predicted_mean", "predicted_std", "upper", "landmarks")),
    )
    with pytest.raises(DataError, match="shapes"):
        write_report(tmp_path, loop_ptm(), surprise_trace=ragged)


def mcmc_ptm(chains: list[list[object]], **inference: object) -> Ptm:
    ptm = loop_ptm()
    return Ptm(ptm.landmarks, ptm.topologies, inference={"method": "mcmc", SRQ_KEY: chains, **inference})


def test_srq_figure_lines() -> None:
    chains = [["a", "b", "a", "a", "c", "a"], ["c", "a", "c", "c", "a", "b"]]
    points, missing = chain_srq(chains)
    assert missing == []
    # pooled counts: a 6, c 4, b 2 -> the atom is "a" in both chains
    assert points["chain 0"][1] == pytest.approx([1 / 6, 3 / 6, 4 / 6, 1.0])
    assert points["chain 1"][0] == pytest.approx([0.5, 1.0])
    assert points["chain 1"][1] == pytest.approx([2 / 5, 1.0])
    fig = srq_figure(points, note="hello")
    (ax,) = fig.axes
    line = artist(ax, "chain 0")
    assert line.get_xdata() == pytest.approx([0.0, 0.25, 0.5, 0.75, 1.0])
    assert line.get_ydata() == pytest.approx([0.0, 1 / 6, 3 / 6, 4 / 6, 1.0])
    assert artist(ax, "diagonal").get_ydata() == pytest.approx([0.0, 1.0])
    assert "max |y − x| = 0.100" in artist(ax, "chain 1").get_label()
    assert "hello" in ax.get_title()
    with pytest.raises(DataError, match="at least one chain"):
        srq_figure({})


def test_report_draws_srq_from_inference_after_json_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(4)
    good = rng.integers(0, 3, 6000).tolist()
    stuck = np.concatenate([rng.integers(0, 3, 3000), rng.integers(0, 6, 3000)]).tolist()
    ptm = load_ptm(save_ptm(mcmc_ptm([good, stuck], **{SRQ_THIN_KEY: 4}), tmp_path / "ptm.json"))
    assert ptm.inference[SRQ_KEY] == [good, stuck]  # plain JSON lists
    html_path = write_report(tmp_path / "r", ptm)
    assert imread(tmp_path / "r" / SRQ).shape[0] > 300
    assert SRQ in html_links(html_path)
    md = (tmp_path / "r" / REPORT_MD).read_text(encoding="utf-8")
    atom = int(np.argmax(np.bincount(good + stuck)))
    devs = [srq_deviation(*srq_points(c, atom)) for c in (good, stuck)]
    # i.i.d.: R ≈ 2000, within 2.7·CV/√R ≈ 0.05 but with probability 1e-6; stuck: ≈ 1/6 (test_convergence)
    assert devs[0] < 0.06 < 0.12 < devs[1]
    assert f"SRQ max |y − x| (0 = ideal mixing): chain 0 {devs[0]:.3f}, chain 1 {devs[1]:.3f}" in md
    assert "method: mcmc" in md and "cold_chain_states" not in md  # the states stay out of the summary


def test_srq_states_as_labels_and_a_chain_missing_the_atom(tmp_path: Path) -> None:
    a, b, c = [0, 1, 2, 0], [0, 1, 0, 1], [0, 0, 0, 0]
    ptm = mcmc_ptm([[a, b, a, a], [c, c, b]])
    chains = chain_states(ptm)
    assert chains == [[tuple(a), tuple(b), tuple(a), tuple(a)], [tuple(c), tuple(c), tuple(b)]]
    assert chains is not None
    points, missing = chain_srq(chains)
    assert list(points) == ["chain 0"] and missing == [1]
    write_report(tmp_path, ptm)
    md = (tmp_path / REPORT_MD).read_text(encoding="utf-8")
    assert "chain 0 0.083; atom never visited by chain 1" in md  # T = 1, 3, 4: max |y - x| = 1/12
    assert chain_states(loop_ptm()) is None
    for bad, match in (
        ("abc", "one state list per chain"),
        ([], "one state list per chain"),
        ([[1], []], r"\[1\]"),
    ):
        with pytest.raises(DataError, match=match):
            write_report(tmp_path, mcmc_ptm(bad))  # type: ignore[arg-type]


def test_draw_srq_writes_a_file(tmp_path: Path) -> None:
    x, y = srq_points([0, 1, 0, 0, 1, 0])
    path = draw_srq({"chain 0": (x, y)}, tmp_path / "srq.png", config=ReportConfig(dpi=50))
    assert path == tmp_path / "srq.png" and imread(path).shape[0] == 300  # 6 in at 50 dpi


def test_ptm_json_keeps_a_chain_summary_and_the_trace_file_the_states(tmp_path: Path) -> None:
    """Issue #25: the cold chains' states leave ptm.json (a summary stays) for a trace file, from which
    the report draws the SRQ plot; without the trace the report gives the SRQ figures and says the plot
    needs ``--trace``; a trace of another run is refused."""
    rng = np.random.default_rng(4)
    good = rng.integers(0, 3, 600).tolist()
    stuck = [5] * 300 + rng.integers(0, 3, 300).tolist()
    labels = [[0, 1, 2, 0], [0, 1, 0, 1], [0, 0, 0, 0], [0, 1, 2, 3], [0, 0, 1, 1], [0, 1, 1, 0]]
    full = mcmc_ptm([good, stuck], **{SRQ_THIN_KEY: 4, SRQ_LABELS_KEY: labels})
    ptm, trace = split_chain_trace(full, trace_file=TRACE)
    assert trace is not None and not {SRQ_KEY, SRQ_THIN_KEY, SRQ_LABELS_KEY} & set(ptm.inference)
    summary = ptm.inference[CHAINS_KEY]
    points, _ = chain_srq(chain_states(full) or [])
    devs = [srq_deviation(*points[f"chain {k}"]) for k in (0, 1)]
    assert summary == {
        "chains": 2,
        "states": [600, 600],
        "thin": 4,
        "srq_max_deviation": devs,
        "trace": TRACE,
    }
    assert trace == {"schema": TRACE_SCHEMA, "thin": 4, "chains": [good, stuck], "topologies": labels}
    saved = save_ptm(ptm, tmp_path / "run" / "ptm.json")
    save_chain_trace(trace, tmp_path / "run" / TRACE)
    before = save_ptm(full, tmp_path / "before.json")
    assert SRQ_KEY not in saved.read_text() and saved.stat().st_size + 2000 < before.stat().st_size
    loaded = load_ptm(saved)
    again = find_chain_trace(loaded, tmp_path / "run")
    assert again == trace
    write_report(tmp_path / "with", loaded, chain_trace=again)
    md = (tmp_path / "with" / REPORT_MD).read_text(encoding="utf-8")
    assert (tmp_path / "with" / SRQ).is_file() and f"chain 0 {devs[0]:.3f}, chain 1 {devs[1]:.3f}" in md
    write_report(tmp_path / "without", loaded)
    md = (tmp_path / "without" / REPORT_MD).read_text(encoding="utf-8")
    assert not (tmp_path / "without" / SRQ).exists()
    assert f"chain 0 {devs[0]:.3f}, chain 1 {devs[1]:.3f}" in md and "run ptm-run with --trace" in md
    assert (
        find_chain_trace(
            replace(loaded, inference={**loaded.inference, CHAINS_KEY: {**summary, "trace": None}}),
            tmp_path / "run",
        )
        is None
    )
    _, other_trace = split_chain_trace(mcmc_ptm([good[:500], stuck]), trace_file=TRACE)
    assert other_trace is not None
    save_chain_trace(other_trace, tmp_path / "run" / TRACE)
    with pytest.raises(DataError, match="the trace of another run"):
        find_chain_trace(loaded, tmp_path / "run")
    (tmp_path / "run" / TRACE).write_text("{}")
    with pytest.raises(DataError, match="not an MCMC trace"):
        load_chain_trace(tmp_path / "run" / TRACE, loaded)
    assert split_chain_trace(loop_ptm()) == (loop_ptm(), None)  # no chains: unchanged


@pytest.mark.slow
def test_report_shows_the_occupancy_map_and_notes(tmp_path: Path) -> None:
    from ptm_ros.maps.occupancy import build_grid, save_png

    # A scanner at the centre of the loop sees a circle of radius 3 m: a real grid image.
    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    grid = build_grid([[5.0, 5.0, 0.0]], [np.full(90, 3.0)], angles[0], angles[1] - angles[0], 10.0)
    src = save_png(grid, tmp_path / "elsewhere" / "map.png")
    out = tmp_path / "r"
    note = "absolute trajectory error: 0.123 m"
    html_path = write_report(out, loop_ptm(), occupancy_map=src, notes=[note])
    assert (out / "map.png").read_bytes() == src.read_bytes()  # copied beside the report
    md = (out / REPORT_MD).read_text(encoding="utf-8")
    assert f"![{MAP_CAPTION}](map.png)" in md
    assert f"- {note}" in md
    html_text = html_path.read_text(encoding="utf-8")
    assert "map.png" in html_links(html_path) and MAP_CAPTION in html_text and note in html_text
    # a map already in the output directory is linked where it is; a clashing name is renamed
    write_report(out, loop_ptm(), occupancy_map=out / "map.png")
    assert "map.png" in html_links(html_path)
    clash = tmp_path / "elsewhere" / HISTOGRAM
    clash.write_bytes(src.read_bytes())
    write_report(out, loop_ptm(), occupancy_map=clash)
    assert (out / f"map_{HISTOGRAM}").read_bytes() == src.read_bytes()
    assert f"map_{HISTOGRAM}" in html_links(html_path)
    with pytest.raises(DataError, match="does not exist"):
        write_report(out, loop_ptm(), occupancy_map=tmp_path / "missing.png")


# --- the map side by side with its reference or its route graph --------------------------------------


def walled_room(width: int = 60) -> np.ndarray:
    """Classes of a walled room at 0.1 m: a one-cell wall ring, free inside, unknown beyond."""
    c = np.full((40, width), -1, dtype=np.int8)
    c[5:-5, 5:55] = 100
    c[6:-6, 6:54] = 0
    return c


def red_pixels(path: Path) -> int:
    rgb = imread(path)[..., :3]
    return int(np.count_nonzero((rgb[..., 0] > 0.7) & (rgb[..., 1] < 0.3) & (rgb[..., 2] < 0.3)))


@pytest.mark.slow
def test_map_comparison_shows_the_leak_in_red_next_to_the_reference(tmp_path: Path) -> None:
    from ptm_ros.maps.map_quality import ClassGrid, map_quality

    r = 0.08  # m: 0.3 m falls between 3 cells (0.24 m) and 4 (0.32 m)
    room = walled_room(80)  # the room and 25 columns of unknown east of it
    reference = ClassGrid(room, (0.0, 0.0, 0.0), r, seen=room != -1)
    # The product turned a quarter clockwise (np.rot90(k=-1): cell [i, j] holds the room's [H-1-j, i]) with
    # its origin at (d0, d1 - W r): a product cell centre (x, y) is the room's (y - d1 + W r, H r - x + d0),
    # i.e. x_ref = R(-90°) x_p + t with t = (W r - d1, H r + d0).
    d = np.array([3.0, 7.0])
    t = np.array([80 * r - d[1], 40 * r + d[0]])

    def product_of(classes: np.ndarray) -> ClassGrid:
        turned = np.ascontiguousarray(np.rot90(classes, k=-1))
        return ClassGrid(turned, (d[0], d[1] - classes.shape[1] * r, 0.0), r)

    clean = product_of(walled_room(80))
    leaky = walled_room(80)
    leaky[15:25, 54:] = 0  # a free corridor out through the east wall (column 54), 2 m beyond the reference
    config = ReportConfig()
    drawn = {}
    for name, product in (("clean", clean), ("leaky", product_of(leaky))):
        q = map_quality(product, reference, theta=-np.pi / 2, t=t)
        comparison = MapComparison(product, reference, theta=-np.pi / 2, t=(t[0], t[1]), quality=q.as_dict())
        drawn[name] = (q, draw_map_comparison(comparison, tmp_path / f"{name}.png", config=config))
    assert drawn["clean"][0].leaked_cells == 0 and red_pixels(drawn["clean"][1]) == 0
    assert drawn["leaky"][0].leaked_cells == 10 * 22  # columns 58..79: 0.32 m and more from the wall
    assert red_pixels(drawn["leaky"][1]) > 50
    # without the motion the map lies elsewhere and most of it leaks: the figure follows the motion given
    wrong = MapComparison(product_of(walled_room(80)), reference)
    assert red_pixels(draw_map_comparison(wrong, tmp_path / "wrong.png", config=config)) > 500
    html_path = write_report(tmp_path / "r", loop_ptm(), map_comparison=comparison)
    md = (tmp_path / "r" / REPORT_MD).read_text(encoding="utf-8")
    assert f"![{REFERENCE_CAPTION}]({MAP_COMPARISON})" in md
    assert MAP_COMPARISON in html_links(html_path)
    assert imread(tmp_path / "r" / MAP_COMPARISON).shape[1] == 12 * config.dpi  # two panels side by side


def test_map_comparison_without_reference_draws_the_route_graph(tmp_path: Path) -> None:
    from ptm_ros.maps.map_quality import ClassGrid
    from ptm_ros.maps.routes import route_graph

    ptm = loop_ptm()
    doc = route_graph(ptm)
    fig = Figure()
    places, edges = draw_route_graph(fig.add_subplot(), doc)
    nodes = [f for f in doc["features"] if f["geometry"]["type"] == "Point"]
    assert places == len(nodes) == len(set(ptm.map_topology.labels))
    assert edges == sum(f["geometry"]["type"] == "MultiLineString" for f in doc["features"]) > 0
    grid = ClassGrid(walled_room(), (-1.0, -1.0, 0.0), 0.3)  # covers the loop (0..10 m)
    html_path = write_report(tmp_path, ptm, map_comparison=MapComparison(grid, route_graph=doc))
    md = (tmp_path / REPORT_MD).read_text(encoding="utf-8")
    assert f"![{ROUTES_CAPTION}]({MAP_COMPARISON})" in md and MAP_COMPARISON in html_links(html_path)
    assert red_pixels(tmp_path / MAP_COMPARISON) == 0


def timeline_ptm() -> Ptm:
    """:func:`loop_ptm` with the timeline the filter would have written, and a greedy answer that joins
    visit 3 to visit 1's place."""
    from ptm_ros.model.ptm import TimelineStep, greedy_dict, timeline_list

    ptm = loop_ptm()
    steps = [TimelineStep(n, ((TRUTH[:n], 0.9), ((0, 1, 2, 3, 4, 5, 6, 7)[:n], 0.1))) for n in range(4, 9)]
    steps = [TimelineStep(n, ((TRUTH[:n], 1.0),)) for n in range(1, 4)] + steps
    steps[3] = TimelineStep(4, (((0, 1, 2, 1), 0.6), ((0, 1, 2, 3), 0.4)))
    inference = {**RBPF_INFERENCE, "timeline": timeline_list(steps)}
    return replace(ptm, inference=inference, extra={"greedy": greedy_dict((0, 1, 2, 1, 0, 3, 2, 1), 0.99)})


@pytest.mark.slow
def test_timeline_figure_draws_the_mass_of_the_truth_and_of_the_greedy_answer(tmp_path: Path) -> None:
    """Issue #25: per visit the most probable topology's mass (bars), the truth's and the greedy answer's
    (cut to the visits so far; an unlisted one at the most it can hold), and where greedy went wrong."""
    from ptm_ros.model.ptm import ptm_timeline
    from ptm_ros.reporting.report import TIMELINE
    from ptm_ros.reporting.timeline_plots import timeline_figure

    ptm = timeline_ptm()
    steps = ptm_timeline(ptm)
    fig = timeline_figure(steps, truth=TRUTH, greedy=(0, 1, 2, 1, 0, 3, 2, 1))
    (ax,) = fig.axes
    assert artist(ax, "truth").get_ydata() == pytest.approx([1, 1, 1, 0.4, 0.9, 0.9, 0.9, 0.9])
    assert artist(ax, "greedy").get_ydata() == pytest.approx([1, 1, 1, 0.6, 0, 0, 0, 0])  # unlisted: <= 0
    assert artist(ax, "commit").get_xdata() == [3, 3]
    assert len([a for a in ax.get_children() if a.get_gid() == "top"]) == 8
    plain = timeline_figure(steps).axes[0]
    assert artist(plain, "second").get_ydata() == pytest.approx([0, 0, 0, 0.4, 0.1, 0.1, 0.1, 0.1])
    assert not [a for a in plain.get_children() if a.get_gid() in ("truth", "greedy", "commit")]
    with pytest.raises(DataError, match="at least one step"):
        timeline_figure(())
    html = write_report(tmp_path, ptm, score=score_ptm(ptm, TRUE_XY, true_places=TRUTH))
    assert TIMELINE in html_links(html) and imread(tmp_path / TIMELINE).shape[0] > 100
    write_report(tmp_path / "none", loop_ptm())
    assert not (tmp_path / "none" / TIMELINE).exists()
