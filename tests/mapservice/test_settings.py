"""Settings: environment overrides, production safety, Kafka client configuration."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import SecretStr, ValidationError

from mapservice.settings import DEFAULT_ADMIN_TOKEN, Settings


TOKEN = "t" * 32


def test_local_defaults() -> None:
    """Without environment, the local defaults apply (2019 MQTT topics, 7-day retention, no built-in admin token)."""
    s = Settings()
    assert s.mode == "local"
    # No publicly known default: local mode generates the API's tokens in the data dir.
    assert s.admin_token.get_secret_value() == "" and s.api_writer_tokens.get_secret_value() == ""
    assert s.api_read_access == "open"
    assert (s.create_chunk_topic, s.coordinate_topic) == ("iot/chunks/create", "iot/coordinates/#")
    assert s.retention_ms == 7 * 86_400_000
    assert s.mqtt_subscriptions == ["iot/chunks/create", "iot/coordinates/#"]


def test_production_refuses_default_admin_token() -> None:
    """mode=production without an admin token, or with the old public default, is refused, naming the variable to set."""
    with pytest.raises(ValidationError, match="MAPSERVICE_ADMIN_TOKEN is empty"):
        Settings(mode="production")
    with pytest.raises(ValidationError, match="MAPSERVICE_ADMIN_TOKEN is the old local default"):
        Settings(mode="production", admin_token=DEFAULT_ADMIN_TOKEN)


@pytest.mark.parametrize("field", ["admin_token", "api_writer_tokens", "api_reader_tokens",
                                   "api_metrics_token"])
def test_production_refuses_short_tokens(field) -> None:
    """A token under 32 characters (e.g. a 1-character admin token) is refused in production, naming its variable; local mode takes it."""
    tokens = {"admin_token": TOKEN, field: f"{'u' * 40}, short"}
    with pytest.raises(ValidationError, match=f"MAPSERVICE_{field.upper()} holds a token of 5 characters"):
        Settings(mode="production", **tokens)
    with pytest.raises(ValidationError, match="MAPSERVICE_ADMIN_TOKEN holds a token of 1 characters"):
        Settings(mode="production", admin_token="t")
    assert Settings(**tokens).mode == "local"


def test_token_lists_are_comma_or_space_separated() -> None:
    """MAPSERVICE_API_WRITER_TOKENS holds one token per robot, separated by commas or whitespace; empty is none."""
    from mapservice.settings import token_list

    s = Settings(api_writer_tokens=f" {'a' * 32},{'b' * 32}\n{'c' * 32} ")
    assert token_list(s.api_writer_tokens) == ["a" * 32, "b" * 32, "c" * 32]
    assert token_list(Settings().api_reader_tokens) == []
    assert "a" * 32 not in repr(s)  # secrets stay out of logs


def test_production_refuses_default_admin_token_from_env(monkeypatch) -> None:
    """MAPSERVICE_MODE=production from the environment is refused with the default token too."""
    monkeypatch.setenv("MAPSERVICE_MODE", "production")
    with pytest.raises(ValidationError, match="MAPSERVICE_ADMIN_TOKEN"):
        Settings()
    monkeypatch.setenv("MAPSERVICE_ADMIN_TOKEN", "s3cret-from-vault-" + "x" * 16)
    s = Settings()
    assert s.mode == "production" and s.admin_token.get_secret_value() == "s3cret-from-vault-" + "x" * 16


def test_production_refuses_empty_clickhouse_password_for_a_server() -> None:
    """Against a ClickHouse server, production needs a password; embedded chDB does not."""
    with pytest.raises(ValidationError, match="MAPSERVICE_CLICKHOUSE_PASSWORD"):
        Settings(mode="production", admin_token=SecretStr(TOKEN),
                 clickhouse_dsn="http://clickhouse:8123")
    ok = Settings(mode="production", admin_token=SecretStr(TOKEN),
                  clickhouse_dsn="http://clickhouse:8123", clickhouse_password=SecretStr("pw"))
    assert ok.resolved_clickhouse_dsn == "http://clickhouse:8123"
    assert Settings(mode="production", admin_token=SecretStr(TOKEN)).mode == "production"


def test_env_vars_override(monkeypatch) -> None:
    """MAPSERVICE_* variables override defaults, with type conversion."""
    monkeypatch.setenv("MAPSERVICE_KAFKA_BOOTSTRAP", "kafka-1:9093,kafka-2:9093")
    monkeypatch.setenv("MAPSERVICE_MAX_GRID", "64")
    monkeypatch.setenv("MAPSERVICE_MAX_FUTURE_SKEW_S", "2.5")
    monkeypatch.setenv("MAPSERVICE_MQTT_SHARE_GROUP", "gw")
    monkeypatch.setenv("mapservice_retention_days", "3")  # case-insensitive
    monkeypatch.setenv("KAFKA_BOOTSTRAP", "ignored-without-prefix:1")
    s = Settings()
    assert s.kafka_bootstrap == "kafka-1:9093,kafka-2:9093"
    assert s.max_grid == 64 and s.max_future_skew_s == 2.5
    assert s.retention_ms == 3 * 86_400_000
    assert s.mqtt_subscriptions == ["$share/gw/iot/chunks/create", "$share/gw/iot/coordinates/#"]


def test_invalid_env_value_is_refused(monkeypatch) -> None:
    """An out-of-bounds value from the environment fails loudly."""
    monkeypatch.setenv("MAPSERVICE_KAFKA_PARTITIONS", "0")
    with pytest.raises(ValidationError, match="kafka_partitions"):
        Settings()


def test_clickhouse_dsn_defaults_to_chdb_in_data_dir(tmp_path: Path) -> None:
    """An empty clickhouse_dsn means embedded chDB under data_dir."""
    s = Settings(data_dir=tmp_path)
    assert s.resolved_clickhouse_dsn == f"chdb://{(tmp_path / 'clickhouse').resolve()}"


def test_kafka_config_without_sasl() -> None:
    """Without credentials, kafka_config has only the bootstrap and protocol."""
    assert Settings().kafka_config() == {"bootstrap.servers": "127.0.0.1:9092",
                                         "security.protocol": "PLAINTEXT"}


def test_kafka_config_includes_sasl_credentials(monkeypatch) -> None:
    """With SASL settings, kafka_config passes mechanism, username and the secret password."""
    monkeypatch.setenv("MAPSERVICE_KAFKA_SECURITY_PROTOCOL", "SASL_SSL")
    monkeypatch.setenv("MAPSERVICE_KAFKA_SASL_MECHANISM", "SCRAM-SHA-512")
    monkeypatch.setenv("MAPSERVICE_KAFKA_USERNAME", "mapservice")
    monkeypatch.setenv("MAPSERVICE_KAFKA_PASSWORD", "kafka-pw")
    s = Settings()
    assert s.kafka_config() == {
        "bootstrap.servers": "127.0.0.1:9092",
        "security.protocol": "SASL_SSL",
        "sasl.mechanism": "SCRAM-SHA-512",
        "sasl.username": "mapservice",
        "sasl.password": "kafka-pw",
    }
    assert "kafka-pw" not in repr(s)  # the secret does not leak into logs


def test_kafka_topics_lists_all_five() -> None:
    """kafka_topics lists the chunk, pose, meta, dead-letter and live topics."""
    assert Settings(topic_meta_events="m").kafka_topics == [
        "mapservice.chunk-events.v1", "mapservice.pose-events.v1", "m",
        "mapservice.dead-letter.v1", "mapservice.live.v1"]


def test_kafka_ca_file_reaches_librdkafka(tmp_path: Path) -> None:
    """MAPSERVICE_KAFKA_SSL_CA_FILE becomes librdkafka's ssl.ca.location; unset, none is set."""
    ca = tmp_path / "ca.crt"
    assert "ssl.ca.location" not in Settings().kafka_config()
    conf = Settings(kafka_security_protocol="SASL_SSL", kafka_ssl_ca_file=ca).kafka_config()
    assert conf["ssl.ca.location"] == str(ca)
