"""The API as `serve` runs it (uvicorn with its own protocol settings, the access guard, the
pools, the analysts' /clickhouse): the heaviest bodies an analyst can send are refused
while /healthz answers within a second."""

from __future__ import annotations

import gzip
import threading

import httpx
import pytest
import uvicorn
from mapservice.api.composition import api_server_config

from mapservice.local.embedded import free_port
from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.http_protocol import MAX_QUERY_BYTES, SqlUser, clickhouse_http_app
from mapservice.sql.read_only import ReadOnlyLimits
from mapservice.sql.request_body import MAX_FORM_FIELDS
from tests.api.access_kit import app_for, settings_for
from tests.heavy_requests_kit import probe_during
from tests.mapservice.sql.serving import ServedApp

ANALYST = ("analyst", "an-analysts-password")
REFUSAL_WITHIN_S = 5.0


class ServedApi(ServedApp):
    """ServedApp with the API's own uvicorn configuration."""

    def __init__(self, app, settings):
        super().__init__(app)
        self.port, self.url = settings.api_port, f"http://127.0.0.1:{settings.api_port}"
        self.server = uvicorn.Server(api_server_config(app, settings))
        self.thread = threading.Thread(target=self.server.run, daemon=True)


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    engine = ChdbEngine(
        tmp_path_factory.mktemp("api-sql") / "ch",
        read_only_settings=ReadOnlyLimits().settings(),
    )
    port = free_port()
    settings = settings_for("open", api_host="127.0.0.1", api_port=port)
    sql = clickhouse_http_app(engine, [SqlUser(*ANALYST, read_only=True)])
    with ServedApi(app_for(settings, sql_app=sql), settings) as served:
        yield served.url
    engine.close()


def test_a_gzip_bomb_on_clickhouse_is_a_400_while_healthz_answers(api) -> None:
    """300 MiB of zeros in 300 KB of gzip (the size that once grew the API by 1.4 GB)."""
    stream = gzip.compress(bytes(1024 * 1024), 9)  # one member per MiB: 300 members
    body = stream * 300
    assert len(body) < MAX_QUERY_BYTES
    run = probe_during(
        f"{api}/healthz",
        lambda: httpx.post(
            f"{api}/clickhouse",
            content=body,
            auth=ANALYST,
            headers={"Content-Encoding": "gzip"},
            timeout=60,
        ),
        label=f"gzip bomb on the API's /clickhouse ({len(body)} bytes, 300 MiB decoded)",
    )
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 400, reply.text
    assert f"more than {MAX_QUERY_BYTES} bytes" in reply.text


def test_five_thousand_fields_on_clickhouse_are_a_400_while_healthz_answers(api) -> None:
    body = b"".join(
        b'--zz\r\nContent-Disposition: form-data; name="param_p%d"\r\n\r\n1\r\n' % n
        for n in range(5000)
    )
    body += b'--zz\r\nContent-Disposition: form-data; name="query"\r\n\r\nSELECT 1\r\n--zz--\r\n'
    run = probe_during(
        f"{api}/healthz",
        lambda: httpx.post(
            f"{api}/clickhouse",
            content=body,
            auth=ANALYST,
            headers={"Content-Type": "multipart/form-data; boundary=zz"},
            timeout=60,
        ),
        label="5,000-field multipart on the API's /clickhouse",
    )
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 400 and f"more than {MAX_FORM_FIELDS} fields" in reply.text
