"""VDA 5050 through the gateway's message handler (`Ingestor.handle`: routing, validation,
dead letters, the producer contract), on the fuzzers' one harness (fuzz_kit.py):

- every official example in the vendored schemas (the `examples` of their fields; the
  VDA5050 repository has no example messages) put into a valid message of its version and
  subtopic: accepted, or dead-lettered with the reason its value calls for (the version
  example `1.3.2` has no schema; the timestamp examples are from 1991);
- generated messages per version and subtopic (fields replaced, dropped or added anywhere,
  in objects and arrays; raw bytes, truncated JSON, deep nesting, over-size): each one
  acknowledged, and either accepted or dead-lettered with a known reason; a message the
  official schema refuses is never accepted (its dead letter says `vda_schema` and where).

Budget: MAPSERVICE_FUZZ_VDA_EXAMPLES generated messages per version and subtopic (default
200, derandomized so a failure reproduces).
"""

from __future__ import annotations

import json
import os
import re

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapservice.core.wire2019 import Reason, format_timestamp
from mapservice.ingest.vda5050 import SCHEMA_DIR, SUBTOPICS, schema_version_for, validator
from tests.fixtures import vda5050 as vda
from tests.ingest.fuzz_kit import NOW, FuzzedGateway, budget, mutate, raw_nasties

VERSIONS = ("2.0.0", "2.1.0", "3.0.0")
BUDGET = budget(int(os.environ.get("MAPSERVICE_FUZZ_VDA_EXAMPLES", "200")))
# Fields an added value is named by, besides generated names: the header's and a map's.
FIELD_NAMES = ("", "x", "version", "timestamp", "mapId")


def topic(version: str, subtopic: str) -> str:
    return f"uagv/v{version[0]}/Acme/001/{subtopic}"


def message(version: str, subtopic: str, ms: int = NOW - 1000) -> dict:
    if subtopic == "connection":
        return vda.connection(version, "Acme", "001", ms, "ONLINE")
    return getattr(vda, subtopic)(version, "Acme", "001", ms)


# Thousands of "message rejected" info lines would cost more than the handling.
pytestmark = pytest.mark.usefixtures("quiet_rejection_logs")


@pytest.fixture(scope="module")
def handler() -> FuzzedGateway:
    return FuzzedGateway("vda-fuzz")


def handle(handler: FuzzedGateway, mqtt_topic: str, payload: bytes) -> tuple[str | None, str]:
    """The message's fate: (None, robot id) accepted, (reason, detail) dead-lettered."""
    fate = handler.fate(mqtt_topic, payload)
    if fate.letter is None:
        assert fate.event is not None
        return None, fate.event.robot_id
    return fate.letter.reason, fate.letter.detail


# ---- the official examples ---------------------------------------------------------------


def schema_examples() -> list[tuple[str, str, str, object]]:
    """(version, subtopic, the field's schema path, example) for every example in the
    vendored schemas."""
    found = []

    def walk(node, path: str, version: str, subtopic: str) -> None:
        if isinstance(node, dict):
            for value in node.get("examples", ()) if isinstance(node.get("examples"), list) else ():
                found.append((version, subtopic, path, value))
            for key, child in node.items():
                if key != "examples":
                    walk(child, f"{path}/{key}", version, subtopic)
        elif isinstance(node, list):
            for i, child in enumerate(node):
                walk(child, f"{path}/{i}", version, subtopic)

    for version in VERSIONS:
        for subtopic in SUBTOPICS:
            schema = json.loads((SCHEMA_DIR / version / f"{subtopic}.schema").read_text())
            walk(schema, "", version, subtopic)
    return found


def with_example(version: str, subtopic: str, field: str, value) -> tuple[dict, str | None]:
    """A valid message of the version and subtopic carrying the example in its field, and
    the dead-letter reason the example's value calls for (None: accepted)."""
    msg = message(version, subtopic)
    if field == "timestamp":
        return {**msg, "timestamp": value}, Reason.TIMESTAMP_TOO_OLD.value
    if field == "version":
        supported = schema_version_for(value, f"v{version[0]}")
        return (
            {**message(supported, subtopic), "version": value}
            if supported
            else {**msg, "version": value}
        ), None if supported else Reason.VDA_UNSUPPORTED_VERSION.value
    if field == "actionId":
        action_state = {"actionId": value, "actionType": "pick", "actionStatus": "WAITING"}
        return {**msg, "actionStates": [action_state]}, None
    if field == "loadPosition":
        return {**msg, "loads": [{"loadId": "L1", "loadPosition": value}]}, None
    if field in ("key", "value"):  # a factsheet's software versions
        config = "mobileRobotConfiguration" if version.startswith("3") else "vehicleConfig"
        entry = {"key": "softwareVersion", "value": "v1.0"} | {field: value}
        return {**msg, config: {**msg.get(config, {}), "versions": [entry]}}, None
    raise AssertionError(
        f"no place for the example of {field!r} in a {version} {subtopic}: "
        "a newer schema brought a new example; give it its place here"
    )


EXAMPLES_FOUND = schema_examples()


def test_the_vendored_schemas_carry_examples() -> None:
    assert len(EXAMPLES_FOUND) >= 30
    assert {v for v, *_ in EXAMPLES_FOUND} == set(VERSIONS)


@pytest.mark.parametrize(
    ("version", "subtopic", "path", "value"),
    EXAMPLES_FOUND,
    ids=[f"{v}-{s}-{p.rsplit('/', 1)[-1]}-{x}" for v, s, p, x in EXAMPLES_FOUND],
)
def test_every_official_example_is_accepted_or_dead_lettered_for_its_value(
    handler, version, subtopic, path, value
) -> None:
    field = re.sub(r"/examples$", "", path).rsplit("/", 1)[-1] if path else ""
    # The example is valid for its field (the schema's own word).
    sub = validator(version, subtopic).schema
    for part in path.strip("/").split("/"):
        sub = sub[int(part)] if isinstance(sub, list) else sub[part]
    if "$ref" not in sub:
        assert not list(type(validator(version, subtopic))(sub).iter_errors(value))
    msg, reason = with_example(version, subtopic, field, value)
    got, detail = handle(handler, topic(version, subtopic), json.dumps(msg).encode())
    assert got == reason, detail
    if field == "timestamp":  # its format, at an instant within the retention: accepted
        recent = value.replace("1991-03-11", format_timestamp(NOW - 86_400_000)[:10])
        assert (
            handle(
                handler, topic(version, subtopic), json.dumps({**msg, "timestamp": recent}).encode()
            )[0]
            is None
        )


# ---- generated messages ------------------------------------------------------------------


@st.composite
def vda_payloads(draw, version: str, subtopic: str) -> tuple[bytes, dict | None]:
    good = message(version, subtopic)
    if draw(st.integers(0, 4)) == 0:
        return draw(raw_nasties(good)), None
    msg = mutate(good, draw, FIELD_NAMES)
    return json.dumps(msg).encode(), msg


def refused_by_the_schema(version: str, subtopic: str, msg) -> bool:
    """The official schema (of the message's own version, on this topic) refuses it."""
    if not isinstance(msg, dict):
        return False
    schema_version = schema_version_for(msg.get("version"), f"v{version[0]}")
    return schema_version is not None and bool(
        next(validator(schema_version, subtopic).iter_errors(msg), None)
    )


def fuzz(handler, version: str, subtopic: str, payload: bytes, msg) -> None:
    reason, detail = handle(handler, topic(version, subtopic), payload)
    if refused_by_the_schema(version, subtopic, msg):
        # never accepted: refused by the schema, or before it for its size
        assert reason in (Reason.VDA_SCHEMA.value, Reason.OVERSIZED.value), (reason, detail)
        if reason == Reason.VDA_SCHEMA.value:
            assert "not a valid VDA 5050 " in detail and " at " in detail
    if reason is None:
        assert detail == "Acme:001"


# One test per version and subtopic, so each has its own budget and a failure names it.
def _fuzz_test(version: str, subtopic: str):
    @BUDGET
    @given(case=vda_payloads(version, subtopic))
    def test(handler, case) -> None:
        fuzz(handler, version, subtopic, *case)

    test.__doc__ = f"Generated VDA 5050 {version} {subtopic} messages: accepted or dead-lettered."
    return test


for _v in VERSIONS:
    for _s in SUBTOPICS:
        globals()[f"test_fuzz_{_v.replace('.', '_')}_{_s}"] = _fuzz_test(_v, _s)


def test_after_the_fuzzing_every_subtopic_is_still_accepted(handler) -> None:
    for version in VERSIONS:
        for subtopic in SUBTOPICS:
            reason, detail = handle(
                handler, topic(version, subtopic), json.dumps(message(version, subtopic)).encode()
            )
            assert reason is None, (version, subtopic, detail)
