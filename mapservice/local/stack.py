"""The whole service on one machine: brokers plus each component in its own process.

Used by `mapservice up`, `mapservice bench` and the integration tests, so all three
run exactly what production runs, only with local addresses.
"""

from __future__ import annotations

import os
import subprocess
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import structlog

from mapservice.adapters.clock import SystemClock
from mapservice.adapters.kafka_publisher import KafkaPublisher
from mapservice.adapters.kafka_topics import ensure_topics
from mapservice.adapters.mqtt_auth import BrokerFiles
from mapservice.core.events import MapMetaSet, make_envelope
from mapservice.core.intake import Intake
from mapservice.local import embedded, kafka_broker, lifetime
from mapservice.local.kafka_auth import TANSU_NO_AUTH
from mapservice.local.side_by_side import SideBySide
from mapservice.local.stack_env import StackEnv
from mapservice.local.stack_mqtt import StackMqtt
from mapservice.robot.map_upload import admitted_meta, publish_events

log = structlog.get_logger(__name__)


@dataclass
class Stack(StackMqtt, StackEnv):
    data_dir: Path
    mqtt: str = "amqtt"  # "amqtt", "mosquitto" or an mqtt:// URL of a running broker
    api_port: int = 0
    foxglove_port: int = 0  # the API process's Foxglove WebSocket server
    mqtt_port: int = 0
    mqtt_ws_port: int = 0  # the embedded broker's MQTT-over-WebSocket listener (browsers)
    kafka_port: int = 0
    # "apache" (a KRaft node, log in DATA_DIR/kafka/) or "tansu" (in memory); empty:
    # MAPSERVICE_EMBEDDED_KAFKA (auto: apache where Java is installed); else the bootstrap
    # servers of a running Kafka (not this stack's to start).
    kafka: str = ""
    health_port: int = 0
    extra_env: dict[str, str] = field(default_factory=dict)
    # The Python that runs the components (another checkout's, to compare two commits:
    # bench/compare.py); empty: this one.
    python: str = ""
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    commands: dict[str, tuple[str, ...]] = field(default_factory=dict)  # how each was spawned
    meta: MapMetaSet | None = None  # the last published map meta (re-published after a restart)
    # Robot identities: Mosquitto with a password file and an ACL (DATA_DIR/mqtt/), no
    # anonymous client; the gateway and the processors connect with service users whose
    # generated passwords are kept in DATA_DIR/secrets/.
    mqtt_auth: bool = False
    # A TLS listener too (a local CA in DATA_DIR/tls/), which the components connect through.
    mqtt_tls: bool = False
    mqtt_tls_port: int = 0
    # The embedded Apache Kafka serves only the service's components, with a generated
    # password (SASL/PLAIN, DATA_DIR/secrets/; local/kafka_auth.py).
    kafka_auth: bool = False
    # Gateway replicas: more than one share the robots' topics through an MQTT shared
    # subscription (as the gateway Deployment's replicas do), each with its own client id
    # (so its own persistent session) and health port.
    gateways: int = 1
    gateway_health_ports: list[int] = field(default_factory=list)
    # `mapservice up`: its processes create files only its user reads; `up` and its
    # components are recorded in the data dir's pid file, a guard stops them in order when
    # `up` dies (even by kill -9), and the next `up` finds what a dead one left running
    # (mapservice.local.lifetime).
    tied_to_parent: bool = False
    guard: subprocess.Popen | None = None
    # `mapservice up`: the API apart from the processors (start_apart), as in the split
    # deployment: `mapservice clickhouse-server` owns the chDB directory (chDB allows one
    # process per directory) and serves ClickHouse HTTP to `mapservice processors` and
    # `mapservice api`, so no API work runs in the history consumer's process.
    apart: bool = False
    clickhouse_port: int = 0
    processors_health_port: int = 0
    # The ports above this stack chose itself (given as 0), until a component was told one.
    _chosen_ports: set[str] = field(default_factory=set, init=False, repr=False)
    # Components started side by side (start_apart): their threads, and the lock under which
    # a process is spawned and recorded, or refused once `stop` began.
    _side_by_side: SideBySide = field(default_factory=SideBySide, init=False, repr=False)
    _lock: threading.RLock = field(default_factory=threading.RLock, init=False, repr=False)
    _stopping: bool = field(default=False, init=False, repr=False)

    def __post_init__(self) -> None:
        self.data_dir = Path(self.data_dir).resolve()
        self.log_dir = self.data_dir / "logs"
        embedded.reserve_ports(  # the given ports are their components' alone
            *(self.api_port, self.foxglove_port, self.kafka_port, self.health_port, self.mqtt_port),
            *(self.mqtt_ws_port, self.mqtt_tls_port, self.clickhouse_port),
            self.processors_health_port,
        )
        self.api_port = self.api_port or embedded.free_port()
        self.foxglove_port = self.foxglove_port or embedded.free_port()
        self.kafka_port = self.kafka_port or embedded.free_port()
        if self.gateways < 1:
            raise ValueError(f"gateways must be at least 1, not {self.gateways}")
        # Replica 1's port is `health_port` (given or chosen); the other replicas' are chosen.
        self._chosen_ports = {
            f"gateway-{replica}"
            for replica in range(1, self.gateways + 1)
            if replica > 1 or not self.health_port
        }
        self.health_port = self.health_port or embedded.free_port()
        self.gateway_health_ports = [self.health_port] + [
            embedded.free_port() for _ in range(self.gateways - 1)
        ]
        if self.mqtt in ("amqtt", "mosquitto"):
            self.mqtt_port = self.mqtt_port or embedded.free_port()
            self.mqtt_url = f"mqtt://127.0.0.1:{self.mqtt_port}"
            self.mqtt_ws_port = self.mqtt_ws_port or embedded.free_port()
            self.mqtt_ws_url = f"ws://127.0.0.1:{self.mqtt_ws_port}/mqtt"
        else:
            self.mqtt_url = self.mqtt
            # A broker of its own: only the operator knows where browsers reach it.
            self.mqtt_ws_url = self.extra_env.get(
                "MAPSERVICE_MQTT_WS_URL", os.environ.get("MAPSERVICE_MQTT_WS_URL", "")
            )
        if (self.mqtt_auth or self.mqtt_tls) and self.mqtt != "mosquitto":
            # amqtt checks topics per user, but deletes or takes over a client id's session
            # before it checks the credential (amqtt 0.12 broker._client_connected): any
            # anonymous client could wipe the gateway's session. Mosquitto does neither.
            raise ValueError(
                "robot identities (mqtt_auth) and MQTT TLS need the embedded "
                "Mosquitto (mqtt='mosquitto'), not " + repr(self.mqtt)
            )
        self.mqtts_url = ""
        if self.mqtt_tls:
            self.mqtt_tls_port = self.mqtt_tls_port or embedded.free_port()
            self.mqtts_url = f"mqtts://127.0.0.1:{self.mqtt_tls_port}"
        self.tls_dir = self.data_dir / "tls"
        self.broker_files = BrokerFiles.in_data_dir(self.data_dir)
        self.kafka = self.kafka or kafka_broker.embedded_choice(self.settings().embedded_kafka)
        if self.kafka_auth and self.kafka != "apache":
            raise ValueError(
                "Kafka credentials (kafka_auth) are the embedded Apache Kafka's: "
                + (TANSU_NO_AUTH if self.kafka == "tansu" else f"{self.kafka} has its own")
            )
        self.pid_file = lifetime.PidFile.in_data_dir(self.data_dir)
        if self.apart:
            self._chosen_ports |= {
                name
                for name, port in (
                    ("clickhouse_port", self.clickhouse_port),
                    ("processors_health_port", self.processors_health_port),
                )
                if not port
            }
            self.clickhouse_port = self.clickhouse_port or embedded.free_port()
            self.processors_health_port = self.processors_health_port or embedded.free_port()
        # The broker files as the running Mosquitto read them, and a change seen once
        # (applied when it holds still: `robot add` replaces the two files one by one).
        self._broker_files_read: tuple = ()
        self._broker_files_seen: tuple = ()

    @property
    def _preexec(self):
        # Not the parent-death signal: all at once, tansu's memory went before the
        # processors had read the last messages from it. The guard stops them in order.
        return lifetime.private_files if self.tied_to_parent else None

    def start_guard(self) -> None:
        """The guard that stops the components in order when this process dies, and what
        this process starts from now on marked as its own (a component it dies while
        starting is in no record yet: the guard finds it by the mark)."""
        if threading.current_thread() is not threading.main_thread():
            # Linux sends the parent-death signal when the *thread* that forked the guard
            # ends, not the process: a guard started on a start thread would stop
            # everything as soon as that thread is done.
            raise RuntimeError("the guard must be started from the main thread")
        mark = lifetime.mark_children()
        self.guard = subprocess.Popen(
            embedded.module_command(
                "mapservice.local.lifetime",
                lifetime.GUARD,
                str(self.pid_file.path),
                str(os.getpid()),
                mark,
            ),
            stdout=self._log("guard"),
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=lifetime.guard_preexec,
        )
        self._record()

    def _record(self) -> None:
        """The pid file names `up` and every component running now."""
        if self.tied_to_parent:
            with self._lock:
                running = {
                    name: proc.pid for name, proc in self.procs.items() if proc.poll() is None
                }
                if self.guard is not None and self.guard.poll() is None:
                    running[lifetime.GUARD] = self.guard.pid
                self.pid_file.write(running)

    def _log(self, name: str):
        self.log_dir.mkdir(parents=True, exist_ok=True)
        return open(self.log_dir / f"{name}.log", "ab")

    def start_brokers(self) -> None:
        if self.embeds_kafka:
            self.start_kafka()
        else:
            ensure_topics(self.settings())
        if self.mqtt in ("amqtt", "mosquitto"):
            self.start_mqtt()

    def spawn(self, name: str, *args: str, env: dict[str, str] | None = None) -> subprocess.Popen:
        """Runs `mapservice <args>` as component `name` (log in log_dir/<name>.log), with the
        stack's environment for it and `env` over it."""
        self.commands[name] = args
        # Under the lock, and refused once `stop` began: a start-up step still running side by
        # side must not leave a process behind the stack.
        with self._lock:
            if self._stopping:
                raise RuntimeError(f"not starting {name}: the stack is being stopped")
            proc = subprocess.Popen(
                embedded.module_command("mapservice.cli", *args, python=self.python),
                env={**self.env(name), **(env or {})},
                stdout=self._log(name),
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=self._preexec,
            )
            self.procs[name] = proc
            self._record()
        return proc

    def start_gateway(self, replica: int = 1) -> subprocess.Popen:
        """Starts gateway replica `replica` (1: the component named "gateway", then
        "gateway-2", ...) and waits until it is ready."""
        name = "gateway" if replica == 1 else f"gateway-{replica}"
        self._rechoose_if_taken(f"gateway-{replica}", f"the {name}'s health endpoint")
        port = self.gateway_health_ports[replica - 1]
        embedded.ensure_port_free(port, f"the {name}'s health endpoint")
        proc = self.spawn(name, "gateway", "--health-port", str(port))
        embedded.wait_for_port(port, proc=proc, what=name)
        self.wait_healthy(f"http://127.0.0.1:{port}/readyz", name, proc)
        return proc

    def start_gateways(self) -> None:
        """Starts every gateway replica (`gateways` of them)."""
        for replica in range(1, self.gateways + 1):
            self.start_gateway(replica)

    def start_server(self) -> subprocess.Popen:
        embedded.ensure_port_free(self.api_port, "the API")
        embedded.ensure_port_free(self.foxglove_port, "the Foxglove server")
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

    def start_api(
        self, port: int | None = None, name: str = "api", env: dict[str, str] | None = None
    ) -> subprocess.Popen:
        """`mapservice api` alone on `port` (default: the stack's API port), ready when
        /readyz says so; another port and name run another replica (`env` overrides)."""
        own = {"MAPSERVICE_API_PORT": str(port or self.api_port)}
        if port and port != self.api_port:
            own["MAPSERVICE_FOXGLOVE_PORT"] = "0"  # another replica: a Foxglove port of its own
        port = port or self.api_port
        embedded.ensure_port_free(port, f"the API ({name})")
        if "MAPSERVICE_FOXGLOVE_PORT" not in own:
            embedded.ensure_port_free(self.foxglove_port, "the Foxglove server")
        proc = self.spawn(name, "api", env={**own, **(env or {})})
        embedded.wait_for_port(port, timeout_s=120, proc=proc, what=name)
        self.wait_healthy(f"http://127.0.0.1:{port}/readyz", name, proc)
        return proc

    def start_clickhouse_server(self) -> subprocess.Popen:
        """`mapservice clickhouse-server` (apart): the one process that opens the data dir's
        chDB, serving ClickHouse HTTP read-write to the service's user."""
        embedded.ensure_port_free(self.clickhouse_port, "the ClickHouse server")
        proc = self.spawn(
            "clickhouse", "clickhouse-server", "--port", str(self.clickhouse_port), "--read-write"
        )
        embedded.wait_for_port(self.clickhouse_port, timeout_s=120, proc=proc, what="clickhouse")
        self.wait_healthy(f"{self.clickhouse_url}/ping", "clickhouse", proc)
        return proc

    def _rechoose_if_taken(self, key: str, what: str) -> None:
        """A port this stack chose itself, and told no component yet, is swapped for a free
        one if something took it meanwhile. It was free when chosen, seconds before: another
        process may have chosen it since (test suites side by side pick free ports the same
        way), or, where the kernel's ephemeral range is not known, a client connection may
        hold it (a restarted `up` once found its ClickHouse server's port taken that way). A
        port that was given is kept, and refused by the start if taken. `key`: the
        attribute's name, or "gateway-N" for replica N's health port."""
        if key not in self._chosen_ports:
            return
        self._chosen_ports.discard(key)  # from now on a component is told it
        port = self._port_named(key)
        if not embedded.port_is_free(port):
            self._set_port(key, embedded.free_port())
            log.info(
                "a port chosen for the stack was taken meanwhile: another chosen",
                component=what,
                taken=port,
                port=self._port_named(key),
            )

    def _port_named(self, key: str) -> int:
        if key.startswith("gateway-"):
            return self.gateway_health_ports[int(key.removeprefix("gateway-")) - 1]
        return int(getattr(self, key))

    def _set_port(self, key: str, port: int) -> None:
        if key.startswith("gateway-"):
            replica = int(key.removeprefix("gateway-"))
            self.gateway_health_ports[replica - 1] = port
            if replica == 1:
                self.health_port = port
        else:
            setattr(self, key, port)

    def start_apart(self, gateway: bool = False) -> None:
        """What `serve` runs, in three processes (apart=True): the ClickHouse server (unless
        it runs), then side by side the processors (creating the schema) and the API on the
        stack's API port (which waits for the schema), and with `gateway` the gateway."""
        if not self.apart:
            raise RuntimeError("this stack runs processors and API in one process (apart=False)")
        if not self.is_alive("clickhouse"):
            self._rechoose_if_taken("clickhouse_port", "the ClickHouse server")
            self.start_clickhouse_server()
        self._rechoose_if_taken("processors_health_port", "the processors' health endpoint")
        self.side_by_side(
            lambda: self.start_processors(self.processors_health_port),
            self.start_api,
            *([self.start_gateway] if gateway else []),
        )

    def start_brokers_and_clickhouse(self, meta: MapMetaSet) -> None:
        """The brokers, the map meta published once Kafka answers, and side by side the
        ClickHouse server (apart); then `start_apart` starts the rest."""
        self._rechoose_if_taken("clickhouse_port", "the ClickHouse server")

        def brokers() -> None:
            self.start_brokers()
            self.publish_meta(meta)

        # The brokers in this thread: Kafka's process is recorded only once it answers, so
        # only this thread's Ctrl-C can stop it while it starts.
        self.side_by_side(brokers, self.start_clickhouse_server)

    def side_by_side(self, here: Callable[[], object], *elsewhere: Callable[[], object]) -> None:
        """Start-up steps at once (SideBySide.run); `stop` waits for those still running."""
        self._side_by_side.run(here, *elsewhere)

    def wait_healthy(
        self, url: str, what: str, proc: subprocess.Popen, timeout_s: float = 60
    ) -> None:
        embedded.wait_healthy(url, what, proc, self.log_dir / f"{what}.log", timeout_s)

    def start_kafka(self) -> subprocess.Popen:
        """Apache Kafka resumes on its log in DATA_DIR/kafka/; tansu keeps topics in memory,
        so a new one gets the topics and the map meta again."""
        if not self.embeds_kafka:
            raise RuntimeError(f"the Kafka at {self.kafka} is not this stack's to start")
        embedded.stop(self.procs.pop("kafka", None))
        settings = self.settings()
        self.procs["kafka"] = kafka_broker.start_embedded(
            self.kafka,
            self.data_dir,
            self.kafka_port,
            settings,
            self._log("kafka" if self.kafka == "apache" else "tansu"),
            preexec_fn=self._preexec,
            sasl_users=self.kafka_users(),
        )
        self._record()
        ensure_topics(settings)
        if self.meta is not None and self.kafka == "tansu":
            self.publish_meta(self.meta)
        return self.procs["kafka"]

    def restart(self, name: str) -> subprocess.Popen:
        """Starts component `name` again after it exited (the supervisor of `up` calls this)."""
        if name == "kafka":
            return self.start_kafka()
        if name == "mqtt":
            return self.start_mqtt()
        embedded.stop(self.procs.pop(name, None))
        if name == "server":
            return self.start_server()
        if name == "clickhouse":
            return self.start_clickhouse_server()
        if name == "processors" and self.apart:
            return self.start_processors(self.processors_health_port)
        if name == "api":
            return self.start_api()
        if name == "gateway":
            return self.start_gateway()
        if name not in self.commands:
            raise KeyError(f"no component {name!r} was started")
        return self.spawn(name, *self.commands[name])

    def is_alive(self, name: str) -> bool:
        proc = self.procs.get(name)
        return proc is not None and proc.poll() is None

    def publish_meta(self, meta: MapMetaSet) -> None:
        """Publishes the map's meta as robot `mapservice`, through the intake every 2019
        write passes (UploadRefused when it refuses the meta)."""
        settings = self.settings()
        admitted = admitted_meta(
            Intake.from_settings(settings), msgspec.json.encode(meta.to_2019())
        )
        self.meta = meta
        publisher = KafkaPublisher(settings, client_id="mapservice-up")
        now = SystemClock().now_ms()
        try:
            envelope = make_envelope("mapservice", now, now, admitted)
            publish_events(publisher, settings, [envelope], "the map meta")
        finally:
            publisher.close()  # else its producer dials the broker for as long as the stack runs

    def start(self, *steps: Callable[[], object]) -> None:
        """Runs `steps` in order (default: brokers, `serve`, the gateways); stops every
        part already started when one fails."""
        try:
            for step in steps or (self.start_brokers, self.start_server, self.start_gateways):
                step()
        except BaseException:
            self.stop()
            raise

    @contextmanager
    def running(self, *steps: Callable[[], object]) -> Iterator[Stack]:
        """The stack started as `start(*steps)`, stopped after use."""
        self.start(*steps)
        try:
            yield self
        finally:
            self.stop()

    def stop(self) -> None:
        with self._lock:
            self._stopping = True
        try:
            self._stop()
            # A start-up step still running side by side ends now that its process is gone.
            self._side_by_side.join()
        finally:
            self._stopping = False

    def _stop(self) -> None:
        # This process stops them itself, in the guard's order; the guard is ended last, so
        # that it still stops the rest if this process is killed meanwhile (the record
        # follows each stop).
        # Replicas with their kind: a processors replica stopped after Kafka spent its whole
        # stop timeout retrying the gone broker.
        for name in sorted(self.procs, key=lifetime.stop_rank):
            embedded.stop(self.procs.pop(name))
            self._record()
        if self.tied_to_parent:
            self.pid_file.remove()
        if self.guard is not None:
            self.guard.kill()
            self.guard.wait()
            self.guard = None

    def __enter__(self) -> Stack:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
