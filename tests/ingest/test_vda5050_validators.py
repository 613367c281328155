"""The VDA 5050 gateway's two schema validators: the compiled one (jsonschema-rs) passes
valid messages, the Python one (jsonschema) words a refused message's reason and judges
where the two disagree.

- their verdicts agree on every official example put into a message, and on the fuzzer's
  generated messages, for every version and subtopic;
- a valid message never reaches the Python validator (the fast path), and a refused one
  gets the same reason as without the compiled validator;
- where the compiled validator refuses what the Python one accepts (a JSON `NaN` is a
  number to Python), the message is accepted as the Python validator says.
"""

from __future__ import annotations

import json

import pytest
from hypothesis import given
from hypothesis import strategies as st
from jsonschema.exceptions import best_match

from mapservice.core.wire2019 import Limits, Reason, Rejection
from mapservice.ingest import vda5050
from mapservice.ingest.vda5050 import SUBTOPICS, VdaIngest, compiled_validator, validator

from .test_vda5050_fuzz import (
    BUDGET,
    EXAMPLES_FOUND,
    NOW,
    VERSIONS,
    message,
    mutate,
    topic,
    with_example,
)

LIMITS = Limits()


def python_verdict(version: str, subtopic: str, msg) -> bool:
    return best_match(validator(version, subtopic).iter_errors(msg)) is None


def compiled_verdict(version: str, subtopic: str, msg) -> bool:
    return compiled_validator(version, subtopic).is_valid(msg)


@pytest.mark.parametrize("version", VERSIONS)
@pytest.mark.parametrize("subtopic", SUBTOPICS)
def test_the_validators_check_the_same_patched_schema(version, subtopic) -> None:
    # The errata: a 2.0.0 state's nodePosition without theta is valid to both.
    msg = json.loads(json.dumps(message(version, subtopic)))
    assert python_verdict(version, subtopic, msg) and compiled_verdict(version, subtopic, msg)
    if (version, subtopic) == ("2.0.0", "state"):
        del msg["nodeStates"][0]["nodePosition"]["theta"]
        assert python_verdict(version, subtopic, msg) and compiled_verdict(version, subtopic, msg)
    # `format` is an annotation to both: a timestamp that is no date-time passes the schema.
    msg["timestamp"] = "yesterday"
    assert python_verdict(version, subtopic, msg) and compiled_verdict(version, subtopic, msg)


def test_the_validators_agree_on_every_official_example() -> None:
    checked = 0
    for version, subtopic, path, value in EXAMPLES_FOUND:
        field = path.removesuffix("/examples").rsplit("/", 1)[-1]
        msg, _ = with_example(version, subtopic, field, value)
        msg = json.loads(json.dumps(msg))
        for schema_version in VERSIONS:  # and against the other versions' schemas
            assert compiled_verdict(schema_version, subtopic, msg) == python_verdict(
                schema_version, subtopic, msg
            ), (schema_version, subtopic, field, value)
            checked += 1
    assert checked >= 90


def _agreement_test(version: str, subtopic: str):
    @BUDGET
    @given(data=st.data())
    def test(data) -> None:
        msg = json.loads(json.dumps(mutate(message(version, subtopic), data.draw)))
        assert compiled_verdict(version, subtopic, msg) == python_verdict(version, subtopic, msg)

    test.__doc__ = f"The validators agree on generated {version} {subtopic} messages."
    return test


# One test per version and subtopic, as in the fuzzer, so a failure names its schema.
for _v in VERSIONS:
    for _s in SUBTOPICS:
        globals()[f"test_agreement_{_v.replace('.', '_')}_{_s}"] = _agreement_test(_v, _s)


def test_a_valid_message_does_not_reach_the_python_validator(monkeypatch) -> None:
    calls: list[tuple[str, str]] = []
    python_validator = vda5050.validator

    def counting(version: str, subtopic: str):
        calls.append((version, subtopic))
        return python_validator(version, subtopic)

    monkeypatch.setattr(vda5050, "validator", counting)
    ingest = VdaIngest("uagv", {})
    for version in VERSIONS:
        for subtopic in SUBTOPICS:
            payload = json.dumps(message(version, subtopic, NOW - 1000)).encode()
            result = ingest.decode(topic(version, subtopic), payload, NOW, LIMITS)
            assert not isinstance(result, Rejection), (version, subtopic, result)
    assert calls == []

    # A refused message is judged (and its reason worded) by the Python validator.
    bad = message("2.1.0", "state", NOW - 1000)
    bad["batteryState"]["batteryCharge"] = "full"
    result = ingest.decode(topic("2.1.0", "state"), json.dumps(bad).encode(), NOW, LIMITS)
    assert calls == [("2.1.0", "state")]
    assert isinstance(result, Rejection) and result.reason is Reason.VDA_SCHEMA
    assert result.detail == (
        "not a valid VDA 5050 2.1.0 state: at batteryState/batteryCharge: "
        "'full' is not of type 'number'"
    )


def test_where_the_compiled_validator_alone_refuses_the_python_verdict_stands() -> None:
    # A NaN number: the compiled validator refuses it, Python's schema check takes it. The
    # gateway's parser refuses the token NaN before either sees it (test_vda5050.py), so
    # the disagreement is shown on the schema check itself.
    msg = message("2.0.0", "visualization", NOW - 1000)
    msg["velocity"]["vx"] = float("nan")
    assert not compiled_verdict("2.0.0", "visualization", msg)
    assert python_verdict("2.0.0", "visualization", msg)
    assert vda5050.schema_error("2.0.0", "visualization", msg) is None
    result = VdaIngest("uagv", {}).decode(
        topic("2.0.0", "visualization"), json.dumps(msg).encode(), NOW, LIMITS
    )
    assert isinstance(result, Rejection) and result.reason is Reason.NOT_JSON
