"""Helpers for tests over real DDS: isolated domains, per-test rclpy contexts, executor threads that are
always shut down, subprocess environments, and polling with timeouts.

Every test gets its own ``rclpy.Context`` on its own ROS domain (derived from the pid, so concurrent test
runs on one machine do not hear each other), discovery restricted to localhost, and the fast Fast DDS
announcement profile. A spinning executor thread left behind aborts the interpreter at exit, so
:func:`ros_context` shuts down every executor, node and context it handed out, even when the test fails.
"""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[1]
MATCH_TIMEOUT = 15.0  # s: discovery and matching on a loaded 2-core machine
_DOMAINS = itertools.count()


def next_domain_id() -> int:
    """A ROS domain id in 20..229 for one test: distinct within this process, spread across pids, and in a
    range of its own for each pytest-xdist worker (``gw0``, ``gw1``: concurrent tests never share one)."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    workers = max(int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")), 1)
    span = 210 // workers
    base = 20 + (int(worker) % workers if worker.isdigit() else 0) * span
    return base + (os.getpid() * 11 + 37 * next(_DOMAINS)) % span  # 11, 37: coprime with 210 and its spans


def dds_env(domain_id: int, base: dict[str, str] | None = None) -> dict[str, str]:
    """The environment of a process on ``domain_id``: localhost discovery, Fast DDS, fast announcements."""
    env = dict(os.environ if base is None else base)
    env.update(
        {
            "ROS_DOMAIN_ID": str(domain_id),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
            "FASTDDS_DEFAULT_PROFILES_FILE": str(REPO / "config" / "fastdds.xml"),
            "AMENT_PREFIX_PATH": env.get("AMENT_PREFIX_PATH", sys.prefix),
            "PYTHONPATH": os.pathsep.join(p for p in (str(REPO), env.get("PYTHONPATH", "")) if p),
            "OPENBLAS_NUM_THREADS": "1",
            "PYTHONUNBUFFERED": "1",
            "RCUTILS_COLORIZED_OUTPUT": "0",
        }
    )
    return env


def wait_for(predicate: Callable[[], Any], timeout: float = MATCH_TIMEOUT, poll: float = 0.02) -> Any:
    """Poll ``predicate`` until it returns something truthy (returned) or fail the test after ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"condition not met within {timeout} s: {getattr(predicate, '__name__', predicate)}")
        time.sleep(poll)


@dataclass
class RosSession:
    """One test's ROS world: a context on its own domain and the executors spinning its nodes."""

    context: Any
    domain_id: int
    nodes: list[Any] = field(default_factory=list)
    _spinners: list[tuple[Any, threading.Thread]] = field(default_factory=list)

    def node(self, name: str, **kwargs: Any) -> Any:
        """A plain node in this context (destroyed at teardown)."""
        import rclpy

        n = rclpy.create_node(name, context=self.context, **kwargs)
        self.nodes.append(n)
        return n

    def add(self, node: Any) -> Any:
        """Register a node built elsewhere (destroyed at teardown)."""
        self.nodes.append(node)
        return node

    def spin(self, *nodes: Any) -> Any:
        """Spin ``nodes`` in a background executor thread (shut down and joined at teardown)."""
        from rclpy.executors import SingleThreadedExecutor

        executor = SingleThreadedExecutor(context=self.context)
        for n in nodes:
            executor.add_node(n)
        thread = threading.Thread(target=self._spin, args=(executor,), daemon=True)
        thread.start()
        self._spinners.append((executor, thread))
        return executor

    @staticmethod
    def _spin(executor: Any) -> None:
        from rclpy.executors import ExternalShutdownException

        with suppress(ExternalShutdownException):
            executor.spin()

    def call(self, node: Any, srv_type: Any, name: str, timeout: float = MATCH_TIMEOUT) -> Any:
        """Call a service from ``node`` (spun elsewhere) and return the response."""
        client = node.create_client(srv_type, name)
        try:
            assert client.wait_for_service(timeout_sec=timeout), f"service {name} not available"
            future = client.call_async(srv_type.Request())
            wait_for(future.done, timeout)
            return future.result()
        finally:
            node.destroy_client(client)

    def close(self) -> None:
        for executor, thread in self._spinners:
            executor.shutdown(timeout_sec=5.0)
            thread.join(timeout=10.0)
        for n in self.nodes:
            n.destroy_node()
        self.context.try_shutdown()


@contextmanager
def ros_context(monkeypatch: pytest.MonkeyPatch | None = None) -> Iterator[RosSession]:
    """A fresh rclpy context on a fresh domain; everything created through it is torn down on exit."""
    import rclpy

    domain = next_domain_id()
    env = dds_env(domain)
    if monkeypatch is not None:
        for key in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "RMW_IMPLEMENTATION", "FASTDDS_DEFAULT_PROFILES_FILE"):
            monkeypatch.setenv(key, env[key])
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    session = RosSession(context=context, domain_id=domain)
    try:
        yield session
    finally:
        session.close()


class Inbox:
    """Messages received on one topic by a subscription of ``node`` (thread-safe)."""

    def __init__(self, node: Any, msg_type: Any, topic: str, qos: Any) -> None:
        self._lock = threading.Lock()
        self._items: list[Any] = []
        self.subscription = node.create_subscription(msg_type, topic, self._on, qos)

    def _on(self, msg: Any) -> None:
        with self._lock:
            self._items.append(msg)

    @property
    def items(self) -> list[Any]:
        with self._lock:
            return list(self._items)

    def last(self) -> Any:
        items = self.items
        return items[-1] if items else None


def processes_mentioning(text: str) -> list[tuple[int, str]]:
    """``(pid, cmdline)`` of every live process whose command line contains ``text`` (Linux /proc)."""
    out = []
    me = os.getpid()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == me:
            continue
        try:
            cmd = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            state = (entry / "stat").read_text().split(") ", 1)[1][:1]
        except (OSError, IndexError):
            continue
        if text in cmd and state != "Z":
            out.append((int(entry.name), cmd.strip()))
    return out


def kill_processes_mentioning(text: str) -> None:
    """Test cleanup: SIGKILL whatever a failed test left behind (only processes naming ``text``)."""
    for pid, _ in processes_mentioning(text):
        with suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)


def assert_no_orphans(*marks: str) -> None:
    """Fails the test when processes naming any of ``marks`` outlive ptm-bringup (after up to 5 s), and
    kills them."""
    deadline = time.monotonic() + 5.0  # a process may take a moment to disappear from /proc
    left = [p for m in marks for p in processes_mentioning(m)]
    while left and time.monotonic() < deadline:
        time.sleep(0.1)
        left = [p for m in marks for p in processes_mentioning(m)]
    for m in marks:
        kill_processes_mentioning(m)
    assert not left, f"processes outlived ptm-bringup: {left}"


class ProcessLogs:
    """The output of the processes a test started, by name. When the test fails, ``conftest.py`` attaches
    each one in full to the test's report (a section per process, after the assertion), so the cause of a
    node's exit code is never lost to pytest's shortening of long assertion operands."""

    def __init__(self) -> None:
        self._sources: dict[str, Callable[[], str]] = {}

    def add(self, name: str, source: Callable[[], str]) -> None:
        """Attach ``source()`` (called when the report is made: the output so far) as the log ``name``."""
        self._sources[name] = source

    def sections(self) -> list[tuple[str, str]]:
        """``(name, text)`` of every attached log."""
        out = []
        for name, source in self._sources.items():
            try:
                text = source()
            except Exception as err:  # a report must never fail for its attachments
                text = f"(log unavailable: {type(err).__name__}: {err})"
            out.append((name, text))
        return out


BRINGUP = [sys.executable, "-m", "ptm_ros.tools.bringup"]


class BringupProcess:
    """A ``ptm-bringup`` process (own process group) whose output is collected line by line."""

    def __init__(self, args: list[str], env: dict[str, str]) -> None:
        self.proc = subprocess.Popen(
            [*BRINGUP, *args],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.append(line)

    @property
    def log(self) -> str:
        return "".join(self.lines)

    def wait_for_line(self, text: str, timeout: float = 120.0) -> None:
        deadline = time.monotonic() + timeout
        while not any(text in line for line in self.lines):
            assert self.proc.poll() is None and time.monotonic() < deadline, f"no {text!r} in:\n{self.log}"
            time.sleep(0.02)

    def wait(self, timeout: float = 120.0) -> int:
        code = self.proc.wait(timeout=timeout)
        self._reader.join(timeout=10)
        return code

    def interrupt(self) -> int:
        """SIGINT to bringup (it stops its children itself); its exit code."""
        self.proc.send_signal(signal.SIGINT)
        return self.wait()

    def kill(self) -> None:
        """SIGKILL to the whole process group, if still running."""
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGKILL)
