"""The whole service on one machine: brokers plus each component in its own process.

Used by `mapservice up`, `mapservice bench` and the integration tests, so all three
run exactly what production runs, only with local addresses.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx
import structlog

from mapservice.local import embedded
from mapservice.adapters.clock import SystemClock
from mapservice.adapters.kafka_publisher import KafkaPublisher
from mapservice.core.events import MapMetaSet, encode, kafka_key, make_envelope
from mapservice.runtime.secrets import ApiSecrets, api_secrets, with_local_api_secrets
from mapservice.settings import Settings
from mapservice.adapters.kafka_topics import ensure_topics

log = structlog.get_logger(__name__)


@dataclass
class Stack:
    data_dir: Path
    mqtt: str = "amqtt"  # "amqtt", "mosquitto" or an mqtt:// URL of a running broker
    api_port: int = 0
    mqtt_port: int = 0
    mqtt_ws_port: int = 0  # the embedded broker's MQTT-over-WebSocket listener (browsers)
    kafka_port: int = 0
    health_port: int = 0
    extra_env: dict[str, str] = field(default_factory=dict)
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    commands: dict[str, tuple[str, ...]] = field(default_factory=dict)  # how each was spawned
    meta: MapMetaSet | None = None  # the last published map meta (re-published after a restart)

    def __post_init__(self) -> None:
        self.data_dir = Path(self.data_dir).resolve()
        self.log_dir = self.data_dir / "logs"
        self.api_port = self.api_port or embedded.free_port()
        self.kafka_port = self.kafka_port or embedded.free_port()
        self.health_port = self.health_port or embedded.free_port()
        if self.mqtt in ("amqtt", "mosquitto"):
            self.mqtt_port = self.mqtt_port or embedded.free_port()
            self.mqtt_url = f"mqtt://127.0.0.1:{self.mqtt_port}"
            self.mqtt_ws_port = self.mqtt_ws_port or embedded.free_port()
            self.mqtt_ws_url = f"ws://127.0.0.1:{self.mqtt_ws_port}/mqtt"
        else:
            self.mqtt_url = self.mqtt
            # A broker of its own: only the operator knows where browsers reach it.
            self.mqtt_ws_url = self.extra_env.get(
                "MAPSERVICE_MQTT_WS_URL", os.environ.get("MAPSERVICE_MQTT_WS_URL", ""))

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    def env(self) -> dict[str, str]:
        return {
            **os.environ,
            "MAPSERVICE_DATA_DIR": str(self.data_dir),
            "MAPSERVICE_KAFKA_BOOTSTRAP": f"127.0.0.1:{self.kafka_port}",
            "MAPSERVICE_MQTT_URL": self.mqtt_url,
            "MAPSERVICE_MQTT_WS_URL": self.mqtt_ws_url,
            "MAPSERVICE_API_HOST": "127.0.0.1",
            "MAPSERVICE_API_PORT": str(self.api_port),
            # Advertisements' chunkUrl must name this API, whatever port it got.
            "MAPSERVICE_PUBLIC_BASE_URL": os.environ.get("MAPSERVICE_PUBLIC_BASE_URL", self.api_url),
            "PYTHONUNBUFFERED": "1",
            **self.extra_env,
        }

    def settings(self) -> Settings:
        env = self.env()
        return Settings(data_dir=self.data_dir, kafka_bootstrap=env["MAPSERVICE_KAFKA_BOOTSTRAP"],
                        mqtt_url=self.mqtt_url, api_port=self.api_port,
                        **{"mqtt_ws_url": self.mqtt_ws_url,
                           **{k[len("MAPSERVICE_"):].lower(): v for k, v in self.extra_env.items()
                              if k.startswith("MAPSERVICE_")}})

    def api_secrets(self) -> ApiSecrets:
        """The API's tokens: as set in extra_env or the environment, else the ones local
        mode generates into the data dir (the same files the server reads)."""
        return api_secrets(with_local_api_secrets(self.settings()))

    def _log(self, name: str):
        self.log_dir.mkdir(parents=True, exist_ok=True)
        return open(self.log_dir / f"{name}.log", "ab")

    def start_brokers(self) -> None:
        self.start_kafka()
        if self.mqtt in ("amqtt", "mosquitto"):
            self.start_mqtt()

    def spawn(self, name: str, *args: str) -> subprocess.Popen:
        """Runs `mapservice <args>` as component `name` (log in log_dir/<name>.log)."""
        self.commands[name] = args
        proc = subprocess.Popen([sys.executable, "-m", "mapservice.cli", *args], env=self.env(),
                                stdout=self._log(name), stderr=subprocess.STDOUT,
                                start_new_session=True)
        self.procs[name] = proc
        return proc

    def start_gateway(self) -> subprocess.Popen:
        embedded.ensure_port_free(self.health_port, "the gateway's health endpoint")
        proc = self.spawn("gateway", "gateway", "--health-port", str(self.health_port))
        embedded.wait_for_port(self.health_port, proc=proc, what="gateway")
        self.wait_healthy(f"http://127.0.0.1:{self.health_port}/readyz", "gateway", proc)
        return proc

    def start_server(self) -> subprocess.Popen:
        embedded.ensure_port_free(self.api_port, "the API")
        proc = self.spawn("server", "serve")
        embedded.wait_for_port(self.api_port, timeout_s=120, proc=proc, what="server")
        self.wait_healthy(f"{self.api_url}/readyz", "server", proc)
        return proc

    def start_processors(self, health_port: int, name: str = "processors") -> subprocess.Popen:
        """`mapservice processors` alone (the split deployment: needs a ClickHouse server,
        MAPSERVICE_CLICKHOUSE_DSN in extra_env); healthy once its consumer group took it
        in. Another `name` runs another replica (its own log)."""
        embedded.ensure_port_free(health_port, "the processors' health endpoint")
        proc = self.spawn(name, "processors", "--health-port", str(health_port))
        embedded.wait_for_port(health_port, timeout_s=120, proc=proc, what=name)
        self.wait_healthy(f"http://127.0.0.1:{health_port}/readyz", name, proc)
        return proc

    def start_api(self, port: int | None = None, name: str = "api",
                  env: dict[str, str] | None = None) -> subprocess.Popen:
        """`mapservice api` alone on `port` (default: the stack's API port), ready when
        /readyz says so; another port and name run another replica (`env` overrides)."""
        port = port or self.api_port
        embedded.ensure_port_free(port, f"the API ({name})")
        proc = subprocess.Popen([sys.executable, "-m", "mapservice.cli", "api"],
                                env={**self.env(), "MAPSERVICE_API_PORT": str(port), **(env or {})},
                                stdout=self._log(name), stderr=subprocess.STDOUT,
                                start_new_session=True)
        self.procs[name] = proc
        embedded.wait_for_port(port, timeout_s=120, proc=proc, what=name)
        self.wait_healthy(f"http://127.0.0.1:{port}/readyz", name, proc)
        return proc

    def wait_healthy(self, url: str, what: str, proc: subprocess.Popen,
                     timeout_s: float = 60) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if proc.poll() is not None:
                raise RuntimeError(f"{what} exited ({proc.returncode}); see {self.log_dir}/{what}.log")
            try:
                if httpx.get(url, timeout=2).status_code == 200:
                    return
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        raise RuntimeError(f"{what} not healthy at {url} after {timeout_s:.0f} s")

    def start_kafka(self) -> subprocess.Popen:
        """tansu keeps topics in memory: a new one gets the topics and the map meta again."""
        embedded.stop(self.procs.pop("kafka", None))
        self.procs["kafka"] = embedded.start_tansu(self.kafka_port, self._log("tansu"))
        ensure_topics(self.settings())
        if self.meta is not None:
            self.publish_meta(self.meta)
        return self.procs["kafka"]

    def start_mqtt(self) -> subprocess.Popen:
        embedded.stop(self.procs.pop("mqtt", None))
        if self.mqtt == "amqtt":
            self.procs["mqtt"] = embedded.start_amqtt(self.mqtt_port, self._log("amqtt"),
                                                      ws_port=self.mqtt_ws_port)
        elif self.mqtt == "mosquitto":
            self.procs["mqtt"] = embedded.start_mosquitto(self.mqtt_port, self.data_dir,
                                                          self._log("mosquitto"),
                                                          ws_port=self.mqtt_ws_port)
        else:
            raise RuntimeError(f"the MQTT broker at {self.mqtt} is not this stack's to start")
        return self.procs["mqtt"]

    def restart(self, name: str) -> subprocess.Popen:
        """Starts component `name` again after it exited (the supervisor of `up` calls this)."""
        if name == "kafka":
            return self.start_kafka()
        if name == "mqtt":
            return self.start_mqtt()
        embedded.stop(self.procs.pop(name, None))
        if name == "server":
            return self.start_server()
        if name == "gateway":
            return self.start_gateway()
        if name not in self.commands:
            raise KeyError(f"no component {name!r} was started")
        return self.spawn(name, *self.commands[name])

    def is_alive(self, name: str) -> bool:
        proc = self.procs.get(name)
        return proc is not None and proc.poll() is None

    def publish_meta(self, meta: MapMetaSet) -> None:
        self.meta = meta
        settings = self.settings()
        publisher = KafkaPublisher(settings, client_id="mapservice-up")
        now = SystemClock().now_ms()
        env = make_envelope("mapservice", now, now, meta)
        errors: list = []
        publisher.publish(settings.topic_meta_events, kafka_key(env), encode(env), errors.append)
        if publisher.flush(30) or any(errors):
            raise RuntimeError(f"could not publish the map meta to Kafka: {errors}")

    def start(self) -> None:
        self.start_brokers()
        self.start_server()
        self.start_gateway()

    def stop(self) -> None:
        for name in ("sim", "gateway", "server", "api", "processors", "mqtt", "kafka"):
            embedded.stop(self.procs.pop(name, None))
        for proc in self.procs.values():
            embedded.stop(proc)
        self.procs.clear()

    def __enter__(self) -> "Stack":
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
