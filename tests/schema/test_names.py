"""The one name rule (schema/names.py), as the spec, channels and storage apply it."""

from __future__ import annotations

import re

import pytest

from schema import InvalidName, NAME_PATTERN, SpecError, check_name, parse_spec

GOOD = ["a", "A1", "skin-1.v2_x", "0", "x" * 100]
BAD = ["", ".", "..", ".hidden", "-rf", "_x", "a b", "a/b", "a\\b", "é", "a\n", "x" * 101, "a\x00"]


@pytest.mark.parametrize("name", GOOD)
def test_good_names_pass_everywhere(name):
    assert check_name(name) == name
    assert re.fullmatch(NAME_PATTERN, name)
    assert parse_spec({"name": name, "medium": {"preset": "skin1"}}).name == name


@pytest.mark.parametrize("name", BAD)
def test_bad_names_are_refused_everywhere_with_the_rule(name):
    with pytest.raises(InvalidName, match=r"starting with a letter or digit; received"):
        check_name(name)
    assert re.fullmatch(NAME_PATTERN, name) is None
    with pytest.raises(SpecError, match=r"name: name must be 1\.\.100 characters"):
        parse_spec({"name": name, "medium": {"preset": "skin1"}})


def test_channel_names_follow_the_rule_with_their_own_length():
    ok = parse_spec({"name": "a", "medium": {"sigma_a": 0.1, "sigma_s": 1, "eta": 1.3, "channel_names": ["x" * 32]}})
    assert ok.medium.channel_names == ["x" * 32]
    for bad in ("x" * 33, ".r", "-g"):
        with pytest.raises(SpecError, match="channel_names entries must be 1..32 characters"):
            parse_spec({"name": "a", "medium": {"sigma_a": 0.1, "sigma_s": 1, "eta": 1.3, "channel_names": [bad]}})


def test_non_strings_are_refused():
    for value in (None, 3, ["a"]):
        with pytest.raises(InvalidName):
            check_name(value)
