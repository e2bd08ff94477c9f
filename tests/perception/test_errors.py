"""How error messages show a bad value (:func:`perception.errors.shown`)."""

from __future__ import annotations

from perception.errors import shown


def test_plain_values_read_as_repr():
    assert shown(0.5) == "0.5" and shown("1") == "'1'" and shown(None) == "None" and shown(True) == "True"


def test_long_values_are_abbreviated():
    assert len(shown("x" * 10_000)) < 40 and len(shown(list(range(10_000)))) < 60


def test_an_integer_too_long_to_print_is_shown_by_its_size():
    """Python refuses to print integers of over 4,300 digits (ValueError from repr): the message names its size."""
    assert shown(10**5000) == f"an integer of {(10**5000).bit_length():,} bits"
    assert shown(-(10**5000)).startswith("an integer of")
