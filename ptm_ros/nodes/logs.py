"""Logging of the nodes' problems, without rclpy: once as a warning, then at debug level."""

from __future__ import annotations

from typing import Any, Protocol


class Logger(Protocol):
    """What the nodes' rclpy-free logic logs through: an rclpy node's logger or a :mod:`logging` logger."""

    def debug(self, message: str) -> Any: ...
    def info(self, message: str) -> Any: ...
    def warning(self, message: str) -> Any: ...
    def error(self, message: str) -> Any: ...


class OnceLogger:
    """Logs the first occurrence of each kind of problem as a warning and later ones at debug level."""

    def __init__(self, logger: Logger) -> None:
        self._logger = logger
        self._seen: set[str] = set()

    def __call__(self, kind: str, message: str) -> None:
        if kind in self._seen:
            self._logger.debug(message)
            return
        self._seen.add(kind)
        self._logger.warning(f"{message} (further '{kind}' problems are counted in /diagnostics, not logged)")
