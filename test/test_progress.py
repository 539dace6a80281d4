"""``ptm_ros/tools/progress.py``: one named bar per phase on the given stream, nothing when quiet."""

from __future__ import annotations

import io

from ptm_ros.tools.progress import Phases


def drawn(stream: io.StringIO) -> list[str]:
    """The names of the bars drawn on ``stream``, first appearance order."""
    lines = stream.getvalue().replace("\r", "\n").splitlines()
    return list(dict.fromkeys(ln.split(":")[0] for ln in lines if "%|" in ln))


def test_every_kind_of_phase_draws_a_named_bar():
    out = io.StringIO()
    phases = Phases(file=out)
    assert list(phases.wrap("visits", "msg")(iter(range(5)), 5)) == [0, 1, 2, 3, 4]
    with phases.counter("MCMC sweeps", "sweep") as sweeps:
        for done in (10, 20, 40):
            sweeps(done, 40)
    with phases.counter("never called"):
        pass
    with phases.step("report"):
        pass
    phases.note("ptm-run: a note")
    assert drawn(out) == ["visits", "MCMC sweeps", "report"]
    text = out.getvalue()
    assert "5/5" in text and "40/40" in text and "ptm-run: a note\n" in text
    assert "report: 100%|" in text and " s" in text.split("report: 100%|")[-1]  # the step's time


def test_quiet_draws_nothing_but_notes():
    out = io.StringIO()
    phases = Phases(quiet=True, file=out)
    assert list(phases.wrap("visits")(iter("abc"), 3)) == ["a", "b", "c"]
    with phases.counter("sweeps") as sweeps:
        sweeps(5, 10)
    with phases.step("map"):
        pass
    phases.note("ptm-run: a warning")
    assert out.getvalue() == "ptm-run: a warning\n"
