"""The embedded Apache Kafka's class-data archive: made once per Java and set of jars (one
archive however many processes ask at once), mapped by the formatter's and the broker's
JVMs, and never a reason for a broker not to start (absent, not whole, made for other
jars, or one the JVM dies on)."""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import subprocess
import threading
from pathlib import Path

import pytest

from mapservice.local import embedded, kafka_broker, kafka_cds

pytestmark = pytest.mark.integration


def java() -> str:
    found = kafka_broker.java_binary()
    if found is None:
        pytest.fail("no Java runtime for Apache Kafka (`make system-deps` installs it)")
    return found


def copy_jars(into: Path, link: bool = True) -> Path:
    """A jars directory of its own (the archive is kept beside the jars): the cached jars,
    with their times kept, linked where the file system allows unless `link` is False (the
    JVM takes a hard link for the file an archive was made with)."""
    libs = kafka_broker.ensure_jars()
    (into / "libs").mkdir(parents=True)
    for jar in libs.glob("*.jar"):
        try:
            if not link:
                raise OSError("copy asked for")
            os.link(jar, into / "libs" / jar.name)
        except OSError:
            shutil.copy2(jar, into / "libs" / jar.name)
    (into / ".complete").write_text(kafka_broker.kafka_version() + "\n")
    return into / "libs"


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """Three processes' worth of callers asking for the archive at once."""
    jars = tmp_path_factory.mktemp("jars")
    libs = copy_jars(jars)
    lines: list[str] = []
    trained: list[tuple[str, ...]] = []
    results: list[Path | None] = []

    def train(dump: tuple[str, ...]) -> None:
        trained.append(dump)
        kafka_broker.train_archive(java(), libs, dump)

    def ask() -> None:
        results.append(kafka_cds.ensure_archive(java(), libs, train, lines.append, wait=True))

    askers = [threading.Thread(target=ask) for _ in range(3)]
    for asker in askers:
        asker.start()
    for asker in askers:
        asker.join(timeout=600)
    return jars, libs, lines, trained, results


def loaded_from_archive(libs: Path, archive: Path, strict: bool = True) -> str:
    """A Kafka tool run on the archive with its class loading logged (`-Xshare:on`: the JVM
    refuses to start unless the archive maps)."""
    done = subprocess.run(
        [
            java(),
            "-XX:+UseSerialGC",
            "-Xshare:on" if strict else "-Xshare:auto",
            f"-XX:SharedArchiveFile={archive}",
            "-Xlog:class+load=info",
            "-cp",
            f"{libs}/*",
            "kafka.tools.StorageTool",
            "random-uuid",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    return done.stdout


def start_node(tmp_path: Path, jars: Path) -> tuple[subprocess.Popen, Path]:
    config = kafka_broker.node_for(tmp_path / "data", embedded.free_port())
    log = tmp_path / "kafka.log"
    with open(log, "ab") as log_file:
        proc = kafka_broker.start_kafka(config, log_file, jars_dir=jars)
    return proc, log


def test_concurrent_callers_make_one_archive_that_maps(made) -> None:
    """One training run, one progress pair, the same archive for every caller, nothing
    partial left; the archive maps and holds Kafka's own classes."""
    jars, libs, lines, trained, results = made
    archive = kafka_cds.archive_path(java(), libs)
    assert len(trained) == 1
    assert results == [archive] * 3
    assert [line.split(" ")[0] for line in lines] == ["making", "made"]
    assert sorted(path.name for path in jars.glob("classes-*")) == [
        archive.name,
        archive.with_suffix(".size").name,
    ]
    loaded = loaded_from_archive(libs, archive)
    # The archive is a broker's: the tool shares the broker's configuration classes.
    assert "kafka.server.KafkaConfig source: shared objects file (top)" in loaded


def test_the_formatter_and_the_broker_start_on_the_archive(made, tmp_path, monkeypatch) -> None:
    """With sharing required the formatter's JVM starts only if the archive maps; the
    broker's maps the archive's file, and the archive is kept."""
    jars, libs, *_ = made
    archive = kafka_cds.archive_path(java(), libs)
    strict = tuple(
        "-Xshare:on" if flag == "-Xshare:auto" else flag for flag in kafka_broker.JVM_FLAGS
    )
    monkeypatch.setattr(kafka_broker, "JVM_FLAGS", strict)
    proc, _ = start_node(tmp_path, jars)
    try:
        assert kafka_broker.mapped_archive(proc) == str(archive)
        assert str(archive) in Path(f"/proc/{proc.pid}/maps").read_text()
        assert archive.exists()
    finally:
        kafka_broker.stop_process_group(proc)


def test_an_archive_made_for_other_jars_only_warns(made, tmp_path) -> None:
    """The archive copied beside the same jars at another path (what another jars directory
    or a moved cache looks like to the JVM): it refuses to map it, says so, and the broker
    serves."""
    _, libs, *_ = made
    other = copy_jars(tmp_path / "other", link=False)
    archive = kafka_cds.archive_path(java(), libs)
    for made_file in (archive, archive.with_suffix(".size")):
        shutil.copy2(made_file, other.parent / made_file.name)
    assert kafka_cds.sharing_flags(java(), other)
    proc, log = start_node(tmp_path, other.parent)
    try:
        copied = kafka_broker.mapped_archive(proc)
        assert copied == str(other.parent / archive.name)
        assert "Unable to use shared archive" in log.read_text()
        assert copied not in Path(f"/proc/{proc.pid}/maps").read_text()
    finally:
        kafka_broker.stop_process_group(proc)


def test_a_truncated_archive_is_not_handed_to_the_jvm(made, tmp_path, caplog) -> None:
    """The JVM dies of a truncated archive even under -Xshare:auto: one shorter than it was
    made is left out (logged) and the broker serves."""
    _, libs, *_ = made
    other = copy_jars(tmp_path / "other")
    archive = kafka_cds.archive_path(java(), libs)
    shutil.copy2(archive.with_suffix(".size"), other.parent)
    with open(archive, "rb") as whole, open(other.parent / archive.name, "wb") as cut:
        cut.write(whole.read(archive.stat().st_size // 2))
    # The note of a failed making: this start does not make the archive again.
    kafka_cds.archive_path(java(), other).with_suffix(".failed").write_text("test\n")
    with caplog.at_level(logging.WARNING):
        assert kafka_cds.sharing_flags(java(), other) == ()
    assert "not whole" in caplog.text
    proc, _ = start_node(tmp_path, other.parent)
    try:
        assert kafka_broker.mapped_archive(proc) is None
    finally:
        kafka_broker.stop_process_group(proc)


@pytest.mark.parametrize("log_dir", ["new", "formatted"])
def test_a_jvm_that_dies_on_the_archive_is_started_again_without_it(
    made, tmp_path, log_dir, caplog
) -> None:
    """An archive the JVM crashes on (a truncated one whose size note was rewritten to
    match): the formatter (a new log directory) or the broker (a formatted one) dies on it,
    the archive is discarded with a warning, and the node serves without it."""
    _, libs, *_ = made
    other = copy_jars(tmp_path / "other")
    config = kafka_broker.node_for(tmp_path / "data", embedded.free_port())
    if log_dir == "formatted":
        config_file = config.write_files()
        assert kafka_broker.format_once(java(), other, config_file, config.log_dir)
    archive = kafka_cds.archive_path(java(), other)
    with open(kafka_cds.archive_path(java(), libs), "rb") as whole:
        archive.write_bytes(whole.read(8 * 1024**2))
    archive.with_suffix(".size").write_text(f"{8 * 1024**2}\n")
    with caplog.at_level(logging.WARNING), open(tmp_path / "kafka.log", "ab") as log_file:
        proc = kafka_broker.start_kafka(config, log_file, jars_dir=other.parent)
    try:
        assert kafka_broker.mapped_archive(proc) is None
        assert not archive.exists()
        assert "discarding Kafka's class-data archive" in caplog.text
        # The crash report is the node's, not left in the working directory.
        assert list(config.log_dir.parent.glob("hs_err_pid*.log"))
        assert not list(Path.cwd().glob("hs_err_pid*.log"))
    finally:
        kafka_broker.stop_process_group(proc)


def test_a_failed_making_is_logged_and_not_tried_at_every_start(tmp_path, caplog) -> None:
    """A training that fails: no archive, a warning naming the note to remove to try again,
    and the next call does not train again."""
    libs = tmp_path / "libs"
    libs.mkdir()
    calls: list[tuple[str, ...]] = []

    def failing(dump: tuple[str, ...]) -> None:
        calls.append(dump)
        raise RuntimeError("Apache Kafka exited with code 1 while starting")

    with caplog.at_level(logging.WARNING):
        assert kafka_cds.ensure_archive(java(), libs, failing) is None
        assert kafka_cds.ensure_archive(java(), libs, failing) is None
    assert len(calls) == 1
    assert "exited with code 1" in caplog.text
    assert str(kafka_cds.archive_path(java(), libs).with_suffix(".failed")) in caplog.text
    assert kafka_cds.sharing_flags(java(), libs) == ()


def test_a_start_does_not_wait_for_another_process_making_it(tmp_path) -> None:
    """While another process holds the making lock a broker's start goes on without the
    archive (it would otherwise wait a broker's start and stop)."""
    libs = tmp_path / "libs"
    libs.mkdir()
    with open(tmp_path / ".classes.lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        called = []
        assert kafka_cds.ensure_archive(java(), libs, called.append, wait=False) is None
        assert called == []


@pytest.mark.parametrize("change", ["a jar grows", "a jar is added", "another java"])
def test_another_java_or_other_jars_name_another_archive(tmp_path, change) -> None:
    """The archive's name changes with the Java runtime and with any jar, so a stale one is
    never looked up."""
    libs = tmp_path / "libs"
    libs.mkdir()
    (libs / "kafka_2.13-4.1.1.jar").write_bytes(b"x" * 100)
    runtime = tmp_path / "jdk" / "bin" / "java"
    runtime.parent.mkdir(parents=True)
    runtime.write_text("")
    before = kafka_cds.archive_path(str(runtime), libs)
    if change == "a jar grows":
        (libs / "kafka_2.13-4.1.1.jar").write_bytes(b"x" * 101)
    elif change == "a jar is added":
        (libs / "kafka-clients-4.2.0.jar").write_bytes(b"x")
    else:
        runtime = tmp_path / "jdk21" / "bin" / "java"
        runtime.parent.mkdir(parents=True)
        runtime.write_text("")
    after = kafka_cds.archive_path(str(runtime), libs)
    assert after != before
    assert after.parent == before.parent == tmp_path


def test_a_formatter_failing_for_its_config_keeps_the_archive(made, tmp_path) -> None:
    """A configuration the tool refuses fails with and without the archive: the error is the
    tool's, and the archive, not at fault, is kept."""
    _, libs, *_ = made
    other = copy_jars(tmp_path / "other")
    archive = kafka_cds.archive_path(java(), libs)
    for made_file in (archive, archive.with_suffix(".size")):
        shutil.copy2(made_file, other.parent / made_file.name)
    sharing = kafka_cds.sharing_flags(java(), other)
    assert sharing
    config_file = tmp_path / "server.properties"
    config_file.write_text("process.roles=broker,controller\n")  # no node.id, no log.dirs
    (tmp_path / "log4j2.yaml").write_text(kafka_broker.LOG4J2_YAML)
    with pytest.raises(RuntimeError, match="formatting Kafka's log"):
        kafka_broker.format_once(java(), other, config_file, tmp_path / "log", sharing=sharing)
    assert kafka_cds.sharing_flags(java(), other) == sharing
