"""The embedded Apache Kafka broker: one KRaft node (broker and controller) run from the
published jars, its log on disk under the data dir.

The jars are resolved once by Maven from `kafka/pom.xml` (which pins the version compose
and the Strimzi files run) into a cache shared by every data dir; the node is formatted
once per log directory, so a restart (or a SIGKILL) keeps every record it acknowledged.
Retention by time and by size bounds its disk; a small heap bounds its memory. Where no
Java is installed, `mapservice up` falls back to tansu (`embedded.start_tansu`), which keeps
records in memory only.
"""

from __future__ import annotations

import fcntl
import os
import re
import shutil
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from mapservice.local.embedded import ensure_port_free, free_port, start_tansu, wait_for_port
from mapservice.local.kafka_auth import TANSU_NO_AUTH, listener_properties, sasl_client_config

if TYPE_CHECKING:
    from mapservice.settings import Settings

POM = Path(__file__).parent / "kafka" / "pom.xml"
NODE_ID = 1
# Start fast and small: the serial collector and the client compiler (C1) only; a JVM's
# class-data sharing archive where the JDK has one. Measured here: ready ~2 s after start.
JVM_FLAGS = (
    "-XX:+UseSerialGC",
    "-XX:TieredStopAtLevel=1",
    "-Xshare:auto",
    "-XX:+ExitOnOutOfMemoryError",
    "-Djava.awt.headless=true",
)
# WARN and above, plus the lines that say the node started and stopped.
LOG4J2_YAML = """\
Configuration:
  Appenders:
    Console:
      name: STDOUT
      PatternLayout:
        pattern: "[%d] %p %m (%c)%n"
  Loggers:
    Root:
      level: WARN
      AppenderRef:
        - ref: STDOUT
    Logger:
      - name: kafka.server.KafkaRaftServer
        level: INFO
"""


def kafka_version() -> str:
    """The Kafka version the pom pins (`kafka.version`)."""
    match = re.search(r"<kafka\.version>([^<]+)</kafka\.version>", POM.read_text())
    if match is None:
        raise RuntimeError(f"{POM} names no <kafka.version>")
    return match.group(1).strip()


def embedded_choice(setting: str) -> str:
    """ "apache" or "tansu" for MAPSERVICE_EMBEDDED_KAFKA (auto: apache where Java is)."""
    if setting == "auto":
        return "apache" if java_binary() is not None else "tansu"
    return setting


TANSU_COST = (
    "tansu keeps every record in memory (~1.7 KB an event, no retention: ~0.7 GB a "
    "day at 5 robots) and a restart of it loses every record it held, acknowledged "
    "or not"
)


def java_binary() -> str | None:
    """The `java` to run the broker with (JAVA_HOME's first), or None where none is installed."""
    home = os.environ.get("JAVA_HOME")
    if home and os.access(Path(home) / "bin" / "java", os.X_OK):
        return str(Path(home) / "bin" / "java")
    return shutil.which("java")


def default_jars_dir() -> Path:
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "mapservice" / f"kafka-{kafka_version()}"


def ensure_jars(
    jars_dir: Path | None = None, progress: Callable[[str], None] = lambda line: None
) -> Path:
    """The directory of the broker's jars, resolved by Maven on first use (44 MB in 46 jars,
    411 files downloaded into a 56 MB Maven repository: 20 s here on a quiet machine, 32-70 s
    at a load average of 22-31; 24-42 s from a warm Maven repository at that load, Maven's
    own start); later calls find them resolved and run no Maven. `progress` gets each jar
    Maven downloads. Concurrent callers (test processes) wait for one download."""
    jars_dir = Path(jars_dir or default_jars_dir())
    libs, done = jars_dir / "libs", jars_dir / ".complete"
    if done.exists():
        return libs
    jars_dir.mkdir(parents=True, exist_ok=True)
    with open(jars_dir / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if done.exists():
            return libs
        mvn = shutil.which("mvn")
        if mvn is None:
            raise RuntimeError(
                "Maven (`mvn`) is not installed, so the Apache Kafka jars cannot be fetched: "
                "`make up` installs it as root (Debian: apt-get install maven), or set "
                "MAPSERVICE_EMBEDDED_KAFKA=tansu to run on tansu (in memory, no retention)"
            )
        staging = jars_dir / "libs.partial"
        shutil.rmtree(staging, ignore_errors=True)
        shutil.rmtree(libs, ignore_errors=True)
        proc = subprocess.Popen(
            [
                mvn,
                "-B",
                "-f",
                str(POM),
                "dependency:copy-dependencies",
                f"-DoutputDirectory={staging}",
                "-Dmdep.useRepositoryLayout=false",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        output: list[str] = []
        assert proc.stdout is not None
        for line in proc.stdout:
            output.append(line.rstrip())
            # Maven logs them as "[INFO] Downloaded from central: <url> (<size> at <rate>)".
            if "Downloaded from" in line and ".jar" in line:
                progress(line[line.index("Downloaded from") :].strip())
        if proc.wait() != 0:
            errors = [line for line in output if "[ERROR]" in line][:5]
            raise RuntimeError(
                f"Maven could not fetch Apache Kafka {kafka_version()}'s jars (is Maven Central "
                "reachable from here? a proxy goes into ~/.m2/settings.xml); set "
                "MAPSERVICE_EMBEDDED_KAFKA=tansu to run on tansu instead. Maven said:\n"
                + "\n".join(errors or output[-10:])
            )
        staging.rename(libs)
        done.write_text(kafka_version() + "\n")
    return libs


@dataclass(frozen=True)
class KafkaNodeConfig:
    """One KRaft node on 127.0.0.1: where it listens and keeps its log, what it keeps. Alone
    by default; with `voters` and `replication` one of a cluster (the fault tests')."""

    log_dir: Path
    port: int
    controller_port: int
    heap_mb: int = 256
    retention_hours: int = 24
    # Per partition; log segments of a sixteenth of it, so retention frees space in steps.
    retention_bytes: int = 256 * 1024**2
    node_id: int = NODE_ID
    voters: str = ""  # id@host:port,...; empty: this node alone
    replication: int = 1  # of internal and new topics
    min_insync_replicas: int = 1
    # (username, password) pairs: both listeners then take only SASL/PLAIN clients that
    # name one of them (kafka_auth.py); the first is the node's own, for its controller
    # connection. Empty: no authentication (anyone who reaches the port may produce).
    sasl_users: tuple[tuple[str, str], ...] = ()

    def properties(self) -> str:
        segment = max(1024**2, self.retention_bytes // 16)
        return "\n".join(
            [
                "process.roles=broker,controller",
                f"node.id={self.node_id}",
                # A static voter set: the controller's port is not written into the metadata
                # log, so a lone node's restart may pick another free port.
                "controller.quorum.voters="
                + (self.voters or f"{self.node_id}@127.0.0.1:{self.controller_port}"),
                *listener_properties(self.port, self.controller_port, self.sasl_users),
                f"log.dirs={self.log_dir}",
                "num.partitions=1",
                f"default.replication.factor={self.replication}",
                f"min.insync.replicas={self.min_insync_replicas}",
                f"offsets.topic.replication.factor={self.replication}",
                "offsets.topic.num.partitions=6",
                f"transaction.state.log.replication.factor={self.replication}",
                f"transaction.state.log.min.isr={self.min_insync_replicas}",
                f"share.coordinator.state.topic.replication.factor={self.replication}",
                f"share.coordinator.state.topic.min.isr={self.min_insync_replicas}",
                "group.initial.rebalance.delay.ms=0",
                # Classic-protocol members may ask for sessions down to 3 s
                # (MAPSERVICE_KAFKA_SESSION_TIMEOUT_S; Kafka's floor is 6 s).
                "group.min.session.timeout.ms=3000",
                # Consumer groups of Kafka 4's protocol (KIP-848, MAPSERVICE_KAFKA_GROUP_PROTOCOL):
                # the broker holds the members' session and heartbeat; the same 10 s and 1 s the
                # classic protocol's members ask for (kafka_batch_source.py), under Kafka's
                # defaults' floors of 45 s and 5 s.
                "group.consumer.min.session.timeout.ms=10000",
                "group.consumer.session.timeout.ms=10000",
                "group.consumer.min.heartbeat.interval.ms=1000",
                "group.consumer.heartbeat.interval.ms=1000",
                # The service creates its own topics (the meta topic compacted).
                "auto.create.topics.enable=false",
                # Everything is in ClickHouse within a second: Kafka keeps a day, and at most
                # retention_bytes per partition, checked every minute.
                f"log.retention.hours={self.retention_hours}",
                f"log.retention.bytes={self.retention_bytes}",
                f"log.segment.bytes={segment}",
                "log.retention.check.interval.ms=60000",
                # After a SIGKILL the restarted node may register only once its old session has
                # expired (9 s by default); heartbeats stay in this one process.
                "broker.heartbeat.interval.ms=1000",
                "broker.session.timeout.ms=4000",
                # Few threads: one small node on a shared machine.
                "num.network.threads=2",
                "num.io.threads=2",
                "background.threads=2",
                "num.recovery.threads.per.data.dir=1",
                "",
            ]
        )

    def client_config(self) -> dict[str, str]:
        """librdkafka's security settings to reach this node (as its own user)."""
        if not self.sasl_users:
            return {}
        return sasl_client_config(*self.sasl_users[0])


def format_once(
    java: str, libs: Path, config_file: Path, log_dir: Path, cluster: str | None = None
) -> bool:
    """Formats the node's log directory unless it already is (then its records and
    offsets are kept); True if it formatted."""
    if (log_dir / "meta.properties").exists():
        return False
    log_dir.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        [
            java,
            *JVM_FLAGS,
            "-Xmx128m",
            "-cp",
            f"{libs}/*",
            f"-Dlog4j2.configurationFile={config_file.with_name('log4j2.yaml')}",
            # `--cluster-id=<id>` in one argument: an id that starts with "-" (one in 32 of
            # the URL-safe ids) is otherwise read by the tool as an option of its own.
            "kafka.tools.StorageTool",
            "format",
            f"--cluster-id={cluster or cluster_id()}",
            "--config",
            str(config_file),
            "--ignore-formatted",
        ],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise RuntimeError(
            f"formatting Kafka's log in {log_dir} failed: "
            f"{(done.stderr or done.stdout).strip()[-2000:]}"
        )
    return True


def cluster_id() -> str:
    """A new cluster id as Kafka writes them (a UUID in URL-safe base64, no padding)."""
    import base64

    return base64.urlsafe_b64encode(uuid.uuid4().bytes).decode().rstrip("=")


def start_kafka(
    config: KafkaNodeConfig,
    log_file=None,
    jars_dir: Path | None = None,
    timeout_s: float = 90.0,
    preexec_fn=None,
) -> subprocess.Popen:
    """Starts the node (formatting its log directory the first time) and returns once it
    answers a metadata request; its own process group, so it stops with `embedded.stop`."""
    earlier = running_pid(config)
    if earlier is not None:
        raise RuntimeError(
            f"an Apache Kafka from an earlier run still holds {config.log_dir} (pid {earlier}, "
            f"left behind by a killed `mapservice up`?): stop it with `kill {earlier}`"
        )
    proc = launch(config, log_file, jars_dir, preexec_fn=preexec_fn)
    (config.log_dir.parent / "kafka.pid").write_text(f"{proc.pid}\n")
    try:
        wait_for_port(config.port, timeout_s=timeout_s, proc=proc, what="Apache Kafka")
        wait_until_serving(f"127.0.0.1:{config.port}", proc, timeout_s, config.client_config())
    except BaseException:
        stop_process_group(proc)
        raise
    return proc


def running_pid(config: KafkaNodeConfig) -> int | None:
    """The pid of a broker still running on this node's config (its pid file and its
    command line agree), else None."""
    try:
        pid = int((config.log_dir.parent / "kafka.pid").read_text())
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except (OSError, ValueError):
        return None
    config_file = str(config.log_dir.parent / "server.properties").encode()
    return pid if b"kafka.Kafka" in cmdline and config_file in cmdline else None


def launch(
    config: KafkaNodeConfig,
    log_file=None,
    jars_dir: Path | None = None,
    cluster: str | None = None,
    preexec_fn=None,
) -> subprocess.Popen:
    """Starts the node's JVM without waiting (the nodes of a cluster form their quorum only
    together); formats its log directory first if it is new, with `cluster` as its id."""
    java = java_binary()
    if java is None:
        raise RuntimeError(
            "no Java runtime for Apache Kafka (Debian: apt-get install "
            "default-jre-headless; `make up` does as root)"
        )
    ensure_port_free(config.port, "Kafka")
    ensure_port_free(config.controller_port, "Kafka's controller")
    libs = ensure_jars(jars_dir)
    config_dir = config.log_dir.parent
    config_dir.mkdir(parents=True, exist_ok=True)
    config_file = config_dir / "server.properties"
    # Only this user reads it: with SASL it holds the users' passwords.
    with open(os.open(config_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600), "w") as file:
        file.write(config.properties())
    config_file.chmod(0o600)
    (config_dir / "log4j2.yaml").write_text(LOG4J2_YAML)
    format_once(java, libs, config_file, config.log_dir, cluster)
    return subprocess.Popen(
        [
            java,
            *JVM_FLAGS,
            f"-Xms{min(64, config.heap_mb)}m",
            f"-Xmx{config.heap_mb}m",
            f"-Dlog4j2.configurationFile={config_dir / 'log4j2.yaml'}",
            "-cp",
            f"{libs}/*",
            "kafka.Kafka",
            str(config_file),
        ],
        stdout=log_file or subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=preexec_fn,
    )


def wait_until_serving(
    bootstrap: str, proc: subprocess.Popen, timeout_s: float, security: dict | None = None
) -> None:
    """Until the broker names itself in a metadata answer (it listens before it has caught
    up with its metadata log)."""
    from confluent_kafka.admin import AdminClient

    admin = AdminClient({"bootstrap.servers": bootstrap, "log_level": 0, **(security or {})})
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"Apache Kafka exited with code {proc.returncode} while starting")
        try:
            if admin.list_topics(timeout=2).brokers:
                return
        except Exception:  # KafkaException while it starts
            pass
        time.sleep(0.1)
    raise RuntimeError(f"Apache Kafka at {bootstrap} did not answer within {timeout_s:.0f} s")


def stop_process_group(proc: subprocess.Popen | None, timeout_s: float = 30.0) -> None:
    """SIGTERM (a clean shutdown: the log is flushed and closed), SIGKILL after timeout_s."""
    if proc is None or proc.poll() is not None:
        return
    import signal

    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    except ProcessLookupError:
        proc.wait()


def start_embedded(
    choice: str,
    data_dir: Path,
    port: int,
    settings: Settings,
    log_file=None,
    preexec_fn=None,
    sasl_users: tuple[tuple[str, str], ...] = (),
) -> subprocess.Popen:
    """The embedded broker `choice` names ("apache" or "tansu", see `embedded_choice`) on
    `port`, Apache Kafka's log under DATA_DIR/kafka/; either stops with `embedded.stop`.
    With `sasl_users` only clients naming one of them (SASL/PLAIN) are served: Apache
    Kafka only (tansu has no authentication)."""
    if choice == "apache":
        node = node_for(
            data_dir,
            port,
            heap_mb=settings.embedded_kafka_heap_mb,
            retention_hours=settings.embedded_kafka_retention_hours,
            retention_bytes=settings.embedded_kafka_retention_bytes,
            sasl_users=sasl_users,
        )
        return start_kafka(node, log_file, jars_dir=settings.kafka_jars_dir, preexec_fn=preexec_fn)
    if choice == "tansu" and sasl_users:
        raise ValueError(TANSU_NO_AUTH)
    if choice == "tansu":
        return start_tansu(port, log_file, preexec_fn=preexec_fn)
    raise ValueError(f"no embedded Kafka broker named {choice!r}: apache or tansu")


def node_for(data_dir: Path, port: int, **limits) -> KafkaNodeConfig:
    """The embedded node of a data dir: its log in DATA_DIR/kafka/log."""
    return KafkaNodeConfig(
        log_dir=Path(data_dir).resolve() / "kafka" / "log",
        port=port,
        controller_port=free_port(),
        **limits,
    )


if __name__ == "__main__":
    # `python -m mapservice.local.kafka_broker fetch`: resolves the jars (make, CI).
    if sys.argv[1:] == ["fetch"]:
        print(ensure_jars(progress=print))
    else:
        sys.exit("usage: python -m mapservice.local.kafka_broker fetch")
