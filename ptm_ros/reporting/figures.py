"""Numbers as a person reads them: the report, ``ptm-run``'s summary and the nodes' log lines.

Measured quantities print with three significant digits (``sig(13.306258008956153)`` → ``"13.3"``,
``sig(175.50218549999386)`` → ``"176"``); values of 100 and more print as whole numbers, those below
0.001 in scientific notation. The effective sample size of the particle filter prints as a share of the
particles it is computed over (:func:`ess_fraction`: ``"1.46/100"``).
"""

from __future__ import annotations

import math

#: Significant digits of :func:`sig` by default.
DIGITS = 3


def sig(value: float, digits: int = DIGITS) -> str:
    """``value`` to ``digits`` significant digits with trailing zeros kept (``1.0000039`` → ``"1.00"``,
    ``0.04512`` → ``"0.0451"``); whole numbers from ``10**(digits-1)`` on (``278.85`` → ``"279"``,
    ``12345.6`` → ``"12346"``), scientific notation below 0.001 (``1.2e-9`` → ``"1.20e-09"``); ``"0"``
    for zero, ``"nan"`` / ``"inf"`` as Python prints them."""
    v = float(value)
    if not math.isfinite(v):
        return str(v)
    if v == 0.0:
        return "0"
    a = abs(v)
    if a >= 10.0 ** (digits - 1):
        return f"{v:.0f}"
    if a < 1e-3:
        return f"{v:.{digits - 1}e}"
    decimals = digits - 1 - math.floor(math.log10(a))
    text = f"{v:.{decimals}f}"
    # rounding may add a digit (9.996 -> "10.00"): drop the surplus decimal
    if decimals > 0 and len(text.lstrip("-").replace(".", "").lstrip("0")) > digits:
        text = f"{v:.{decimals - 1}f}"
    return text


def ess_fraction(ess: float, particles: int) -> str:
    """The effective sample size ``1/Σw²`` of ``particles`` weighted particles as ``"ESS/particles"``
    (``ess_fraction(37.24, 100)`` → ``"37.2/100"``): 1 when one particle holds all the weight,
    ``particles`` when all weigh the same."""
    return f"{sig(ess)}/{int(particles)}"
