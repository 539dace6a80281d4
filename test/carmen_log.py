"""A small CARMEN log with every kind of line, well-formed and malformed (test_carmen, test_convert)."""

from __future__ import annotations

import gzip
from pathlib import Path

# Line numbers matter: the tests refer to them.
LOG_LINES = [
    "# CARMEN test log",  # 1
    "PARAM robot_front_laser_max 7.5 nohost 0",  # 2
    "",  # 3
    "ODOM 0.5 -0.25 0.125 0.3 -0.1 0 100.5 hostA 0.5",  # 4
    "FLASER 4 1.0 2.0 3.0 4.5 1.1 2.2 0.3 1.0 2.0 0.25 100.75 hostA 0.75",  # 5
    "NEFF 27.6 0 pippo 0",  # 6
    "FLASER 5 1 2 3 4 5 0 0 3.2 0 0 3.2 101.0 hostB 1.0",  # 7
    "ROBOTLASER1 0 -1.5 3.0 0.5 30.0 0.01 0 7 1 2 3 4 5 6 7 2 10 20 "
    "1.0 2.0 0.1 0.9 1.9 0.05 0.4 0.2 1.5 0.5 0.3 101.25 hostC 1.25",  # 8
    "SYNC foo",  # 9
    "FLASER 3 1 2 0 0 0 0 0 0 5.0 h 5.0",  # 10: one range short
    "ODOM 1 2 abc 0 0 0 1 h 1",  # 11: non-numeric theta
    "FLASER x 1 2",  # 12: non-integer count
    "ODOM 1 2 nan 0 0 0 1 h 1",  # 13: non-finite pose
    "ROBOTLASER1 0 -1.5 3.0 0.5 30.0 0.01 0 7 1 2 3",  # 14: truncated
    "ODOM 2.0 3.0 -3.0 0 0 0 102.0 hostA 2.0",  # 15
    "  # indented comment",  # 16
    "FLASER 0 0 0 0 0 0 0 1 h 1",  # 17: no beams
]
#: The lines of LOG_LINES (1-based) the parser reports as malformed.
MALFORMED_LINES = [10, 11, 12, 13, 14, 17]


def write_log(path: Path, lines: list[str] = LOG_LINES, *, gz: bool = False) -> Path:
    """``lines`` written to ``path`` (gzip-compressed with ``gz``)."""
    text = "\n".join(lines) + "\n"
    if gz:
        with gzip.open(path, "wt") as f:
            f.write(text)
    else:
        path.write_text(text)
    return path
