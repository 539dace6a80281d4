"""Running a console tool's ``main(argv)`` in process, as a user would from a shell."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Callable, Sequence


def call(main: Callable[[Sequence[str]], int], argv: Sequence[object]) -> tuple[int, str, str]:
    """A tool's ``main(argv)`` in process: (exit code, stdout, stderr); argparse's exits included."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 1
    return code, out.getvalue(), err.getvalue()


def one_error_line(err: str, prog: str) -> str:
    """The single line of an error exit (asserted: one non-empty line, the tool's prefix, no traceback)."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), err
    return lines[0]
