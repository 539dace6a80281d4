"""Numbers as people read them (``ptm_ros/reporting/figures.py``): three significant digits, whole numbers
from 100, scientific notation below 0.001, the ESS as a share of the particles."""

from __future__ import annotations

import math

import pytest

from ptm_ros.reporting.figures import ess_fraction, sig


@pytest.mark.parametrize(
    ("value", "text"),
    [
        (13.306258008956153, "13.3"),  # issue #25's "ess 13.306258008956153"
        (175.50218549999386, "176"),  # and its "update_ms_median 175.50218549999386"
        (1.000003920786198, "1.00"),
        (0.04512, "0.0451"),
        (0.5, "0.500"),
        (9.996, "10.0"),  # rounding up adds no digit
        (99.96, "100"),
        (278.8545398789153, "279"),
        (12345.6, "12346"),
        (-3.14159, "-3.14"),
        (0.001, "0.00100"),
        (1.2e-9, "1.20e-09"),
        (0.0, "0"),
        (math.inf, "inf"),
        (math.nan, "nan"),
    ],
)
def test_sig(value, text):
    assert sig(value) == text


def test_sig_other_digits_and_the_ess_fraction():
    assert sig(0.123456, 2) == "0.12"
    assert sig(1234.5, 5) == "1234.5"
    assert ess_fraction(37.24, 100) == "37.2/100"
    assert ess_fraction(1.0000039, 100) == "1.00/100"
