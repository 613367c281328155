"""Webhook deliveries are signed so that a receiver can tell them authentic and fresh, wait
longer after each failed try up to a cap, and only URLs a delivery may go to are accepted:
checked on generated bodies, secrets, clocks and URLs."""

from __future__ import annotations

import string

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapservice.adapters.webhook_urls import URL_MAX_CHARS, check_url
from mapservice.core.webhooks import (
    SIGNATURE_HEADER,
    TIMESTAMP_HEADER,
    WebhookHealth,
    backoff_s,
    check_secret,
    derived_secret,
    signed_headers,
    verify,
)

secrets = st.text(
    alphabet=string.ascii_letters + string.digits + "!#$%&*+-./:=?@^_~", min_size=16, max_size=64
)


@given(secrets, st.binary(max_size=2000), st.integers(0, 2**33))
def test_a_signed_delivery_verifies_and_any_change_does_not(secret, body, ts) -> None:
    headers = signed_headers(secret, ts, body)
    assert headers[SIGNATURE_HEADER].startswith("sha256=")
    assert verify(secret, headers, body, now_s=ts)
    # header names are case-insensitive in HTTP
    assert verify(secret, {k.lower(): v for k, v in headers.items()}, body, now_s=ts)
    assert not verify(secret + "x", headers, body, now_s=ts)
    assert not verify(secret, headers, body + b" ", now_s=ts)
    moved = {**headers, TIMESTAMP_HEADER: str(ts + 1)}  # a replay under a fresher timestamp
    assert not verify(secret, moved, body, now_s=ts + 1)
    assert not verify(secret, {**headers, TIMESTAMP_HEADER: "soon"}, body, now_s=ts)


@given(st.integers(0, 2**33), st.floats(0, 10_000))
def test_a_delivery_is_fresh_only_within_the_tolerance(ts, late) -> None:
    headers = signed_headers("0123456789abcdef", ts, b"{}")
    assert verify("0123456789abcdef", headers, b"{}", ts + late, 300) is (late <= 300)


@given(st.integers(1, 200), st.floats(0.01, 10), st.floats(0.01, 600))
def test_backoff_doubles_from_the_base_up_to_the_cap(attempt, base, cap) -> None:
    wait = backoff_s(attempt, base, cap)
    assert wait == min(cap, base * 2 ** (attempt - 1))
    assert backoff_s(attempt + 1, base, cap) >= wait


def test_backoff_counts_tries_from_one() -> None:
    with pytest.raises(ValueError):
        backoff_s(0, 1, 60)


hosts = st.from_regex(r"[a-z][a-z0-9-]{0,20}(\.[a-z]{2,6}){0,2}", fullmatch=True)
paths = st.from_regex(r"(/[A-Za-z0-9._~-]{0,12}){0,4}", fullmatch=True)
ports = st.one_of(st.just(""), st.integers(1, 65535).map(lambda p: f":{p}"))


@given(st.sampled_from(["http", "https"]), hosts, ports, paths)
def test_http_and_https_urls_with_a_host_are_accepted(scheme, host, port, path) -> None:
    url = f"{scheme}://{host}{port}{path}"
    assert check_url(url) == url


def bad_urls():
    good = st.builds(lambda h, p: f"https://{h}{p}", hosts, paths)
    return st.one_of(
        # other schemes
        st.builds(
            lambda s, h: f"{s}://{h}/",
            st.sampled_from(["ftp", "file", "gopher", "javascript", "ws", "mqtt", "HTTP-X"]),
            hosts,
        ),
        # credentials in the URL
        st.builds(
            lambda u, h: f"https://{u}@{h}/",
            st.from_regex(r"[a-z]{1,8}(:[a-z0-9]{1,8})?", fullmatch=True),
            hosts,
        ),
        # no host, a bad port, a fragment, whitespace or control characters
        st.sampled_from(
            [
                "https://",
                "https:///path",
                "http://:80/",
                "https://h:0/",
                "https://h:99999/",
                "https://h:port/",
            ]
        ),
        st.builds(lambda u: u + "#frag", good),
        st.builds(
            lambda u, c: u + c + "x", good, st.sampled_from([" ", "\t", "\n", "\x00", "\x7f"])
        ),
        # too long
        st.builds(lambda u: u + "/" + "a" * URL_MAX_CHARS, good),
        # not a URL at all
        st.text(alphabet=string.ascii_letters + "/:.", max_size=30).filter(
            lambda t: "://" not in t
        ),
    )


@given(bad_urls())
def test_every_bad_url_is_refused_with_a_reason(url) -> None:
    with pytest.raises(ValueError) as refused:
        check_url(url)
    assert str(refused.value).startswith("the URL")


@given(
    st.one_of(
        st.text(max_size=15),
        st.text(min_size=257, max_size=300),
        st.text(min_size=16).filter(lambda s: any(not ("!" <= c <= "~") for c in s)),
    )
)
def test_a_short_long_or_unprintable_secret_is_refused(secret) -> None:
    with pytest.raises(ValueError, match="the secret"):
        check_secret(secret)


def test_a_paused_webhook_says_why_and_a_resume_clears_it() -> None:
    health = WebhookHealth()
    health.tried_and_failed("HTTP 500", 1_000)
    assert (health.last_try_ms, health.last_result) == (1_000, "HTTP 500")
    health.pause(6)
    assert health.state == "paused" and "6 tries" in health.paused_reason
    assert "HTTP 500" in health.paused_reason
    health.resume()
    assert health.state == "active" and health.last_error == "HTTP 500"
    health.succeeded(2_000)
    assert (health.last_try_ms, health.last_result, health.delivered) == (2_000, "delivered", 1)
    assert health.last_error == "HTTP 500"  # the last failure stays told


@given(st.text(min_size=1, max_size=64), st.text(min_size=1, max_size=64))
def test_a_derived_secret_is_a_valid_one_and_differs_by_key_and_webhook(key, webhook_id) -> None:
    secret = derived_secret(key, webhook_id)
    assert check_secret(secret) == secret == derived_secret(key, webhook_id)
    assert derived_secret(key + "x", webhook_id) != secret
    assert derived_secret(key, webhook_id + "x") != secret


def test_no_secret_is_derived_without_a_key() -> None:
    with pytest.raises(ValueError, match="no signing key"):
        derived_secret("", "wh-0000000000000001")
