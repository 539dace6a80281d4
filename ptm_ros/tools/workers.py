"""The worker processes of ``ptm-run --jobs N`` (:class:`RegistrationPool`): the visits' patches, the
filter's registrations, the refinement's scan matches and the report's figures, each outcome the same as in
one process. The workers' fork server preloads :mod:`ptm_ros.tools.pipeline` (which imports this module)
and matplotlib's Agg backend.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ProcessPoolExecutor
from multiprocessing.connection import wait
from typing import Any, TypeVar

from ptm_ros.maps.refinement import RegistrationJob
from ptm_ros.perception.laser import Registration

_T = TypeVar("_T")


def _exit_with_parent() -> None:
    """A worker's initializer: end the worker as soon as the process that started it has ended (a killed
    ``ptm-run`` leaves no workers behind holding its pipes)."""
    parent = multiprocessing.parent_process()
    if parent is None:
        return

    def watch() -> None:
        wait([parent.sentinel])
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


class RegistrationPool:
    """``jobs`` worker processes for a run's independent scan matching: the visits' patches and the
    filter's registrations (:meth:`submit`, a :class:`~ptm_ros.perception.laser.WorkerPool`) and the
    refinement's (a :class:`~ptm_ros.maps.refinement.Mapper`; batches of fewer than ``min_batch``, and
    everything when ``jobs`` <= 1, run here: a pool's start-up costs more than they do). Outcomes are computed
    by the same functions and come back in order, so the files are identical whatever ``jobs``. Workers come
    from a fork server that has imported the offline pipeline and matplotlib once (forking this process
    could copy a held lock of its threads), started on first use; a worker ends when this process does,
    even killed."""

    def __init__(self, jobs: int, min_batch: int = 32) -> None:
        self.jobs = jobs
        self.min_batch = min_batch
        self._pool: ProcessPoolExecutor | None = None

    def _workers(self) -> ProcessPoolExecutor:
        if self._pool is None:
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(["ptm_ros.tools.pipeline", "matplotlib.backends.backend_agg"])
            self._pool = ProcessPoolExecutor(
                max_workers=self.jobs, mp_context=context, initializer=_exit_with_parent
            )
        return self._pool

    def __call__(
        self, fn: Callable[[RegistrationJob], Registration | None], jobs: Iterable[RegistrationJob], /
    ) -> Iterable[Registration | None]:
        batch = list(jobs)
        if self.jobs <= 1 or len(batch) < self.min_batch:
            return map(fn, batch)
        chunk = max(1, len(batch) // (4 * self.jobs))
        return self._workers().map(fn, batch, chunksize=chunk)

    @property
    def workers(self) -> RegistrationPool | None:
        """This pool as a :class:`~ptm_ros.perception.laser.WorkerPool`; None when ``jobs`` <= 1 (all work
        here)."""
        return self if self.jobs > 1 else None

    def submit(self, fn: Callable[..., _T], /, *args: Any, **kwargs: Any) -> Future[_T]:
        """``fn(*args, **kwargs)`` in a worker process."""
        return self._workers().submit(fn, *args, **kwargs)

    def __enter__(self) -> RegistrationPool:
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
            self._pool = None
