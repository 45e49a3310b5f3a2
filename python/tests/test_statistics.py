"""The intervals the evaluation reports, against published values."""

from __future__ import annotations

import pytest
from scdp import metaworld


def paired_results(both: int, only_a: int, only_b: int, neither: int) -> tuple[dict, dict]:
    """Two `eval` results on the same seeds with the given 2x2 table of outcomes."""
    n = both + only_a + only_b + neither
    seeds = range(n)
    a_fails = [s for s in seeds if s >= both + only_a]
    b_fails = [s for s in seeds if both <= s < both + only_a or s >= both + only_a + only_b]
    return ({"first_seed": 0, "episodes": n, "failed_seeds": a_fails},
            {"first_seed": 0, "episodes": n, "failed_seeds": b_fails})


@pytest.mark.parametrize("table, expected", [
    # Newcombe (1998), Statistics in Medicine 17, 2635-2650, table II, method 10.
    ((36, 12, 2, 0), (0.0569, 0.3404)),
])
def test_paired_difference_interval_is_newcombes(table, expected):
    a, b = paired_results(*table)
    paired = metaworld.paired_difference_interval(a, b)
    assert paired["difference_95"] == pytest.approx(expected, abs=5e-5)
    assert paired["discordant"] == [table[1], table[2]]


def test_paired_difference_interval_of_identical_outcomes_holds_zero():
    a, _ = paired_results(150, 0, 0, 50)
    paired = metaworld.paired_difference_interval(a, a)
    low, high = paired["difference_95"]
    assert paired["difference"] == 0 and low < 0 < high


def test_wilson_interval():
    # Newcombe (1998), Statistics in Medicine 17, 857-872, table I, method 3: 81/263.
    assert metaworld.wilson_interval(81, 263) == pytest.approx((0.2553, 0.3662), abs=5e-5)
