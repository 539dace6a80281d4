"""Tests of ptm_ros.report: figures, report.md and report.html of a PTM."""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure
from matplotlib.image import imread

from ptm_ros.errors import ConfigError, DataError, ModelError
from ptm_ros.evaluation import score_ptm
from ptm_ros.ptm import Landmark, Ptm, Topology, make_ptm
from ptm_ros.report import (
    HISTOGRAM,
    REPORT_HTML,
    REPORT_MD,
    SCORES,
    TOPOLOGIES,
    ReportConfig,
    label_string,
    place_edges,
    place_positions,
    write_report,
)

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
