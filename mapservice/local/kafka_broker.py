"""The embedded Apache Kafka broker: one KRaft node (broker and controller) run from the
published jars, its log on disk under the data dir.

The jars are resolved once by Maven from `kafka/pom.xml` (which pins the version compose
and the Strimzi files run) into a cache shared by every data dir; the node is formatted
once per log directory, so a restart (or a SIGKILL) keeps every record it acknowledged.
Both JVMs (the formatter's and the broker's) map the jars' class-data archive, made once
by `fetch` or the first start (kafka_cds.py).
Retention by time and by size bounds its disk; a small heap bounds its memory. Where no
Java is installed, `mapservice up` falls back to tansu (`embedded.start_tansu`), which keeps
records in memory only.
"""

from __future__ import annotations

import dataclasses
import fcntl
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import structlog

from mapservice.local import kafka_cds
from mapservice.local.embedded import (
    ensure_port_free,
    free_port,
    port_is_free,
    start_tansu,
    wait_for_port,
)
from mapservice.local.kafka_auth import TANSU_NO_AUTH
from mapservice.local.kafka_node import LOG4J2_YAML as LOG4J2_YAML
from mapservice.local.kafka_node import NODE_ID as NODE_ID
from mapservice.local.kafka_node import KafkaNodeConfig as KafkaNodeConfig

if TYPE_CHECKING:
    from mapservice.settings import Settings

log = structlog.get_logger(__name__)

POM = Path(__file__).parent / "kafka" / "pom.xml"
# Start fast and small: the serial collector and the client compiler (C1) only; the JDK's
# class-data sharing archive, and over it the jars' own (kafka_cds.py) once it is made.
JVM_FLAGS = (
    "-XX:+UseSerialGC",
    "-XX:TieredStopAtLevel=1",
    "-Xshare:auto",
    "-XX:+ExitOnOutOfMemoryError",
    "-Djava.awt.headless=true",
)


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


def format_once(
    java: str,
    libs: Path,
    config_file: Path,
    log_dir: Path,
    cluster: str | None = None,
    sharing: tuple[str, ...] = (),
) -> bool:
    """Formats the node's log directory unless it already is (then its records and
    offsets are kept); True if it formatted. `sharing`: flags of a class-data archive
    (kafka_cds.py); if the tool fails with them, the archive is discarded and it runs again
    without."""
    if (log_dir / "meta.properties").exists():
        return False
    log_dir.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        [
            java,
            *JVM_FLAGS,
            *sharing,
            "-Xmx128m",
            # A JVM's crash report beside its config, not in the caller's working directory.
            f"-XX:ErrorFile={config_file.with_name('hs_err_pid%p.log')}",
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
    if done.returncode != 0 and sharing:
        # Discarded only if the tool then succeeds without it (a bad config fails both ways).
        formatted = format_once(java, libs, config_file, log_dir, cluster)
        kafka_cds.discard(java, libs, f"Kafka's StorageTool exited with {done.returncode}")
        return formatted
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
    config = with_free_controller_port(config)
    proc = launch(config, log_file, jars_dir, preexec_fn=preexec_fn)
    try:
        wait_ready(config, proc, timeout_s)
    except ExitedWhileStarting:
        if mapped_archive(proc) is None:
            raise
        # A JVM that dies while it starts on an archive is retried once without it.
        kafka_cds.discard(
            str(java_binary()),
            ensure_jars(jars_dir),
            f"a broker started on it exited with {proc.returncode}",
        )
        proc = launch(config, log_file, jars_dir, preexec_fn=preexec_fn, sharing=())
        wait_ready(config, proc, timeout_s)
    return proc


def with_free_controller_port(config: KafkaNodeConfig) -> KafkaNodeConfig:
    """The node alone with another controller port if something took its own since it was
    chosen. That port is told to no client and to no other node, so it is the node's to
    change; it was free when chosen, but processes side by side choose free ports the same
    way and one of them may bind it first. A cluster's nodes keep theirs: the voters name
    them."""
    if config.voters or port_is_free(config.controller_port):
        return config
    chosen = dataclasses.replace(config, controller_port=free_port())
    log.info(
        "the Kafka controller's port was taken since it was chosen: another chosen",
        taken=config.controller_port,
        port=chosen.controller_port,
    )
    return chosen


def wait_ready(config: KafkaNodeConfig, proc: subprocess.Popen, timeout_s: float) -> None:
    """Until the node answers a metadata request; stops it if it does not."""
    (config.log_dir.parent / "kafka.pid").write_text(f"{proc.pid}\n")
    try:
        wait_for_port(config.port, timeout_s=timeout_s, proc=proc, what="Apache Kafka")
        wait_until_serving(f"127.0.0.1:{config.port}", proc, timeout_s, config.client_config())
    except BaseException as error:
        exited = proc.poll() is not None
        stop_process_group(proc)
        if exited and isinstance(error, RuntimeError):
            raise ExitedWhileStarting(f"{error} (exit code {proc.returncode})") from error
        raise


class ExitedWhileStarting(RuntimeError):
    """The broker's JVM ended before it served."""


def mapped_archive(proc: subprocess.Popen) -> str | None:
    """The class-data archive a JVM was started on, if any."""
    flag = "-XX:SharedArchiveFile="
    args = [str(arg) for arg in proc.args] if isinstance(proc.args, list) else []
    return next((arg[len(flag) :] for arg in args if arg.startswith(flag)), None)


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
    sharing: tuple[str, ...] | None = None,
) -> subprocess.Popen:
    """Starts the node's JVM without waiting (the nodes of a cluster form their quorum only
    together); formats its log directory first if it is new, with `cluster` as its id.
    `sharing`: the class-data flags of both JVMs; by default the jars' archive, made first
    if no other process is making it (`class_sharing`)."""
    java = java_binary()
    if java is None:
        raise RuntimeError(
            "no Java runtime for Apache Kafka (Debian: apt-get install "
            "default-jre-headless; `make up` does as root)"
        )
    ensure_port_free(config.port, "Kafka")
    ensure_port_free(config.controller_port, "Kafka's controller")
    libs = ensure_jars(jars_dir)
    if sharing is None:
        sharing = class_sharing(java, libs, wait=False)
    config_file = config.write_files()
    format_once(java, libs, config_file, config.log_dir, cluster, sharing)
    if sharing and not kafka_cds.sharing_flags(java, libs):
        sharing = ()  # the formatter died on it: discarded
    return subprocess.Popen(
        [
            *broker_command(java, libs, config, config_file),
            *sharing,
            "kafka.Kafka",
            str(config_file),
        ],
        stdout=log_file or subprocess.DEVNULL,
        stderr=subprocess.STDOUT,
        start_new_session=True,
        preexec_fn=preexec_fn,
    )


def broker_command(java: str, libs: Path, config: KafkaNodeConfig, config_file: Path) -> list[str]:
    """The broker's JVM and its flags, up to its main class."""
    return [
        java,
        *JVM_FLAGS,
        f"-Xms{min(64, config.heap_mb)}m",
        f"-Xmx{config.heap_mb}m",
        f"-XX:ErrorFile={config_file.with_name('hs_err_pid%p.log')}",
        f"-Dlog4j2.configurationFile={config_file.with_name('log4j2.yaml')}",
        "-cp",
        f"{libs}/*",
    ]


def class_sharing(
    java: str, libs: Path, wait: bool, progress: Callable[[str], None] = lambda line: None
) -> tuple[str, ...]:
    """The flags that map the jars' class-data archive, made first by a broker's start where
    there is none (kafka_cds.py); none where it cannot be made, or (without `wait`) while
    another process makes it."""
    kafka_cds.ensure_archive(
        java, libs, lambda dump: train_archive(java, libs, dump), progress, wait=wait
    )
    return kafka_cds.sharing_flags(java, libs)


def train_archive(java: str, libs: Path, dump: tuple[str, ...]) -> None:
    """Starts a throwaway node with `dump`'s flags until it serves, then stops it cleanly:
    the JVM writes the classes it loaded at its exit."""
    with tempfile.TemporaryDirectory(prefix="kafka-cds-") as tmp:
        config = KafkaNodeConfig(
            log_dir=Path(tmp) / "kafka" / "log", port=free_port(), controller_port=free_port()
        )
        config_file = config.write_files()
        format_once(java, libs, config_file, config.log_dir)
        with open(Path(tmp) / "kafka.log", "w+") as log_file:
            proc = subprocess.Popen(
                [
                    *broker_command(java, libs, config, config_file),
                    *dump,
                    "kafka.Kafka",
                    str(config_file),
                ],
                stdout=log_file,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
            try:
                wait_ready(config, proc, timeout_s=120)
            finally:
                # Writing the archive (~50 MB) at the exit takes seconds more on a busy machine.
                stop_process_group(proc, timeout_s=180)


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
            metadata_idle_ms=settings.embedded_kafka_metadata_idle_ms,
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
    # `python -m mapservice.local.kafka_broker fetch`: resolves the jars and makes their
    # class-data archive (make, CI).
    if sys.argv[1:] == ["fetch"]:
        print(libs := ensure_jars(progress=print))
        if (java := java_binary()) is not None:
            class_sharing(java, libs, wait=True, progress=print)
    else:
        sys.exit("usage: python -m mapservice.local.kafka_broker fetch")
