"""Progress of ``ptm-run``'s phases on stderr: one named tqdm bar per phase, none with ``--quiet``.

:class:`Phases` is the one helper the offline pipeline (:mod:`ptm_ros.tools.pipeline`) reports through:

* :meth:`Phases.wrap` gives the core's progress hook (:data:`ptm_ros.session.Progress`,
  ``hook(items, total)`` yields the items): reading the bag (messages), extracting the landmark visits
  (messages), the particle filter (visits), exact enumeration (topologies);
* :meth:`Phases.counter` a bar the caller moves itself: MCMC's sweeps (``hook(done, target)``, the target
  growing as the sampler doubles its sweeps);
* :meth:`Phases.step` a phase of one call (smoothing, the map, the route graph, the scores, the report):
  its bar shows the phase's name when it starts and its time when it ends.

Every bar writes to stderr (``file``), so stdout keeps only the summary; ``quiet`` disables them all
(:meth:`Phases.note` lines, e.g. warnings, are written either way).
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterable, Iterator
from typing import Any, TextIO

from tqdm import tqdm

#: Seconds between two redraws of a bar.
MININTERVAL = 0.5
#: The bar of a one-call phase: its name, done or not, and its time.
STEP_FORMAT = "{desc}: {percentage:3.0f}%|{bar}| {elapsed_s:.1f} s"


class Phases:
    """Named tqdm bars on ``file`` (default stderr), one per phase; ``quiet``: none at all."""

    def __init__(self, *, quiet: bool = False, file: TextIO | None = None) -> None:
        self.quiet = quiet
        self.file = file

    def _bar(self, name: str, total: float | None, unit: str, bar_format: str | None = None) -> tqdm:
        return tqdm(
            total=total,
            desc=name,
            unit=unit,
            file=self.file if self.file is not None else sys.stderr,
            mininterval=MININTERVAL,
            disable=self.quiet,
            dynamic_ncols=True,
            bar_format=bar_format,
        )

    def wrap(self, name: str, unit: str = "it") -> Callable[[Iterable[Any], int], Iterable[Any]]:
        """A progress hook ``hook(items, total)`` that yields the items with a bar named ``name``."""

        def hook(items: Iterable[Any], total: int) -> Iterator[Any]:
            with self._bar(name, total, unit) as bar:
                for item in items:
                    yield item
                    bar.update(1)

        return hook

    @contextlib.contextmanager
    def counter(self, name: str, unit: str = "it") -> Iterator[Callable[[int, int], None]]:
        """A bar moved by ``hook(done, total)`` (absolute counts; the total may grow), drawn from the first
        call on (a phase that never calls it shows nothing)."""
        bars: list[tqdm] = []

        def hook(done: int, total: int) -> None:
            if not bars:
                bars.append(self._bar(name, total, unit))
            bar = bars[0]
            bar.total = total
            bar.update(done - bar.n)

        try:
            yield hook
        finally:
            for bar in bars:
                bar.close()

    def note(self, text: str) -> None:
        """A line between the bars (a warning, a note): written without breaking a bar being drawn."""
        tqdm.write(text, file=self.file if self.file is not None else sys.stderr)

    @contextlib.contextmanager
    def step(self, name: str) -> Iterator[None]:
        """A phase of one call: its bar is drawn when it starts and completed, with its time, at the end."""
        with self._bar(name, 1, "step", bar_format=STEP_FORMAT) as bar:
            yield
            bar.update(1)
