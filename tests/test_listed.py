"""femcal.errors.listed: how a message lists things."""

from __future__ import annotations

from femcal.errors import listed


def test_the_first_ones_are_shown_and_the_rest_counted():
    assert listed(["a", "b", "c"], most=2) == "a, b (and 1 more)"
    assert listed(["a", "b"], most=2, sep="; ") == "a; b"
    assert listed(["a"], total=4, most=2) == "a (and 2 more)"  # only some items given
    assert listed([]) == ""
