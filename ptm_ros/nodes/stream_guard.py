"""Stamp jumps, duplicates and teleports of the nodes' input streams, without rclpy (issue #9).

A live robot's topics, and a replayed bag's, deliver messages whose stamps go back (a bag looped, a clock
reset), jump forward, repeat, or whose odometry jumps in space; :class:`StreamGuard` tells these from a
bad message by waiting for consistent messages to confirm them (:class:`GuardConfig`). The landmark
detector keeps one guard per input stream (:mod:`ptm_ros.nodes.detector_inbox`).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ptm_ros.errors import ConfigError

#: Odometry steps up to this long are never a teleport (absorbs stamp jitter: a CARMEN log's logger
#: timestamps give apparent speeds of 14 m/s over 20 ms steps).
TELEPORT_SLACK_M = 1.0

#: Events of :class:`StreamGuard` (``Admission.event``).
START, FORWARD_JUMP, CLOCK_RESET, TELEPORT = "start", "forward-jump", "clock-reset", "teleport"


@dataclass(frozen=True)
class GuardConfig:
    """How a stream guard tells a stamp jump or an odometry teleport from a bad message.

    Attributes:
        stamp_jump_s: a stamp more than this before the stream's latest is a jump back (s), and one
            more than this after it always a jump forward (a smaller limit applies once the stream's
            rate is known: :meth:`StreamGuard.forward_limit`); must exceed the longest regular gap
            between two messages of any topic.
        confirm: consecutive, mutually consistent messages that confirm a jump or a stream's start.
        max_speed: fastest plausible odometry motion (m/s): a step longer than
            ``max_speed·Δt + TELEPORT_SLACK_M`` is a teleport; ``inf`` turns the check off.
    """

    stamp_jump_s: float = 30.0
    confirm: int = 3
    max_speed: float = 5.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.stamp_jump_s) and self.stamp_jump_s > 0.0):
            msg = f"stamp_jump_s must be finite and > 0, got {self.stamp_jump_s}"
            raise ConfigError(msg)
        if self.confirm < 1:
            msg = f"jump_confirm must be >= 1, got {self.confirm}"
            raise ConfigError(msg)
        if not self.max_speed > 0.0:
            msg = f"max_speed must be > 0 (inf: no teleport check), got {self.max_speed}"
            raise ConfigError(msg)


@dataclass(frozen=True)
class Admission:
    """What :meth:`StreamGuard.admit` decided about one message.

    Attributes:
        released: ``(stamp, payload)`` to use now, in stream order (the message itself, or the held
            messages a confirmation releases); empty while a jump is held or for a duplicate.
        duplicate: the message repeats the stream's latest (same stamp, equal payload).
        outliers: held messages dropped because the stream went back to its timeline.
        event: ``start`` (the stream's first messages confirmed), ``forward-jump``, ``clock-reset``
            (stamps jumped back: bag looped, clock reset), ``teleport`` (odometry jumped in space), or None.
    """

    released: tuple[tuple[float, Any], ...] = ()
    duplicate: bool = False
    outliers: int = 0
    event: str | None = None


class StreamGuard:
    """Duplicates, stamp jumps and teleports of one message stream (per topic, in arrival order).

    * A message repeating the latest or a held one (same stamp, ``equal`` payloads) is a duplicate.
    * A message more than ``stamp_jump_s`` before the latest, more than :meth:`forward_limit` after it,
      or (with ``position``) farther from it than ``max_speed·Δt + TELEPORT_SLACK_M``, is a *jump* and is
      held, appended to the first
      held run it continues consistently (stamps non-decreasing, steps within ``stamp_jump_s``,
      plausible speed), else starting a new run from the longest beginning of a held run it continues
      (the good messages held before a bad one that came between them), else from nothing (at most
      :attr:`MAX_RUNS` runs; the oldest is dropped). The first run to reach ``confirm`` messages is
      released (the messages of no other run in it are outliers); a message back on the old timeline
      drops every run (outliers). A confirmed backward jump is a clock reset.
    * The stream's first messages are held the same way (event ``start``), so that a lone bad message
      cannot set the timeline.
    * Any other message is released at once (a small step back in time too: the consumer decides).

    Args:
        config: thresholds.
        equal: whether two payloads are the same message.
        position: ``(x, y)`` of a payload, for the teleport check (odometry); None: stamps only.
    """

    MAX_RUNS = 8
    GAP_HISTORY = 32  # recent gaps between accepted messages kept for the forward limit
    GAP_FACTOR = 10.0  # forward limit = GAP_FACTOR x their lower quartile ...
    MIN_FORWARD_S = 0.25  # ... but at least this long (s)

    def __init__(
        self,
        config: GuardConfig,
        *,
        equal: Callable[[Any, Any], bool],
        position: Callable[[Any], tuple[float, float]] | None = None,
    ) -> None:
        self.config = config
        self._equal = equal
        self._position = position
        self._last: tuple[float, Any] | None = None
        self._runs: list[tuple[str, list[tuple[float, Any]]]] = []  # (event, messages) held
        self._gaps: deque[float] = deque(maxlen=self.GAP_HISTORY)
        self._forward = config.stamp_jump_s

    def forward_limit(self) -> float:
        """How far (s) a message may follow the latest one before it is a forward jump: ``GAP_FACTOR``
        times the lower quartile of the stream's recent gaps (its confirmed start on), at least
        ``MIN_FORWARD_S``, at most ``stamp_jump_s`` (which applies until two gaps are known). A lone
        message stamped seconds ahead would otherwise make the consumer drop every later message older
        than it. (Held runs only need steps within ``stamp_jump_s``, so a stream whose rate drops is
        delayed by ``confirm`` messages per step, never stopped, until the quartile follows.)"""
        return self._forward

    def _accept(self, stamp: float, payload: Any) -> None:
        if self._last is not None and stamp > self._last[0]:
            self._gaps.append(stamp - self._last[0])
            if len(self._gaps) >= 2:
                quartile = float(np.percentile(np.fromiter(self._gaps, dtype=float), 25.0))
                limit = max(self.MIN_FORWARD_S, self.GAP_FACTOR * quartile)
                self._forward = min(self.config.stamp_jump_s, limit)
        self._last = (stamp, payload)

    @property
    def held(self) -> int:
        """Messages held for confirmation (each once: runs may share their first messages)."""
        return len({id(m) for _, run in self._runs for m in run})

    @property
    def last_stamp(self) -> float | None:
        """Stamp of the latest accepted message (None before the stream's start is confirmed)."""
        return None if self._last is None else self._last[0]

    def _too_far(self, a: tuple[float, Any], stamp: float, payload: Any) -> bool:
        if self._position is None or not math.isfinite(self.config.max_speed):
            return False
        (xa, ya), (xb, yb) = self._position(a[1]), self._position(payload)
        dt = max(stamp - a[0], 0.0)
        return math.hypot(xb - xa, yb - ya) > self.config.max_speed * dt + TELEPORT_SLACK_M

    def _jump(self, stamp: float, payload: Any) -> str | None:
        assert self._last is not None
        last = self._last[0]
        if stamp < last - self.config.stamp_jump_s:
            return CLOCK_RESET
        if stamp >= last and self._too_far(self._last, stamp, payload):
            return TELEPORT
        if stamp > last + self._forward:
            return FORWARD_JUMP
        return None

    def _consistent(self, prev: tuple[float, Any], stamp: float, payload: Any) -> bool:
        in_time = prev[0] <= stamp <= prev[0] + self.config.stamp_jump_s
        return in_time and not self._too_far(prev, stamp, payload)

    def _is_duplicate(self, ref: tuple[float, Any] | None, stamp: float, payload: Any) -> bool:
        return ref is not None and ref[0] == stamp and bool(self._equal(ref[1], payload))

    def admit(self, stamp: float, payload: Any) -> Admission:
        """Decide about the next message of the stream (``stamp`` finite, payload validated)."""
        refs = [self._last, *(run[-1] for _, run in self._runs)]
        if any(self._is_duplicate(ref, stamp, payload) for ref in refs):
            return Admission(duplicate=True)
        event = START if self._last is None else self._jump(stamp, payload)
        if event is None:
            outliers = self.held
            self._runs.clear()
            assert self._last is not None  # else the event is START
            if stamp >= self._last[0]:
                self._accept(stamp, payload)
            return Admission(released=((stamp, payload),), outliers=outliers)
        outliers = 0
        run = next((r for _, r in self._runs if self._consistent(r[-1], stamp, payload)), None)
        if run is None:
            run_event, run = self._fork(stamp, payload)
            self._runs.append((run_event or event, run))
            if len(self._runs) > self.MAX_RUNS:
                _, oldest = self._runs.pop(0)
                outliers += self._unheld(oldest)
        run.append((stamp, payload))
        if len(run) < self.config.confirm:
            return Admission(outliers=outliers)
        return self._release(run, outliers)

    def _fork(self, stamp: float, payload: Any) -> tuple[str | None, list[tuple[float, Any]]]:
        """A new run for a message that continues no held run: the longest beginning of a held run it
        continues (a good message that arrived before a bad one held in the same run, e.g. a copy
        stamped ahead just after the stream's first message), with that run's event; else empty."""
        best: tuple[str | None, list[tuple[float, Any]]] = (None, [])
        for run_event, run in self._runs:
            for k in range(len(run) - 1, -1, -1):
                if self._consistent(run[k], stamp, payload):
                    if k + 1 > len(best[1]):
                        best = (run_event, run[: k + 1])
                    break
        return best

    def _unheld(self, messages: list[tuple[float, Any]]) -> int:
        """How many of ``messages`` no held run has (runs may share their first messages)."""
        held = {id(m) for _, run in self._runs for m in run}
        return sum(id(m) not in held for m in messages)

    def _release(self, run: list[tuple[float, Any]], outliers: int = 0) -> Admission:
        event = next(e for e, r in self._runs if r is run)
        outliers += self.held - len(run)
        self._runs.clear()
        self._last = run[0]  # the jump itself is no gap of the stream
        for stamp, payload in run:
            self._accept(stamp, payload)
        return Admission(released=tuple(run), outliers=outliers, event=event)

    def settle(self) -> Admission:
        """End of input: release the longest held start or forward jump (nothing refuted it; the
        earliest of equally long ones); drop held clock resets and teleports (too few messages to confirm
        them) and every other run (outliers)."""
        usable = [r for e, r in self._runs if e in (START, FORWARD_JUMP)]
        if usable:
            return self._release(max(usable, key=len))
        outliers = self.held
        self._runs.clear()
        return Admission(outliers=outliers)


def sum_counters(a: Mapping[str, Any], b: Mapping[str, Any]) -> dict[str, Any]:
    """Counters of ``a`` plus those of ``b``, key by key (nested mappings recursively; a value that is
    not a number is taken from ``b``)."""
    out: dict[str, Any] = dict(a)
    for key, value in b.items():
        mine = out.get(key)
        if isinstance(value, Mapping):
            out[key] = sum_counters(mine if isinstance(mine, Mapping) else {}, value)
        elif isinstance(value, int | float) and not isinstance(value, bool) and isinstance(mine, int | float):
            out[key] = mine + value
        else:
            out[key] = value
    return out
