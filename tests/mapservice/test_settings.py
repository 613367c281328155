"""Settings: environment overrides, production safety, Kafka client configuration."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import SecretStr, ValidationError

from mapservice.settings import DEFAULT_ADMIN_TOKEN, Settings

VDA = ("state", "visualization", "connection", "factsheet")  # what VDA 5050 vehicles publish


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
    assert s.mqtt_subscriptions == [
        "iot/chunks/create",
        "iot/coordinates/#",
        "iot/chunks/create/+",
        *(f"uagv/+/+/+/{t}" for t in VDA),
        "iot/robots/+/command-events",
    ]


def test_production_refuses_default_admin_token() -> None:
    """mode=production without an admin token, or with the old public default, is refused, naming the variable to set."""
    with pytest.raises(ValidationError, match="MAPSERVICE_ADMIN_TOKEN is empty"):
        Settings(mode="production")
    with pytest.raises(ValidationError, match="MAPSERVICE_ADMIN_TOKEN is the old local default"):
        Settings(mode="production", admin_token=DEFAULT_ADMIN_TOKEN)


@pytest.mark.parametrize(
    "field", ["admin_token", "api_writer_tokens", "api_reader_tokens", "api_metrics_token"]
)
def test_production_refuses_short_tokens(field) -> None:
    """A token under 32 characters (e.g. a 1-character admin token) is refused in production, naming its variable; local mode takes it."""
    tokens = {"admin_token": TOKEN, field: f"{'u' * 40}, short"}
    with pytest.raises(
        ValidationError, match=f"MAPSERVICE_{field.upper()} holds a token of 5 characters"
    ):
        Settings(mode="production", **tokens)
    with pytest.raises(
        ValidationError, match="MAPSERVICE_ADMIN_TOKEN holds a token of 1 characters"
    ):
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
    assert (
        s.mode == "production"
        and s.admin_token.get_secret_value() == "s3cret-from-vault-" + "x" * 16
    )


def test_production_refuses_empty_clickhouse_password_for_a_server() -> None:
    """Against a ClickHouse server, production needs a password; embedded chDB does not."""
    with pytest.raises(ValidationError, match="MAPSERVICE_CLICKHOUSE_PASSWORD"):
        Settings(
            mode="production", admin_token=SecretStr(TOKEN), clickhouse_dsn="http://clickhouse:8123"
        )
    ok = Settings(
        mode="production",
        admin_token=SecretStr(TOKEN),
        clickhouse_dsn="http://clickhouse:8123",
        clickhouse_password=SecretStr("pw"),
    )
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
    assert s.mqtt_subscriptions == [
        "$share/gw/iot/chunks/create",
        "$share/gw/iot/coordinates/#",
        "$share/gw/iot/chunks/create/+",
        *(f"$share/gw/uagv/+/+/+/{t}" for t in VDA),
        "$share/gw/iot/robots/+/command-events",
    ]


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
    assert Settings().kafka_config() == {
        "bootstrap.servers": "127.0.0.1:9092",
        "security.protocol": "PLAINTEXT",
    }


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


def test_kafka_topics_lists_all_seven() -> None:
    """kafka_topics lists the chunk, pose, meta, dead-letter, live, annotation and command topics."""
    assert Settings(topic_meta_events="m").kafka_topics == [
        "mapservice.chunk-events.v1",
        "mapservice.pose-events.v1",
        "m",
        "mapservice.dead-letter.v1",
        "mapservice.live.v1",
        "mapservice.annotation-events.v1",
        "mapservice.command-events.v1",
    ]


def test_kafka_ca_file_reaches_librdkafka(tmp_path: Path) -> None:
    """MAPSERVICE_KAFKA_SSL_CA_FILE becomes librdkafka's ssl.ca.location; unset, none is set."""
    ca = tmp_path / "ca.crt"
    assert "ssl.ca.location" not in Settings().kafka_config()
    conf = Settings(kafka_security_protocol="SASL_SSL", kafka_ssl_ca_file=ca).kafka_config()
    assert conf["ssl.ca.location"] == str(ca)


@pytest.fixture
def cert_chains(monkeypatch) -> list[tuple]:
    """Every client certificate an ssl.SSLContext loads (file names), recorded."""
    import ssl

    loaded: list[tuple] = []
    original = ssl.SSLContext.load_cert_chain

    def load_cert_chain(self, certfile, keyfile=None, password=None):
        loaded.append((str(certfile), str(keyfile)))
        return original(self, certfile, keyfile, password)

    monkeypatch.setattr(ssl.SSLContext, "load_cert_chain", load_cert_chain)
    return loaded


def test_kafka_client_certificate_reaches_librdkafka_and_faust(tmp_path: Path, cert_chains) -> None:
    """MAPSERVICE_KAFKA_SSL_CERT_FILE/KEY_FILE become librdkafka's ssl.certificate.location and
    ssl.key.location (every confluent-kafka client) and the faust SSL context's cert chain."""
    from mapservice.local.certs import make_client_cert
    from mapservice.processors.app import _faust_credentials

    files = make_client_cert(tmp_path, "mapservice")
    s = Settings(
        kafka_security_protocol="SSL",
        kafka_ssl_ca_file=files.ca_file,
        kafka_ssl_cert_file=files.cert_file,
        kafka_ssl_key_file=files.key_file,
    )
    conf = s.kafka_config()
    assert (
        conf["ssl.ca.location"],
        conf["ssl.certificate.location"],
        conf["ssl.key.location"],
    ) == (str(files.ca_file), str(files.cert_file), str(files.key_file))
    assert "ssl.certificate.location" not in Settings().kafka_config()
    creds = _faust_credentials(s)
    assert creds.context.cert_store_stats()["x509_ca"] == 1
    assert cert_chains == [(str(files.cert_file), str(files.key_file))]
    with pytest.raises(ValueError, match="go together"):
        Settings(kafka_security_protocol="SSL", kafka_ssl_cert_file=files.cert_file)
    with pytest.raises(ValueError, match="SSL or SASL_SSL"):
        Settings(kafka_ssl_cert_file=files.cert_file, kafka_ssl_key_file=files.key_file)


def test_clickhouse_tls_files_reach_clickhouse_connect_and_the_sql_engine(
    tmp_path: Path, monkeypatch, cert_chains
) -> None:
    """MAPSERVICE_CLICKHOUSE_CA_FILE/CERT_FILE/KEY_FILE are passed to clickhouse-connect's
    get_client (ca_cert, client_cert, client_cert_key) by the store (writer, reader, ping) and
    to the analysts' SQL engine's TLS context; only for an https:// DSN."""
    import clickhouse_connect

    from mapservice.adapters.clickhouse.store import ClickHouseStore
    from mapservice.local.certs import make_client_cert
    from mapservice.sql.apps import engine_for

    files = make_client_cert(tmp_path, "mapservice")
    s = Settings(
        clickhouse_dsn="https://ch.example:8443",
        clickhouse_ca_file=files.ca_file,
        clickhouse_cert_file=files.cert_file,
        clickhouse_key_file=files.key_file,
    )
    expected = {
        "ca_cert": str(files.ca_file),
        "client_cert": str(files.cert_file),
        "client_cert_key": str(files.key_file),
    }
    assert s.clickhouse_tls() == expected
    calls: list[dict] = []
    monkeypatch.setattr(clickhouse_connect, "get_client", lambda **kw: calls.append(kw) or object())
    store = ClickHouseStore.from_settings(s)
    store.connect()
    try:
        store.ping()
    except AttributeError:
        pass  # the fake client has no command(); the arguments are what counts
    assert len(calls) == 2 and all({k: c[k] for k in expected} == expected for c in calls)
    engine = engine_for(s)
    context = engine._http._transport._pool._ssl_context
    assert context.cert_store_stats()["x509_ca"] == 1
    assert cert_chains == [(str(files.cert_file), str(files.key_file))]
    assert Settings().clickhouse_tls() == {}
    with pytest.raises(ValueError, match="https://"):
        Settings(clickhouse_dsn="http://ch:8123", clickhouse_ca_file=files.ca_file)


def test_mqtt_tls_files_reach_paho(tmp_path: Path, cert_chains) -> None:
    """MAPSERVICE_MQTT_CA_FILE/CERT_FILE/KEY_FILE become the gateway's and advertiser's paho
    tls_set (CA and client certificate); they need an mqtts:// URL."""
    from mapservice.adapters.mqtt_client import service_client
    from mapservice.local.certs import make_client_cert

    files = make_client_cert(tmp_path, "mapservice-gateway")
    s = Settings(
        mqtt_url="mqtts://broker:8883",
        mqtt_ca_file=files.ca_file,
        mqtt_cert_file=files.cert_file,
        mqtt_key_file=files.key_file,
        mqtt_username="mapservice-gateway",
        mqtt_password="pw",
    )
    client = service_client(s, "gw")
    context = client._ssl_context
    assert context is not None and context.cert_store_stats()["x509_ca"] == 1
    assert cert_chains == [(str(files.cert_file), str(files.key_file))]
    assert client._username == b"mapservice-gateway"
    assert service_client(Settings(), "gw")._ssl_context is None
    with pytest.raises(ValueError, match="mqtts://"):
        Settings(mqtt_ca_file=files.ca_file)
    with pytest.raises(ValueError, match="go together"):
        Settings(mqtt_url="mqtts://broker:8883", mqtt_cert_file=files.cert_file)


def test_robot_chunk_topic_must_end_with_a_robot_level() -> None:
    """MAPSERVICE_ROBOT_CHUNK_TOPIC ends with /+ (the robot id); anything else is refused."""
    assert Settings(robot_chunk_topic="site/chunks/+").robot_chunk_topic == "site/chunks/+"
    with pytest.raises(ValueError, match="/\\+"):
        Settings(robot_chunk_topic="site/chunks/#")


def test_map_transforms_as_json_text_in_the_environment_or_a_keyword(monkeypatch) -> None:
    text = '{"hall": [3, 2, 0.5]}'
    assert Settings(vda5050_map_transforms=text).vda5050_map_transforms == {"hall": (3, 2, 0.5)}
    monkeypatch.setenv("MAPSERVICE_VDA5050_MAP_TRANSFORMS", text)
    assert Settings().vda5050_map_transforms == {"hall": (3, 2, 0.5)}
    with pytest.raises(ValidationError):
        Settings(vda5050_map_transforms='{"hall": [3, 2]}')


def test_one_settings_class_holds_every_section_once_in_the_sections_order() -> None:
    """Settings is composed of one section per concern; pydantic orders the fields by the
    reversed method resolution order, so listing the sections in another order, or a field
    defined in two sections, would reorder or merge the configuration's fields."""
    from mapservice.settings.api import ApiSettings
    from mapservice.settings.clickhouse import ClickHouseSettings
    from mapservice.settings.foxglove import FoxgloveSettings
    from mapservice.settings.history import HistorySettings
    from mapservice.settings.kafka import KafkaSettings
    from mapservice.settings.live import LiveSettings
    from mapservice.settings.mqtt import MqttSettings
    from mapservice.settings.process import ProcessSettings

    sections = (
        ProcessSettings,
        KafkaSettings,
        ClickHouseSettings,
        MqttSettings,
        HistorySettings,
        LiveSettings,
        ApiSettings,
        FoxgloveSettings,
    )
    expected = [name for section in sections for name in section.model_fields]
    assert list(Settings.model_fields) == expected
    assert list(Settings.model_fields)[:2] == ["mode", "data_dir"]
