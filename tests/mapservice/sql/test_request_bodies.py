"""Request bodies of the ClickHouse HTTP interface: every encoding decoded within the user's
cap, multipart fields counted, and neither holding the event loop (probes every 100 ms
answer within 1 s while the heaviest bodies are refused)."""

from __future__ import annotations

import gzip
import tracemalloc
import zlib
from collections.abc import Callable

import httpx
import lz4.frame
import pytest
import zstandard

from mapservice.sql.body_decoding import ENCODINGS, OUTPUT_STEP, BodyTooLarge, decode
from mapservice.sql.chdb_engine import ChdbEngine
from mapservice.sql.engine import SqlError
from mapservice.sql.http_protocol import (
    MAX_INSERT_BYTES,
    MAX_QUERY_BYTES,
    SqlUser,
    clickhouse_http_app,
)
from mapservice.sql.read_only import ReadOnlyLimits
from mapservice.sql.request_body import MAX_FORM_FIELDS, MAX_PART_HEADER_BYTES, form_fields
from tests.heavy_requests_kit import probe_during

from .serving import ServedApp


def timed_probes(test: Callable[..., None]) -> Callable[..., None]:
    """Probes timed while a heavy request runs: an integration test run alone on the machine,
    so that another test's load does not stand for the server's."""
    marked: Callable[..., None] = pytest.mark.alone(pytest.mark.integration(test))
    return marked


MiB = 1024 * 1024
ANALYST, WRITER = ("analyst", "a-pw"), ("writer", "w-pw")
# A refused body's answer, however large it claims to be once decoded (the refusal comes
# after the cap's worth of decoding: a few milliseconds for 1 MiB, under a second for 256).
REFUSAL_WITHIN_S = 5.0


def compressed(encoding: str, data: bytes, repeat: int = 1) -> bytes:
    """`data` * `repeat`, encoded, without ever holding the whole plain text."""
    if encoding in ("gzip", "deflate"):
        stream = zlib.compressobj(9, wbits=31 if encoding == "gzip" else 15)
        out = b"".join(stream.compress(data) for _ in range(repeat))
        return out + stream.flush()
    if encoding == "lz4":
        frame = lz4.frame.LZ4FrameCompressor()
        out = frame.begin() + b"".join(frame.compress(data) for _ in range(repeat))
        return out + frame.flush()
    stream = zstandard.ZstdCompressor().compressobj()
    return b"".join(stream.compress(data) for _ in range(repeat)) + stream.flush()


def bomb(encoding: str, mib: int) -> bytes:
    """`mib` MiB of zeros, encoded: a few hundred KB at most."""
    return compressed(encoding, bytes(MiB), mib)


@pytest.fixture(scope="module")
def url(tmp_path_factory):
    engine = ChdbEngine(
        tmp_path_factory.mktemp("bodies") / "ch",
        read_only_settings=ReadOnlyLimits(max_result_rows=5000).settings(),
    )
    app = clickhouse_http_app(
        engine, [SqlUser(*WRITER, read_only=False), SqlUser(*ANALYST, read_only=True)]
    )
    with ServedApp(app) as served:
        yield served.url
    engine.close()


# --- decoding, unit by unit ------------------------------------------------------------


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_a_bomb_is_refused_after_the_caps_worth_of_memory(encoding) -> None:
    """64 MiB of zeros in each encoding, against a 1 MiB cap: refused, naming the limit,
    having held a few times the cap at most (the output growing by doubling, a decoding
    step, the library's buffers), not the 64 MiB."""
    body = bomb(encoding, 64)
    tracemalloc.start()
    try:
        with pytest.raises(BodyTooLarge) as refused:
            decode(body, encoding, MAX_QUERY_BYTES, "send less")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert f"{MAX_QUERY_BYTES} bytes" in str(refused.value) and "send less" in str(refused.value)
    assert refused.value.code == 131 and refused.value.http_status == 400
    assert peak < 3 * (MAX_QUERY_BYTES + OUTPUT_STEP) + len(body), peak


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_a_body_decoding_to_exactly_the_cap_passes_one_byte_more_does_not(encoding) -> None:
    text = bytes(range(256)) * (MAX_QUERY_BYTES // 256)
    assert decode(compressed(encoding, text), encoding, MAX_QUERY_BYTES, "") == text
    with pytest.raises(BodyTooLarge):
        decode(compressed(encoding, text + b"x"), encoding, MAX_QUERY_BYTES, "")


@pytest.mark.parametrize("encoding", ENCODINGS)
def test_concatenated_streams_decode_whole_and_truncated_ones_are_a_400(encoding) -> None:
    """gzip members, lz4 and zstd frames one after another decode to all of them (as the
    libraries' one-shot functions read them); a stream cut short is a 400 naming the
    encoding at every cut, never a silently shorter body."""
    one = compressed(encoding, b"SELECT 1; " * 1000)
    if encoding != "deflate":
        assert decode(one + one, encoding, MAX_QUERY_BYTES, "") == b"SELECT 1; " * 2000
    for cut in range(1, len(one)):
        with pytest.raises(SqlError) as failed:
            decode(one[:cut], encoding, MAX_QUERY_BYTES, "")
        assert failed.value.http_status == 400 and encoding in str(failed.value)


def test_the_writers_cap_is_the_insert_cap() -> None:
    from mapservice.sql.http_protocol import BODY_CAPS

    assert BODY_CAPS[True].max_bytes == MAX_QUERY_BYTES
    assert BODY_CAPS[False].max_bytes == MAX_INSERT_BYTES


# --- over HTTP, with the probes ---------------------------------------------------------


@timed_probes
@pytest.mark.parametrize("encoding", ENCODINGS)
def test_an_analysts_bomb_is_a_400_and_the_probes_keep_answering(url, encoding) -> None:
    """200 MiB of zeros in well under the 1 MiB a statement may take (gzip: 200 KB): a 400
    that names the limit within REFUSAL_WITHIN_S, /ping answering within 1 s meanwhile."""
    body = bomb(encoding, 200)
    assert len(body) < MAX_QUERY_BYTES
    run = probe_during(
        f"{url}/ping",
        lambda: httpx.post(
            url, content=body, auth=ANALYST, headers={"Content-Encoding": encoding}, timeout=60
        ),
        label=f"analyst's {encoding} bomb ({len(body)} bytes, 200 MiB decoded)",
    )
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 400, reply.text
    assert reply.headers["X-ClickHouse-Exception-Code"] == "131"
    assert f"decodes to more than {MAX_QUERY_BYTES} bytes" in reply.text


@timed_probes
def test_a_writers_bomb_is_refused_at_the_insert_cap(url) -> None:
    """A writer's zstd body of 300 MiB decoded: a 400 at MAX_INSERT_BYTES, probes on time."""
    body = bomb("zstd", 300)
    run = probe_during(
        f"{url}/ping",
        lambda: httpx.post(
            url,
            params={"query": "INSERT INTO t FORMAT TSV"},
            content=body,
            auth=WRITER,
            headers={"Content-Encoding": "zstd"},
            timeout=60,
        ),
        label=f"writer's zstd bomb ({len(body)} bytes, 300 MiB decoded)",
    )
    reply = run.assert_responsive(max_heavy_s=10 * REFUSAL_WITHIN_S)
    assert reply.status_code == 400 and f"more than {MAX_INSERT_BYTES} bytes" in reply.text


@pytest.mark.parametrize(
    "header", ["gzip, gzip", "gzip,deflate", "identity, gzip", "br", "compress", "x-gzip"]
)
def test_stacked_or_unknown_encodings_are_a_clear_400(url, header) -> None:
    reply = httpx.post(
        url,
        content=gzip.compress(gzip.compress(b"SELECT 1")),
        auth=ANALYST,
        headers={"Content-Encoding": header},
    )
    assert reply.status_code == 400 and repr(header) in reply.text


def multipart(fields: dict[str, bytes], boundary: str = "b0undary") -> tuple[bytes, str]:
    parts = [
        b'--%s\r\nContent-Disposition: form-data; name="%s"\r\n\r\n%s\r\n'
        % (boundary.encode(), name.encode(), value)
        for name, value in fields.items()
    ]
    body = b"".join(parts) + b"--%s--\r\n" % boundary.encode()
    return body, f"multipart/form-data; boundary={boundary}"


@timed_probes
def test_five_thousand_fields_are_a_400_and_the_probes_keep_answering(url) -> None:
    fields = {"query": b"SELECT 1"} | {f"param_p{n}": b"x" for n in range(5000)}
    body, content_type = multipart(fields)
    run = probe_during(
        f"{url}/ping",
        lambda: httpx.post(
            url, content=body, auth=ANALYST, headers={"Content-Type": content_type}, timeout=60
        ),
        label="5,000-field multipart",
    )
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 400 and f"more than {MAX_FORM_FIELDS} fields" in reply.text


@timed_probes
def test_the_largest_allowed_multipart_is_answered_and_the_probes_keep_answering(url) -> None:
    """MAX_FORM_FIELDS fields filling the 1 MiB cap: parsed off the event loop and run."""
    size = MAX_QUERY_BYTES // MAX_FORM_FIELDS - 120
    fields = {"query": b"SELECT length({p0:String})"} | {
        f"param_p{n}": b"y" * size for n in range(MAX_FORM_FIELDS - 1)
    }
    body, content_type = multipart(fields)
    assert MAX_QUERY_BYTES - 200 * MAX_FORM_FIELDS < len(body) <= MAX_QUERY_BYTES
    run = probe_during(
        f"{url}/ping",
        lambda: httpx.post(
            url, content=body, auth=ANALYST, headers={"Content-Type": content_type}, timeout=60
        ),
        label=f"{MAX_FORM_FIELDS}-field multipart of {len(body)} bytes",
    )
    reply = run.assert_responsive(max_heavy_s=REFUSAL_WITHIN_S)
    assert reply.status_code == 200 and reply.text == f"{size}\n", reply.text


def test_the_field_cap_holds_at_its_boundary_whatever_the_encoding() -> None:
    fields = {f"param_p{n}": b"1" for n in range(MAX_FORM_FIELDS)}
    body, content_type = multipart(fields)
    assert len(form_fields(content_type, body)) == MAX_FORM_FIELDS
    body, content_type = multipart(fields | {"query": b"SELECT 1"})
    with pytest.raises(SqlError, match=f"more than {MAX_FORM_FIELDS} fields"):
        form_fields(content_type, body)


def test_a_gzipped_multipart_body_is_capped_decoded_and_parsed(url) -> None:
    body, content_type = multipart({"query": b"SELECT {a:UInt8} + 1", "param_a": b"41"})
    reply = httpx.post(
        url,
        content=gzip.compress(body),
        auth=ANALYST,
        headers={"Content-Type": content_type, "Content-Encoding": "gzip"},
    )
    assert reply.text == "42\n"


@pytest.mark.parametrize(
    "body, why",
    [
        (b'--b0undary\r\nContent-Disposition: form-data; name="q"\r\n\r\nSELECT', "closing"),
        # One header line over python-multipart's own cap, and several within it but over
        # MAX_PART_HEADER_BYTES together.
        (b"--b0undary\r\nX-Pad: " + b"p" * MAX_PART_HEADER_BYTES + b"\r\n\r\n", "header"),
        (
            b"--b0undary\r\n"
            + b"".join(b"X-Pad-%d: %s\r\n" % (n, b"p" * 3000) for n in range(6))
            + b"\r\n",
            f"more than {MAX_PART_HEADER_BYTES} bytes of headers",
        ),
        (b"--b0undary\r\nContent-Disposition: form-data\r\n\r\nx\r\n--b0undary--\r\n", "no name"),
        (b"garbage", "multipart"),
    ],
)
def test_a_broken_multipart_body_is_a_clear_400(url, body, why) -> None:
    reply = httpx.post(
        url,
        content=body,
        auth=ANALYST,
        headers={"Content-Type": "multipart/form-data; boundary=b0undary"},
    )
    assert reply.status_code == 400 and why in reply.text, reply.text
