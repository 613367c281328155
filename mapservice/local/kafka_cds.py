"""A class-data sharing archive for the embedded Apache Kafka's JVMs: the classes a broker
loads while it starts, parsed and verified once and mapped from a file by every later JVM
(the log formatter's and the broker's), which then start on about half the CPU.

One archive per jars directory, Java runtime and set of jars: its name carries a digest of
them, so another Java or another Kafka version never maps an archive made for the other
one. It is made by a broker's own start (`-XX:ArchiveClassesAtExit`), written under a
temporary name, proved to map (`-Xshare:on`) and only then renamed into place; a file
beside it records the size it was made with. A JVM handed a truncated archive crashes even
under `-Xshare:auto`, so an archive whose size differs is never handed to one; any other
mismatch the JVM itself refuses with a warning and starts without it. Where the archive
cannot be made (or is being made by another process), brokers start without it.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import logging
import os
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

log = logging.getLogger(__name__)

# Runs a broker's start to its end with the given extra JVM flags (kafka_broker.py).
Trainer = Callable[[tuple[str, ...]], None]


def archive_path(java: str, libs: Path) -> Path:
    """Where the archive for this Java and these jars lives: beside the jars."""
    return libs.parent / f"classes-{archive_key(java, libs)}.jsa"


def archive_key(java: str, libs: Path) -> str:
    """A digest of the Java runtime (its binary and its module image, which another update
    of the JDK replaces) and of every jar (name, size, time)."""
    digest = hashlib.sha256()
    runtime = Path(os.path.realpath(java))
    digest.update(str(runtime).encode())
    for part in (runtime, runtime.parent.parent / "lib" / "modules"):
        with contextlib.suppress(OSError):
            stat = part.stat()
            digest.update(f"{part}:{stat.st_size}:{stat.st_mtime_ns}\n".encode())
    for jar in sorted(libs.glob("*.jar")):
        stat = jar.stat()
        digest.update(f"{jar.name}:{stat.st_size}:{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:16]


def sharing_flags(java: str, libs: Path) -> tuple[str, ...]:
    """The JVM flags that map this Java's archive for these jars, or none where there is no
    whole one (absent, or not the size it was made with)."""
    archive = archive_path(java, libs)
    try:
        made = int(_size_file(archive).read_text())
        whole = archive.stat().st_size == made
    except (OSError, ValueError):
        return ()
    if not whole:
        log.warning("Kafka's class-data archive %s is not whole: starting without it", archive)
        return ()
    return (f"-XX:SharedArchiveFile={archive}",)


def discard(java: str, libs: Path, why: str) -> None:
    """Removes an archive a JVM could not start with, so that the next start makes none of
    it (and `ensure_archive` makes it again)."""
    archive = archive_path(java, libs)
    log.warning("discarding Kafka's class-data archive %s: %s", archive, why)
    for path in (_size_file(archive), archive):
        with contextlib.suppress(OSError):  # a read-only cache: then it is only not used
            path.unlink(missing_ok=True)


def ensure_archive(
    java: str,
    libs: Path,
    train: Trainer,
    progress: Callable[[str], None] = lambda line: None,
    wait: bool = True,
) -> Path | None:
    """The archive for this Java and these jars, made by `train` the first time (a broker's
    start and stop: 10-50 s here, by load). One process makes it; with `wait` the others
    wait for it, without they go on without it. None (logged) where it cannot be made; then
    no start makes it until the jars or the Java change or the note of the failure goes."""
    archive = archive_path(java, libs)
    if sharing_flags(java, libs):
        return archive
    failed = archive.with_suffix(".failed")
    if failed.exists() or not os.access(libs.parent, os.W_OK):
        return None

    def say(line: str) -> None:
        log.info(line)
        progress(line)

    with _lock(libs.parent / ".classes.lock", wait) as held:
        if not held:
            return None
        if sharing_flags(java, libs):
            return archive
        say(f"making a class-data archive of Apache Kafka's JVM in {archive} (once)...")
        started = time.monotonic()
        try:
            _make(java, libs, archive, train)
        except Exception as error:  # a broker that did not start, a JVM that did not dump
            with contextlib.suppress(OSError):
                failed.write_text(f"{error}\n")
            log.warning(
                "could not make Kafka's class-data archive (brokers start without it; remove "
                "%s to try again): %s",
                failed,
                error,
            )
            return None
        say(
            f"made the class-data archive in {time.monotonic() - started:.1f} s "
            f"({archive.stat().st_size // 1024**2} MB)"
        )
        return archive


def _make(java: str, libs: Path, archive: Path, train: Trainer) -> None:
    partial = archive.with_name(f"{archive.name}.{os.getpid()}.partial")
    partial.unlink(missing_ok=True)
    try:
        train((f"-XX:ArchiveClassesAtExit={partial}",))
        if not partial.exists():
            raise RuntimeError("the JVM wrote no archive at its exit")
        _prove_it_maps(java, libs, partial)
        # The size first: an archive without it is never used, one with it is whole.
        _size_file(archive).write_text(f"{partial.stat().st_size}\n")
        partial.rename(archive)
    finally:
        partial.unlink(missing_ok=True)


def _prove_it_maps(java: str, libs: Path, archive: Path) -> None:
    """Starts a small Kafka tool on it with sharing required: the JVM refuses to start
    unless it maps."""
    done = subprocess.run(
        [
            java,
            "-Xshare:on",
            f"-XX:SharedArchiveFile={archive}",
            "-XX:TieredStopAtLevel=1",
            "-cp",
            f"{libs}/*",
            "kafka.tools.StorageTool",
            "random-uuid",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    if done.returncode != 0:
        raise RuntimeError(
            f"the archive made does not map: {(done.stderr or done.stdout).strip()[-1000:]}"
        )


def _size_file(archive: Path) -> Path:
    return archive.with_suffix(".size")


@contextlib.contextmanager
def _lock(path: Path, wait: bool) -> Iterator[bool]:
    with open(path, "w") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if wait else fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        yield True
