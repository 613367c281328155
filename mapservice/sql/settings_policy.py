"""Which settings a read-only user (the analysts) may send, by any channel.

A setting can come as a URL parameter, a multipart form field, a `SETTINGS` clause (in any
subquery), a `SET` statement or a query parameter bound into one of them: every channel
goes through `check_setting`. Allowed are

- a short, named set of output and format settings that only change how the result is
  written (`HARMLESS`); format settings that name a file (`format_schema`,
  `format_template_*`) are not among them: the engine would read that file;
- the limits, only to tighten them: a positive number at most the limit in force (0 means
  "unlimited" to the engine, so it is refused).

Everything else is refused with a message naming the setting. The engines then apply the
allowed settings first, the limits (the tighter of the two) after them and `readonly = 1`
last (`apply_read_only`), so nothing a request sends can lift read-only or a limit.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping

from mapservice.sql.engine import ACCESS_DENIED, SqlError

# Settings that change only how a result is written out, never what is read or computed,
# where or how long. clickhouse-connect reads system.settings and sends none of them to a
# read-only user; these are for curl, Grafana and analysts who ask for a format's variant.
HARMLESS = frozenset(
    {
        "date_time_output_format",
        "output_format_decimal_trailing_zeros",
        "output_format_json_quote_64bit_integers",
        "output_format_json_quote_64bit_floats",
        "output_format_json_quote_decimals",
        "output_format_json_quote_denormals",
        "output_format_json_named_tuples_as_objects",
        "output_format_json_array_of_rows",
        "output_format_json_validate_utf8",
        "output_format_write_statistics",
        "output_format_pretty_max_rows",
        "output_format_pretty_max_value_width",
        "output_format_pretty_color",
        "output_format_pretty_grid_charset",
        "output_format_csv_crlf_end_of_line",
        "output_format_tsv_crlf_end_of_line",
        "output_format_arrow_string_as_string",
        "output_format_parquet_string_as_string",
        "output_format_native_write_json_as_string",
        "format_csv_delimiter",
        "format_csv_null_representation",
        "format_tsv_null_representation",
        "extremes",
    }
)
# Limits with no value of their own here: any positive value tightens them (0: unlimited).
UNSET_LIMITS = frozenset({"max_result_bytes", "max_rows_to_read", "max_bytes_to_read"})
# X-ClickHouse-* request headers of a ClickHouse server's HTTP interface (credentials,
# the database, the output format, a quota key, clickhouse-connect's certificate login,
# which this interface does not offer, so the password still decides). Any other is
# refused for a read-only user rather than ignored: a client that meant it as a setting
# learns it had no effect.
PROTOCOL_HEADERS = frozenset(
    {
        "x-clickhouse-user",
        "x-clickhouse-key",
        "x-clickhouse-database",
        "x-clickhouse-format",
        "x-clickhouse-quota",
        "x-clickhouse-ssl-certificate-auth",
    }
)
_NUMBER = re.compile(r"^\s*'?(\d+(\.\d+)?)'?\s*$")


class SettingRefused(SqlError):
    def __init__(self, message: str):
        super().__init__(message, ACCESS_DENIED)


def _number(value: str) -> float | None:
    found = _NUMBER.match(value)
    return float(found.group(1)) if found else None


def check_setting(name: str, value: str, limits: Mapping[str, str], channel: str) -> None:
    """Raises SettingRefused unless `name = value`, sent by `channel` ("URL parameter",
    "SETTINGS clause", ...), is harmless or tightens a limit of `limits`."""
    if name in HARMLESS:
        return
    if name == "readonly" and value.strip("'") == "1":
        return  # what it is already (a server's client, e.g. our ServerEngine, sends it)
    if name in limits and _number(limits[name]) is None:  # a mode: only as it is
        if value.strip("'") == limits[name]:
            return
        raise SettingRefused(
            f"Setting {name} = {value[:40]!r} ({channel}) is not allowed for analysts: it "
            f"is {limits[name]} for them"
        )
    if name in limits or name in UNSET_LIMITS:
        asked = _number(value)
        ceiling = _number(limits[name]) if name in limits else None
        if asked is not None and asked > 0 and (ceiling is None or asked <= ceiling):
            return
        bound = f"a positive number up to {limits[name]}" if name in limits else "positive"
        raise SettingRefused(
            f"Setting {name} = {value[:40]!r} ({channel}) is not allowed for analysts: this "
            f"limit may only be tightened ({bound})"
        )
    raise SettingRefused(
        f"Setting {name} ({channel}) is not allowed for analysts: only output settings "
        f"({', '.join(sorted(HARMLESS))}) and tighter limits "
        f"({', '.join(sorted({*limits, *UNSET_LIMITS} - {'result_overflow_mode'}))}) are; "
        "read-only and the limits are fixed"
    )


def check_headers(names: Iterable[str]) -> None:
    for name in names:
        if name.lower().startswith("x-clickhouse-") and name.lower() not in PROTOCOL_HEADERS:
            raise SettingRefused(
                f"Header {name} is not understood here: send settings as URL parameters "
                f"(headers read: {', '.join(sorted(PROTOCOL_HEADERS))})"
            )


def check_settings(settings: Mapping[str, str], limits: Mapping[str, str], channel: str) -> None:
    for name, value in settings.items():
        check_setting(name, value, limits, channel)


def apply_read_only(settings: Mapping[str, str], limits: Mapping[str, str]) -> dict[str, str]:
    """The settings a read-only statement runs with, in the order to apply them: the
    request's own (already checked), the limits (a request's tighter value kept), then
    `readonly = 1`. A later entry wins over an earlier one. Raises SettingRefused for a
    setting the policy does not allow (the protocol refused it already; an engine called
    directly holds the same line)."""
    check_settings(
        {k: v for k, v in settings.items() if k != "readonly"}, limits, "request setting"
    )
    applied = {k: v for k, v in settings.items() if k != "readonly" and k not in limits}
    for name, limit in limits.items():
        asked, ceiling = _number(settings.get(name, "")), _number(limit)
        tighter = asked is not None and asked > 0 and ceiling is not None and asked < ceiling
        applied[name] = settings[name] if tighter else limit
    applied["readonly"] = "1"
    return applied


# --- settings inside a statement -------------------------------------------------------

_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_PARAMETER = re.compile(r"^\{(\w+):[^}]*\}$")


def _skip_quoted(text: str, i: int) -> int:
    """The index after the quoted literal or identifier starting at `i`."""
    quote, j = text[i], i + 1
    while j < len(text) and text[j] != quote:
        j += 2 if text[j] == "\\" else 1
    return j + 1


def _value_end(text: str, i: int) -> int:
    """The end of the literal starting at `i` (a string, number, map, array or tuple; a
    query parameter `{name:Type}`): the first space, comma or closing bracket outside it."""
    depth = 0
    while i < len(text):
        char = text[i]
        if char in "'\"`":
            i = _skip_quoted(text, i)
            continue
        if char in "([{":
            depth += 1
        elif char in ")]}":
            if depth == 0:
                return i
            depth -= 1
        elif depth == 0 and (char.isspace() or char == ","):
            return i
        i += 1
    return i


def _settings_list(text: str, i: int) -> tuple[list[tuple[str, str]], int] | None:
    """`name = value, name = value` from `i` on, as formatQuerySingleLine writes a SETTINGS
    clause or a SET statement; None where the text there is not one."""
    pairs: list[tuple[str, str]] = []
    while True:
        while i < len(text) and text[i] == " ":
            i += 1
        if i < len(text) and text[i] == "`":
            end = _skip_quoted(text, i)
            name = text[i + 1 : end - 1]
        else:
            word = _WORD.match(text, i)
            if not word:
                return None
            name, end = word.group(), word.end()
        if not text.startswith(" = ", end):
            return None
        value_start = end + 3
        value_end = _value_end(text, value_start)
        pairs.append((name, text[value_start:value_end]))
        i = value_end
        if not text.startswith(", ", i):
            return pairs, i
        i += 2


def statement_settings(canonical: str) -> list[list[tuple[str, str]]]:
    """The settings each SETTINGS clause (any subquery, CTE or EXPLAIN) and a SET statement
    of `canonical` (formatQuerySingleLine's text) change, clause by clause. String
    literals and quoted identifiers are skipped, so `'SETTINGS x = 1'` is no clause; the
    caller compares the number of clauses with the `Set` nodes of the engine's parse."""
    clauses, i = [], 0
    if canonical.startswith("SET "):
        found = _settings_list(canonical, 4)
        if found:
            clauses.append(found[0])
            i = found[1]
    elif canonical.startswith("EXPLAIN "):
        # `EXPLAIN [kind] option = value, ... <statement>`: EXPLAIN's own options, no settings.
        i = len("EXPLAIN ")
        while (word := _WORD.match(canonical, i)) and word.group().isupper():
            i = word.end() + 1
        found = _settings_list(canonical, i)
        if found:
            i = found[1]
    while i < len(canonical):
        char = canonical[i]
        if char in "'\"`":
            i = _skip_quoted(canonical, i)
            continue
        word = _WORD.match(canonical, i)
        if not word:
            i += 1
            continue
        i = word.end()
        if word.group() == "SETTINGS" and canonical.startswith(" ", i):
            found = _settings_list(canonical, i + 1)
            if found:
                clauses.append(found[0])
                i = found[1]
    return clauses


def parameter_value(value: str, params: Mapping[str, str]) -> str:
    """A setting's value as it runs: a query parameter `{name:Type}` is its bound value."""
    found = _PARAMETER.match(value)
    return params.get(found.group(1), value) if found else value
