"""A ClickHouse HTTP request's body: read, decoded and parsed within the user's cap, the
decoding and the parsing on threads of their own.

The cap is the user's: a read-only user's statement (MAX_QUERY_BYTES) or a writer's insert
(MAX_INSERT_BYTES), on the bytes received and again on what they decode to. A multipart
body (clickhouse-connect's statement and bound parameters over 4 KB) is parsed by
python-multipart's streaming parser with its fields counted as they come, so a body of
thousands of tiny fields is refused at the first one over MAX_FORM_FIELDS.

Decoding and parsing are CPU work proportional to the cap (a writer's is 256 MiB), so they
run on `BodyWork`'s threads: never on the event loop, which the probes and every other
request share, and never on anyio's shared threads, which a burst of bodies could fill.
A body with nothing to decode or parse (a plain statement, identity-encoded rows) takes
no thread.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import Request

from mapservice.sql.body_decoding import BodyTooLarge, content_encoding, decode
from mapservice.sql.engine import NOT_IMPLEMENTED, SqlError
from mapservice.sql.query_gate import QueryGate

CANNOT_PARSE_INPUT = 27
# Each bound parameter is a field: a thousand is more than any statement binds, and few
# enough that counting them costs nothing.
MAX_FORM_FIELDS = 1000
# A part's headers (Content-Disposition, Content-Type): a few hundred bytes in practice.
MAX_PART_HEADER_BYTES = 16 * 1024
_WRITE_STEP = 64 * 1024


@dataclass(frozen=True)
class BodyCap:
    """The most a user's body may hold (received and decoded), and what to do beyond it."""

    max_bytes: int
    advice: str


@dataclass(frozen=True)
class RequestBody:
    data: bytes  # the decoded body; empty when it was a form
    form: dict[str, str] | None  # a multipart/form-data body's fields


async def read_raw(request: Request, cap: BodyCap) -> bytes:
    """The body as received, refused (unread beyond the cap) once it passes the cap."""
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > cap.max_bytes:
            raise BodyTooLarge(cap.max_bytes, cap.advice, decoded=False)
        chunks.append(chunk)
    return b"".join(chunks)


def is_form(content_type: str) -> bool:
    # Only multipart: curl --data-binary labels a plain statement
    # application/x-www-form-urlencoded, and a ClickHouse server reads that as the statement.
    return content_type.split(";", 1)[0].strip().lower() == "multipart/form-data"


def decoded_body(raw: bytes, encoding: str, content_type: str, cap: BodyCap) -> RequestBody:
    """Blocking: the body decoded and, if a form, parsed (run it on `BodyWork`)."""
    data = decode(raw, encoding, cap.max_bytes, cap.advice)
    if is_form(content_type):
        return RequestBody(b"", form_fields(content_type, data))
    return RequestBody(data, None)


class _FormFields:
    """python-multipart's callbacks, collecting text fields and stopping at the caps."""

    def __init__(self) -> None:
        self.fields: dict[str, str] = {}
        self.count = 0
        self.ended = False
        self._header_name = bytearray()
        self._header_value = bytearray()
        self._header_bytes = 0
        self._headers: dict[bytes, bytes] = {}
        self._data: list[bytes] = []

    def callbacks(self) -> dict[str, Callable[..., None]]:
        return {
            "on_part_begin": self._part_begin,
            "on_header_field": self._header_field,
            "on_header_value": self._header_value_data,
            "on_header_end": self._header_end,
            "on_part_data": self._part_data,
            "on_part_end": self._part_end,
            "on_end": self._end,
        }

    def _part_begin(self) -> None:
        self.count += 1
        if self.count > MAX_FORM_FIELDS:
            raise SqlError(
                f"The multipart/form-data body has more than {MAX_FORM_FIELDS} fields, the "
                "limit: bind fewer parameters (pass a list as one Array parameter)",
                CANNOT_PARSE_INPUT,
            )
        self._headers, self._data, self._header_bytes = {}, [], 0

    def _count_header(self, size: int) -> None:
        self._header_bytes += size
        if self._header_bytes > MAX_PART_HEADER_BYTES:
            raise SqlError(
                f"A multipart/form-data part has more than {MAX_PART_HEADER_BYTES} bytes "
                "of headers, the limit: send a part's name in a short Content-Disposition",
                CANNOT_PARSE_INPUT,
            )

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._count_header(end - start)
        self._header_name += data[start:end]

    def _header_value_data(self, data: bytes, start: int, end: int) -> None:
        self._count_header(end - start)
        self._header_value += data[start:end]

    def _header_end(self) -> None:
        self._headers[bytes(self._header_name).strip().lower()] = bytes(self._header_value)
        self._header_name.clear()
        self._header_value.clear()

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        self._data.append(data[start:end])

    def _part_end(self) -> None:
        _, disposition = parse_options_header(self._headers.get(b"content-disposition"))
        name = _text(disposition.get(b"name", b""), "utf-8", "A part's name")
        if not name:
            raise SqlError("A multipart/form-data part has no name", CANNOT_PARSE_INPUT)
        if b"filename" in disposition:
            raise SqlError(
                f"External data ({name}: a file in the form) is not supported "
                "here; send the rows as a table in the statement",
                NOT_IMPLEMENTED,
            )
        _, content_type = parse_options_header(self._headers.get(b"content-type"))
        charset = content_type.get(b"charset", b"utf-8").decode("latin-1")
        self.fields[name] = _text(b"".join(self._data), charset, f"Form field {name}")

    def _end(self) -> None:
        self.ended = True


def _text(value: bytes, charset: str, what: str) -> str:
    try:
        return value.decode(charset)
    except (LookupError, UnicodeDecodeError) as exc:
        raise SqlError(f"{what} is not {charset} text: {exc}", CANNOT_PARSE_INPUT) from exc


def form_fields(content_type: str, body: bytes) -> dict[str, str]:
    """The fields of a multipart/form-data body (the statement as `query`, parameters as
    `param_<name>`); at most MAX_FORM_FIELDS, each part's headers within
    MAX_PART_HEADER_BYTES (the body itself is already within the user's cap)."""
    _, options = parse_options_header(content_type)
    boundary = options.get(b"boundary")
    if not boundary:
        raise SqlError(
            "Cannot parse the multipart/form-data body: its Content-Type has no boundary",
            CANNOT_PARSE_INPUT,
        )
    collected = _FormFields()
    try:
        parser = MultipartParser(boundary, callbacks=collected.callbacks())  # type: ignore[arg-type]
        for at in range(0, len(body), _WRITE_STEP):
            parser.write(body[at : at + _WRITE_STEP])
    except FormParserError as exc:
        raise SqlError(
            f"Cannot parse the multipart/form-data body: {exc}", CANNOT_PARSE_INPUT
        ) from exc
    if not collected.ended:
        raise SqlError(
            "Cannot parse the multipart/form-data body: it ends before its closing "
            f"boundary (--{boundary.decode('latin-1')}--)",
            CANNOT_PARSE_INPUT,
        )
    return collected.fields


class BodyWork:
    """Reads a request's body within a cap and decodes and parses it on `gate`'s threads.

    A gate of its own per kind of user: a burst of analysts' bodies waits for the analysts'
    threads, never for the ones the service's own inserts decode on."""

    def __init__(self, gate: QueryGate):
        self.gate = gate

    async def read(self, request: Request, cap: BodyCap) -> RequestBody:
        encoding = content_encoding(request.headers.get("content-encoding", ""))
        content_type = request.headers.get("content-type", "")
        raw = await read_raw(request, cap)
        if not encoding and not is_form(content_type):
            return RequestBody(raw, None)
        return await self.gate.run(decoded_body, raw, encoding, content_type, cap)

    def close(self) -> None:
        self.gate.close()


def body_work(kind: str) -> BodyWork:
    """Body work for `kind` users (read-only, read-write): two threads, up to 32 bodies
    waiting for them 30 s at most. Decoding a capped body takes well under a second, so a
    longer queue means a flood, refused with 503."""
    return BodyWork(
        QueryGate(
            concurrent=2,
            queued=32,
            queue_timeout_s=30,
            name=f"{kind}-body",
            who=f"{kind} users' request bodies",
        )
    )
