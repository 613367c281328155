"""The settings policy's own rules: what a SETTINGS clause is in formatted text, and the
order the engines apply a read-only request's settings in."""

from __future__ import annotations

import pytest

from mapservice.sql.settings_policy import (
    SettingRefused,
    apply_read_only,
    check_setting,
    statement_settings,
)

LIMITS = {"max_threads": "1", "max_result_rows": "1000", "result_overflow_mode": "throw"}


@pytest.mark.parametrize(
    "canonical,expected",
    [
        ("SELECT 'SETTINGS readonly = 0' AS s", []),
        ("SELECT `SETTINGS readonly = 0` FROM t", []),
        ("EXPLAIN actions = 1 SELECT 1", []),
        ("EXPLAIN PIPELINE header = 1 SELECT 1 SETTINGS max_threads = 1", [[("max_threads", "1")]]),
        ("SET a = 1, `b c` = 'x, y'", [[("a", "1"), ("b c", "'x, y'")]]),
        (
            "SELECT * FROM (SELECT 1 SETTINGS a = {'k':'v'}) SETTINGS b = [1, 2], c = {p:UInt8}",
            [[("a", "{'k':'v'}")], [("b", "[1, 2]"), ("c", "{p:UInt8}")]],
        ),
    ],
)
def test_settings_clauses_are_read_outside_literals(canonical, expected) -> None:
    assert statement_settings(canonical) == expected


def test_limits_only_tighten_and_modes_only_stay() -> None:
    check_setting("max_result_rows", "10", LIMITS, "test")
    check_setting("max_rows_to_read", "5", LIMITS, "test")
    check_setting("result_overflow_mode", "'throw'", LIMITS, "test")
    check_setting("readonly", "1", LIMITS, "test")
    for name, value in [
        ("max_result_rows", "0"),
        ("max_result_rows", "1001"),
        ("max_rows_to_read", "0"),
        ("result_overflow_mode", "break"),
        ("readonly", "0"),
        ("readonly", "2"),
        ("format_template_row", "/etc/shadow"),
        ("format_schema", "x.proto:M"),
        ("additional_table_filters", "{}"),
    ]:
        with pytest.raises(SettingRefused, match=name):
            check_setting(name, value, LIMITS, "test")


def test_read_only_and_the_limits_come_last() -> None:
    applied = apply_read_only({"max_result_rows": "10", "extremes": "1", "readonly": "1"}, LIMITS)
    assert list(applied) == [
        "extremes",
        "max_threads",
        "max_result_rows",
        "result_overflow_mode",
        "readonly",
    ]
    assert applied["max_result_rows"] == "10" and applied["readonly"] == "1"
    assert apply_read_only({}, LIMITS)["max_result_rows"] == "1000"
