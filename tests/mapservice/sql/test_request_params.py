"""Naming parameters (query_id, database, user, ...) with a control, format or line-break
character: a 400 naming the parameter, through every channel, never a dropped connection
(a query_id comes back in a response header)."""

from __future__ import annotations

import sys
import unicodedata

import httpx
import pytest

from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import SqlError
from mapservice.sql.http_protocol import SqlUser, clickhouse_http_app
from mapservice.sql.request_params import ASCII_PARAMS, NAMING_HEADERS, NAMING_PARAMS, check_value

from .serving import ServedApp

ANALYST = ("analyst", "a-pw")
# Every C0 and C1 control character and DEL, the line and paragraph separators.
CONTROLS = [chr(c) for c in (*range(0x20), 0x7F, *range(0x80, 0xA0), 0x2028, 0x2029)]


@pytest.fixture(scope="module")
def url(tmp_path_factory):
    engine = ChdbEngine(tmp_path_factory.mktemp("params") / "ch")
    app = clickhouse_http_app(engine, [SqlUser(*ANALYST, read_only=True)])
    with ServedApp(app) as served:
        yield served.url
    engine.close()


# The planes with assigned characters (basic, supplementary, ideographic, tags and variation
# selectors) whole, and the private-use planes' edges.
CODE_POINTS = [
    *range(0x30000),
    *range(0xE0000, 0xE1000),
    *(0xF0000, 0xFFFFD, 0x100000, sys.maxunicode),
]


def test_every_character_a_name_may_hold_is_printable_and_an_echoed_one_is_ascii() -> None:
    """What check_value accepts for query_id fits a header (printable ASCII), and what it
    accepts for any naming parameter is printable (no category C or Z but the space)."""
    accepted_id = set()
    for code in CODE_POINTS:
        char = chr(code)
        try:
            check_value("database", char)
        except SqlError:
            pass
        else:
            category = unicodedata.category(char)
            assert char == " " or category[0] not in "CZ", hex(code)
        try:
            check_value("query_id", char)
            accepted_id.add(char)
        except SqlError:
            pass
    assert accepted_id == {chr(c) for c in range(0x20, 0x7F)}


@pytest.mark.parametrize("name", sorted(NAMING_PARAMS))
def test_a_control_character_in_a_url_parameter_is_a_400(url, name) -> None:
    """Each naming URL parameter x each control character, in the middle of a fit value:
    a 400 that names the parameter, on a connection that stays usable."""
    with httpx.Client(auth=ANALYST, timeout=30) as client:
        for char in CONTROLS:
            reply = client.post(url, params={name: f"ab{char}cd"}, content=b"SELECT 1")
            assert reply.status_code == 400, (name, hex(ord(char)), reply.text)
            assert f"The {name} parameter has" in reply.text
            assert reply.headers["X-ClickHouse-Exception-Code"] == "36"
        assert client.post(url, content=b"SELECT 1").text == "1\n"


@pytest.mark.parametrize("name", sorted(ASCII_PARAMS))
def test_an_echoed_parameter_outside_ascii_is_a_400(url, name) -> None:
    for value in ("é", "日本", "\U0001f600"):
        reply = httpx.post(url, params={name: value}, content=b"SELECT 1", auth=ANALYST, timeout=30)
        assert reply.status_code == 400 and "printable ASCII" in reply.text


@pytest.mark.parametrize("name", sorted(NAMING_PARAMS))
def test_a_control_character_in_a_form_field_is_a_400(url, name) -> None:
    with httpx.Client(auth=ANALYST, timeout=30) as client:
        for char in CONTROLS:
            reply = client.post(url, files={"query": (None, "SELECT 1"), name: (None, f"x{char}")})
            assert reply.status_code == 400 and f"The {name} parameter has" in reply.text


@pytest.mark.parametrize("header", sorted(NAMING_HEADERS))
def test_a_control_character_in_a_header_is_a_400(url, header) -> None:
    """What HTTP lets through in a header value (a tab, C1 bytes read as Latin-1)."""
    with httpx.Client(auth=ANALYST, timeout=30) as client:
        for char in ["\t", *(chr(c) for c in range(0x80, 0xA0))]:
            value = f"x{char}y".encode("latin-1")
            reply = client.post(url, content=b"SELECT 1", headers={header: value})
            assert reply.status_code == 400, (header, hex(ord(char)))
            assert f"The {NAMING_HEADERS[header]} parameter has" in reply.text


def test_a_fit_query_id_is_echoed(url) -> None:
    reply = httpx.post(
        url, params={"query_id": "nightly-report 7"}, content=b"SELECT 1", auth=ANALYST
    )
    assert reply.headers["X-ClickHouse-Query-Id"] == "nightly-report 7"
