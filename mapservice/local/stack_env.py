"""What the local stack tells each component: its environment (addresses, TLS, credentials,
the gateway replicas' identities, the split deployment's ClickHouse server), the settings it
reads from it, and the service users' generated passwords. A part of `Stack`
(local/stack.py), which mixes it in."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from mapservice.adapters.mqtt_auth import GATEWAY_USER, PROCESSORS_USER
from mapservice.local.embedded import TANSU_FETCH_WAIT_MS
from mapservice.local.kafka_auth import KAFKA_NODE_USER, KAFKA_SERVICE_USER, component_env
from mapservice.runtime.secrets import (
    ApiSecrets,
    api_secrets,
    local_secret,
    with_local_api_secrets,
)
from mapservice.settings import Settings


class StackEnv:
    """The components' environment's part of `Stack`."""

    if TYPE_CHECKING:  # what it uses of the Stack it is mixed into
        data_dir: Path
        tls_dir: Path
        kafka: str
        kafka_port: int
        mqtt_url: str
        mqtts_url: str
        mqtt_ws_url: str
        mqtt_auth: bool
        mqtt_tls: bool
        kafka_auth: bool
        api_port: int
        foxglove_port: int
        apart: bool
        clickhouse_port: int
        processors_health_port: int
        gateways: int
        extra_env: dict[str, str]

    @property
    def embeds_kafka(self) -> bool:
        return self.kafka in ("apache", "tansu")

    @property
    def kafka_bootstrap(self) -> str:
        return f"127.0.0.1:{self.kafka_port}" if self.embeds_kafka else self.kafka

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    @property
    def foxglove_url(self) -> str:
        return f"ws://127.0.0.1:{self.foxglove_port}"

    @property
    def ca_file(self) -> Path:
        """The local CA's certificate (clients of the TLS listener trust it)."""
        return self.tls_dir / "ca.crt"

    def service_password(self, username: str, system: str = "mqtt") -> str:
        """The generated password of a service user (kept in DATA_DIR/secrets/): an MQTT
        one, a Kafka one (system="kafka"), or "clickhouse" (the service's user on
        `mapservice clickhouse-server`)."""
        name = (
            "clickhouse-password" if username == "clickhouse" else f"{system}-{username}-password"
        )
        # As long as new_password's (24 random bytes), and created once even when components
        # start side by side (two threads asking at once end with the same password).
        return local_secret(self.data_dir, name, nbytes=24)

    def _mqtt_env(self, component: str | None) -> dict[str, str]:
        """A component's MQTT address, TLS and credential: the gateway its service user, the
        processors (advertisements) theirs; anything else (robots, tools) none."""
        env: dict[str, str] = {}
        if self.mqtt_tls:
            env.update(
                {
                    "MAPSERVICE_MQTT_URL": self.mqtts_url,
                    "MAPSERVICE_MQTT_CA_FILE": str(self.ca_file),
                }
            )
        if self.mqtt_auth and component is not None:
            user = (
                GATEWAY_USER
                if component.startswith("gateway")
                else PROCESSORS_USER
                if component.startswith(("server", "processors"))
                else None
            )
            if user is not None:
                env.update(
                    {
                        "MAPSERVICE_MQTT_USERNAME": user,
                        "MAPSERVICE_MQTT_PASSWORD": self.service_password(user),
                    }
                )
        return env

    def kafka_users(self) -> tuple[tuple[str, str], ...]:
        """The embedded Kafka's users with kafka_auth (the node's own first), else none."""
        if not self.kafka_auth:
            return ()
        return tuple(
            (user, self.service_password(user, "kafka"))
            for user in (KAFKA_NODE_USER, KAFKA_SERVICE_USER)
        )

    def _kafka_env(self) -> dict[str, str]:
        """Every component is the service's: with kafka_auth each gets its Kafka user. On
        the embedded tansu, fetches wait 50 ms for new records unless told otherwise: tansu
        answers a fetch only when its wait runs out, so the default wait (for Apache Kafka,
        which answers on arrival) would be every record's latency."""
        env = {}
        if self.kafka == "tansu" and "MAPSERVICE_KAFKA_FETCH_WAIT_MS" not in os.environ:
            env["MAPSERVICE_KAFKA_FETCH_WAIT_MS"] = str(TANSU_FETCH_WAIT_MS)
        if self.kafka == "apache" and "MAPSERVICE_KAFKA_PARTITIONS" not in os.environ:
            # One processors replica reads the embedded broker, so more partitions share
            # nothing out; they cost produce requests (librdkafka sends one per partition
            # and linger) that the broker's CPU follows: one partition per topic took it to
            # 0.42x at 1,000 robots (BENCHMARKS.md). tansu keeps the default: two producers
            # on one of its partitions can hide a batch from a reader (docs/embedded.md).
            env["MAPSERVICE_KAFKA_PARTITIONS"] = "1"
        if self.kafka_auth:
            env |= component_env(self.service_password(KAFKA_SERVICE_USER, "kafka"))
        return env

    @property
    def clickhouse_url(self) -> str:
        """The ClickHouse HTTP interface of `mapservice clickhouse-server` (apart only)."""
        return f"http://127.0.0.1:{self.clickhouse_port}"

    def _apart_env(self) -> dict[str, str]:
        """Apart: every component reaches the history through the ClickHouse server, as the
        service's ClickHouse user with a generated password (DATA_DIR/secrets/: the port is
        open to every local user); the API asks the processors whether it is stored."""
        if not self.apart:
            return {}
        return {
            "MAPSERVICE_CLICKHOUSE_DSN": self.clickhouse_url,
            "MAPSERVICE_CLICKHOUSE_PASSWORD": self.service_password("clickhouse"),
            "MAPSERVICE_PROCESSORS_STATUS_URL": f"http://127.0.0.1:{self.processors_health_port}",
        }

    def env(self, component: str | None = None) -> dict[str, str]:
        return {
            **os.environ,
            **self._apart_env(),
            "MAPSERVICE_DATA_DIR": str(self.data_dir),
            "MAPSERVICE_KAFKA_BOOTSTRAP": self.kafka_bootstrap,
            "MAPSERVICE_MQTT_URL": self.mqtt_url,
            "MAPSERVICE_MQTT_WS_URL": self.mqtt_ws_url,
            "MAPSERVICE_API_HOST": "127.0.0.1",
            "MAPSERVICE_API_PORT": str(self.api_port),
            "MAPSERVICE_FOXGLOVE_HOST": "127.0.0.1",
            "MAPSERVICE_FOXGLOVE_PORT": str(self.foxglove_port),
            # Advertisements' chunkUrl must name this API, whatever port it got.
            "MAPSERVICE_PUBLIC_BASE_URL": os.environ.get(
                "MAPSERVICE_PUBLIC_BASE_URL", self.api_url
            ),
            "PYTHONUNBUFFERED": "1",
            **self._kafka_env(),
            **self._mqtt_env(component),
            **self.extra_env,
            **self._gateway_replica_env(component),
        }

    def _gateway_replica_env(self, component: str | None) -> dict[str, str]:
        """With several gateways: each replica's client id, and the shared subscription's
        group (MAPSERVICE_MQTT_SHARE_GROUP if set, else `mapservice-gateways`)."""
        if self.gateways == 1 or component is None or not component.startswith("gateway"):
            return {}
        replica = 1 if component == "gateway" else int(component.rsplit("-", 1)[1])
        settings_env = {**os.environ, **self.extra_env}
        base = settings_env.get("MAPSERVICE_MQTT_CLIENT_ID", "mapservice-gateway")
        return {
            "MAPSERVICE_MQTT_CLIENT_ID": f"{base}-{replica}",
            "MAPSERVICE_MQTT_SHARE_GROUP": settings_env.get("MAPSERVICE_MQTT_SHARE_GROUP")
            or "mapservice-gateways",
        }

    def settings(self) -> Settings:
        env = self.env()
        return Settings(
            data_dir=self.data_dir,
            kafka_bootstrap=env["MAPSERVICE_KAFKA_BOOTSTRAP"],
            mqtt_url=self.mqtt_url,
            api_port=self.api_port,
            **{
                "mqtt_ws_url": self.mqtt_ws_url,
                **{
                    k[len("MAPSERVICE_") :].lower(): v
                    for k, v in {**self._kafka_env(), **self.extra_env}.items()
                    if k.startswith("MAPSERVICE_")
                },
            },
        )

    def api_secrets(self) -> ApiSecrets:
        """The API's tokens: as set in extra_env or the environment, else the ones local
        mode generates into the data dir (the same files the server reads)."""
        return api_secrets(with_local_api_secrets(self.settings()))
