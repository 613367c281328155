"""The faust app is configured like the confluent-kafka clients."""

from __future__ import annotations

import faust

from mapservice.processors.app import _faust_credentials, faust_broker_url
from mapservice.settings import Settings


def test_plaintext_has_no_credentials():
    """PLAINTEXT without a user gives faust no credentials."""
    assert _faust_credentials(Settings()) is None


def test_sasl_ssl_carries_user_and_tls_context():
    """SASL_SSL with a user gives SASL credentials with a TLS context and the mechanism."""
    creds = _faust_credentials(
        Settings(
            kafka_security_protocol="SASL_SSL",
            kafka_sasl_mechanism="SCRAM-SHA-512",
            kafka_username="u",
            kafka_password="p",
        )
    )
    assert isinstance(creds, faust.SASLCredentials)
    assert creds.username == "u" and creds.password == "p"
    assert creds.ssl_context is not None
    assert str(creds.mechanism.value) == "SCRAM-SHA-512"


def test_ssl_without_user_uses_tls_only():
    """SSL without a user gives TLS credentials."""
    assert isinstance(
        _faust_credentials(Settings(kafka_security_protocol="SSL")), faust.SSLCredentials
    )


def test_broker_url_lists_every_bootstrap_server():
    """Each bootstrap server becomes a kafka:// URL for faust."""
    url = faust_broker_url(Settings(kafka_bootstrap="a:9092, b:9093"))
    assert url == "kafka://a:9092;kafka://b:9093"


def test_ssl_ca_file_is_loaded_into_the_faust_context(tmp_path):
    """MAPSERVICE_KAFKA_SSL_CA_FILE is the CA the processors' TLS context trusts; a missing file fails loudly."""
    import certifi
    import pytest

    creds = _faust_credentials(
        Settings(kafka_security_protocol="SSL", kafka_ssl_ca_file=certifi.where())
    )
    assert creds.context.get_ca_certs()
    with pytest.raises(FileNotFoundError):
        _faust_credentials(
            Settings(kafka_security_protocol="SSL", kafka_ssl_ca_file=tmp_path / "missing.pem")
        )


def test_the_faust_group_heartbeats_every_three_seconds_within_a_third_of_its_session(tmp_path):
    """A quiet plant's `serve` pays a heartbeat every 3 s, not every second; a short
    session still gets three heartbeats in it."""
    from mapservice.processors.app import faust_app

    default = faust_app(Settings(data_dir=tmp_path)).conf
    assert (default.broker_heartbeat_interval, default.broker_session_timeout) == (3.0, 10.0)
    short = faust_app(
        Settings(data_dir=tmp_path, kafka_session_timeout_s=3, kafka_rebalance_timeout_s=3)
    ).conf
    assert short.broker_heartbeat_interval == 1.0
