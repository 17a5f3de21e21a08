"""Shared input checks and message helpers (afm_core.checks)."""

from afm_core.checks import few


def test_few_lists_the_first_items_and_counts_the_rest():
    assert few(range(3)) == "0, 1, 2"
    assert few(range(25), shown=4) == "0, 1, 2, 3 and 21 more"
    assert few([]) == ""
