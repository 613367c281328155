"""One settings object per process, read from the environment (prefix ``MAPSERVICE_``).

`Settings` is one class composed of one section per concern (the modules beside this one);
what spans sections (validation across them, derived values) is here.
"""

from __future__ import annotations

from functools import cached_property

from pydantic import model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from mapservice.settings.api import ApiSettings
from mapservice.settings.clickhouse import ClickHouseSettings
from mapservice.settings.credentials import (
    DEFAULT_ADMIN_TOKEN,
    DEFAULT_CLICKHOUSE_PASSWORD,
    MIN_TOKEN_CHARS,
    robot_tokens,
    token_list,
)
from mapservice.settings.foxglove import FoxgloveSettings
from mapservice.settings.history import HistorySettings
from mapservice.settings.kafka import KafkaSettings
from mapservice.settings.live import LiveSettings
from mapservice.settings.mqtt import VDA5050_SUBTOPICS, MqttSettings
from mapservice.settings.process import ProcessSettings

__all__ = [
    "DEFAULT_ADMIN_TOKEN",
    "DEFAULT_CLICKHOUSE_PASSWORD",
    "MIN_TOKEN_CHARS",
    "VDA5050_SUBTOPICS",
    "Settings",
    "robot_tokens",
    "token_list",
]


# pydantic orders the fields by the reversed method resolution order: the sections are listed
# last first, so the fields (and `Settings.model_fields`) run process, Kafka, ClickHouse, MQTT,
# history, live, API, Foxglove.
class Settings(
    FoxgloveSettings,
    ApiSettings,
    LiveSettings,
    HistorySettings,
    MqttSettings,
    ClickHouseSettings,
    KafkaSettings,
    ProcessSettings,
    BaseSettings,
):
    """Everything a component needs to know; only addresses differ between modes."""

    model_config = SettingsConfigDict(env_prefix="MAPSERVICE_", extra="ignore")

    @model_validator(mode="after")
    def _check_tls_and_topics(self) -> Settings:
        for hop, cert, key in (
            ("MQTT", self.mqtt_cert_file, self.mqtt_key_file),
            ("KAFKA_SSL", self.kafka_ssl_cert_file, self.kafka_ssl_key_file),
            ("CLICKHOUSE", self.clickhouse_cert_file, self.clickhouse_key_file),
        ):
            if (cert is None) != (key is None):
                raise ValueError(
                    f"MAPSERVICE_{hop}_CERT_FILE and MAPSERVICE_{hop}_KEY_FILE go "
                    "together (a client certificate needs its key)"
                )
        if (self.mqtt_ca_file or self.mqtt_cert_file) and not self.mqtt_url.startswith(
            ("mqtts:", "ssl:")
        ):
            raise ValueError(
                "MAPSERVICE_MQTT_CA_FILE/CERT_FILE are for TLS: use an mqtts:// "
                f"MAPSERVICE_MQTT_URL (not {self.mqtt_url})"
            )
        if (
            self.clickhouse_ca_file or self.clickhouse_cert_file
        ) and not self.resolved_clickhouse_dsn.startswith("https:"):
            raise ValueError(
                "MAPSERVICE_CLICKHOUSE_CA_FILE/CERT_FILE are for TLS: use an "
                "https:// MAPSERVICE_CLICKHOUSE_DSN"
            )
        if (
            self.kafka_ssl_ca_file or self.kafka_ssl_cert_file
        ) and "SSL" not in self.kafka_security_protocol.upper():
            raise ValueError(
                "MAPSERVICE_KAFKA_SSL_* files are for TLS: set "
                "MAPSERVICE_KAFKA_SECURITY_PROTOCOL to SSL or SASL_SSL"
            )
        if self.robot_chunk_topic and not self.robot_chunk_topic.endswith("/+"):
            raise ValueError(
                "MAPSERVICE_ROBOT_CHUNK_TOPIC must end with /+ (its last level is "
                f"the robot id), not {self.robot_chunk_topic!r}"
            )
        return self

    @model_validator(mode="after")
    def _refuse_default_secrets(self) -> Settings:
        robot_tokens(self.api_robot_tokens)  # malformed pairs: refused in every mode
        if self.mode == "production":
            admin = self.admin_token.get_secret_value()
            if not admin or admin == DEFAULT_ADMIN_TOKEN:
                raise ValueError(
                    f"MAPSERVICE_ADMIN_TOKEN is {'empty' if not admin else 'the old local default'}; "
                    f"set a secret of at least {MIN_TOKEN_CHARS} characters (openssl rand -hex 32) "
                    "before running with MAPSERVICE_MODE=production"
                )
            for name in (
                "admin_token",
                "api_reader_tokens",
                "api_writer_tokens",
                "api_operator_tokens",
                "api_metrics_token",
                "api_robot_tokens",
            ):
                tokens = (
                    list(robot_tokens(self.api_robot_tokens))
                    if name == "api_robot_tokens"
                    else token_list(getattr(self, name))
                )
                short = [t for t in tokens if len(t) < MIN_TOKEN_CHARS]
                if short:
                    raise ValueError(
                        f"MAPSERVICE_{name.upper()} holds a token of {len(short[0])} characters; "
                        f"production mode needs at least {MIN_TOKEN_CHARS} (openssl rand -hex 32)"
                    )
            key = self.webhook_signing_key.get_secret_value()
            if key and len(key) < MIN_TOKEN_CHARS:
                raise ValueError(
                    f"MAPSERVICE_WEBHOOK_SIGNING_KEY has {len(key)} characters; production mode "
                    f"needs at least {MIN_TOKEN_CHARS} (openssl rand -hex 32)"
                )
            if self.resolved_clickhouse_dsn.startswith("http") and (
                self.clickhouse_password.get_secret_value() == DEFAULT_CLICKHOUSE_PASSWORD
            ):
                raise ValueError(
                    "MAPSERVICE_CLICKHOUSE_PASSWORD is empty; set it before running "
                    "with MAPSERVICE_MODE=production"
                )
        return self

    @property
    def metrics_access(self) -> str:
        return self.api_metrics_access or ("open" if self.mode == "local" else "token")

    @property
    def docs_access(self) -> str:
        return self.api_docs_access or ("open" if self.mode == "local" else "token")

    @property
    def resolved_clickhouse_dsn(self) -> str:
        if self.clickhouse_dsn:
            return self.clickhouse_dsn
        return f"chdb://{(self.data_dir / 'clickhouse').resolve()}"

    @property
    def migrates_on_start(self) -> bool:
        return self.migrate_on_start if self.migrate_on_start is not None else self.mode == "local"

    @cached_property
    def mqtt_subscriptions(self) -> list[str]:
        prefix = f"$share/{self.mqtt_share_group}/" if self.mqtt_share_group else ""
        # Only what vehicles publish: a master control's `order` and `instantActions` go
        # to the vehicles through the same subtree and are none of the gateway's business.
        vda = [
            f"{self.vda5050_interface}/+/+/+/{subtopic}"
            for subtopic in VDA5050_SUBTOPICS
            if self.vda5050_interface
        ]
        return [
            prefix + topic
            for topic in (
                self.create_chunk_topic,
                self.coordinate_topic,
                self.robot_chunk_topic,
                *vda,
                self.command_response_filter,
            )
            if topic
        ]

    @property
    def command_response_filter(self) -> str:
        """The MQTT filter of every robot's acks and outcomes: <root>+/command-events."""
        return (
            f"{self.robot_topic_root.rstrip('/')}/+/command-events" if self.robot_topic_root else ""
        )

    def command_topic(self, robot_id: str) -> str:
        """Where one robot reads its commands."""
        return f"{self.robot_topic_root.rstrip('/')}/{robot_id}/commands"
