"""Paths on the command line. Output paths are checked before the work (issue #25): a tool that would fail
on its first write after minutes of inference fails at once instead, with one line naming the fix (exit
code 2)."""

from __future__ import annotations

import argparse
import os
import tempfile
from pathlib import Path

from ptm_ros.errors import ConfigError


def _probe(directory: Path, what: str) -> None:
    """Create and remove a file in ``directory`` (permissions, read-only file systems, root or not)."""
    try:
        with tempfile.TemporaryFile(dir=directory):
            pass
    except OSError as err:
        reason = err.strerror or type(err).__name__
        msg = f"cannot write into {directory} ({reason}): choose a writable {what}"
        raise ConfigError(msg) from err


def _nearest_existing(path: Path, what: str) -> Path:
    """The nearest existing ancestor of ``path`` (which does not exist), checked to be a directory."""
    ancestor = path.absolute().parent
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        msg = f"cannot create {what} {path}: {ancestor} is a file, not a directory"
        raise ConfigError(msg)
    return ancestor


def output_dir(path: Path, flag: str = "--out") -> Path:
    """Check that the output directory ``path`` can be written: an existing directory files can be
    created in, or a new one whose nearest existing ancestor is such a directory (nothing is created).

    Raises:
        ConfigError: ``path`` is an existing file, or it cannot be created or written in.
    """
    path = Path(path)
    if path.exists() and not path.is_dir():
        msg = f"{flag} {path} is an existing file, not a directory: choose a directory (new or existing)"
        raise ConfigError(msg)
    _probe(path if path.exists() else _nearest_existing(path, f"{flag} directory"), flag)
    return path


def new_output(path: Path, what: str = "OUT_BAG") -> Path:
    """Check that ``path`` (a bag directory to create) does not exist and that its nearest existing
    ancestor is a writable directory; nothing is created.

    Raises:
        ConfigError: ``path`` exists, or cannot be created there.
    """
    path = Path(path)
    if os.path.lexists(path):
        kind = "directory" if path.is_dir() else "file"
        msg = f"{what} {path} exists already (a {kind}); choose a new path (rosbag2 never overwrites)"
        raise ConfigError(msg)
    _probe(_nearest_existing(path, what), what)
    return path


def add_params_option(parser: argparse.ArgumentParser) -> None:
    """The ``--params FILE`` option of the tools that read a parameter file (ptm-run, ptm-calibrate)."""
    parser.add_argument(
        "--params",
        type=Path,
        default=None,
        help="YAML parameter file, any subset of config/ptm.yaml (default: none, the built-in defaults)",
    )
