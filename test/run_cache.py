"""Expensive fixture values computed once per test run, whichever pytest-xdist worker asks first.

Session- and module-scoped fixtures are made once per worker: two workers that both need one make it
twice. :func:`once_per_run` makes it once (the first worker to ask, while the others wait), pickles it in
the run's base temporary directory and hands the others that pickle; without xdist it just makes it.
"""

from __future__ import annotations

import fcntl
import os
import pickle
import re
from collections.abc import Callable
from typing import TypeVar

import pytest

T = TypeVar("T")


def once_per_run(tmp_path_factory: pytest.TempPathFactory, key: str, make: Callable[[], T]) -> T:
    """``make()``, computed by one xdist worker of this run and loaded by the others (``key`` names the
    value: unique and stable); the value must pickle, and the files it names stay where the maker wrote
    them."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return make()
    root = tmp_path_factory.getbasetemp().parent  # the run's: each worker's base is popen-gwN inside it
    name = re.sub(r"[^\w.-]", "_", key)
    with (root / f"{name}.lock").open("a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        path = root / f"{name}.pickle"
        if path.is_file():
            value: T = pickle.loads(path.read_bytes())
            return value
        value = make()
        path.write_bytes(pickle.dumps(value, protocol=pickle.HIGHEST_PROTOCOL))
        return value
