"""ClickHouse's disk fills up while events flow: the service says so and loses nothing.

The real pipeline in both of the service's topologies over the data dir's chDB: `up`'s
three processes (`mapservice clickhouse-server --read-write` owning the chDB directory,
`mapservice processors`, `mapservice api` asking the processors' /history-status), and
`serve` (processors and API in one process, as docs/production.md runs chDB). Tansu and
amqtt as brokers; ClickHouse's data directory on a small tmpfs of its own; poses are
published to Kafka all along (what Kafka acknowledged is what the gateway would have
acknowledged to a robot). A filler file takes the rest of the disk: ClickHouse answers
reads and `SELECT 1` but refuses every insert (NOT_ENOUGH_SPACE). Then:

- the API's /readyz answers 503 with `history_store` false and the reason (since when,
  the error), the processors' /metrics has mapservice_history_insert_failing 1 (the
  alert's expression), /api/v1/status says the history is not stored since when, and the
  replay UI (Chromium) shows "history not stored since HH:MM:SS UTC";
- the filler removed, the processors recover by themselves (ready again, gauge 0, the
  banner gone), and every pose Kafka acknowledged, before, during and after the full
  disk, is stored once.

Mounting needs root (CAP_SYS_ADMIN); without it the test is skipped and says why. Only
the ClickHouse directory is on the tmpfs, so the logs and the other components' files
stay writable and what fails is what a full ClickHouse volume fails. Bounded: each wait
is at most 60 s; about a minute a topology on an idle machine.
"""

from __future__ import annotations

import collections
import errno
import subprocess
import threading
import time
from pathlib import Path

import httpx
import pytest

from mapservice.adapters.kafka_publisher import KafkaPublisher
from mapservice.core.events import PoseReported, encode, kafka_key, make_envelope
from mapservice.local.checkout import TEST_UI_ENV
from mapservice.local.stack import Stack
from tests.ui.conftest import ARTIFACTS, DIST, module_browser, page  # noqa: F401  (fixtures)

from .conftest import stored_keys

pytestmark = pytest.mark.long

DISK_MB = 96
ROBOTS = [f"df-r{i}" for i in range(5)]
RATE_HZ = 10  # per robot: 50 poses a second in all


def mount_tmpfs(path: Path, size_mb: int) -> None:
    path.mkdir(parents=True, exist_ok=True)
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size_mb}m", "tmpfs", str(path)],
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        pytest.skip(
            f"cannot mount a {size_mb} MB tmpfs as ClickHouse's data dir (needs root "
            f"and CAP_SYS_ADMIN): {done.stderr.strip() or done.returncode}"
        )


def unmount(path: Path) -> None:
    for args in (["umount", str(path)], ["umount", "-l", str(path)]):  # -l: still busy
        if subprocess.run(args, capture_output=True).returncode == 0:
            return


@pytest.fixture(scope="module")
def browser(module_browser):
    """This module's browser ends with the module (see tests/ui/conftest.playwright_browser)."""
    return module_browser


@pytest.fixture(scope="module", params=["up", "serve"])
def stack(request, tmp_path_factory):
    """`up`: the ClickHouse server, the processors and the API apart (as `mapservice up`
    runs them); `serve`: processors and API in one process."""
    if not DIST.exists():
        pytest.fail("replay-ui is not built: run `make ui` first")
    data_dir = tmp_path_factory.mktemp(f"disk-full-{request.param}")
    clickhouse_dir = data_dir / "clickhouse"  # the chDB directory, in both topologies
    mount_tmpfs(clickhouse_dir, DISK_MB)
    apart = request.param == "up"
    stack = Stack(data_dir, mqtt="amqtt", apart=apart, extra_env=dict(TEST_UI_ENV))
    try:
        with stack.running(stack.start_brokers, stack.start_apart if apart else stack.start_server):
            yield stack
    finally:
        unmount(clickhouse_dir)


def processors_url(stack: Stack) -> str:
    """Where the processors' health endpoint (/readyz, /metrics) answers: their own port
    apart, the API's in one process."""
    return f"http://127.0.0.1:{stack.processors_health_port}" if stack.apart else stack.api_url


def processors_log(stack: Stack) -> str:
    return (stack.log_dir / ("processors.log" if stack.apart else "server.log")).read_text()


class Poses:
    """Publishes RATE_HZ poses a second per robot to Kafka from a thread; keeps the
    identity (robot, event time) of every pose Kafka acknowledged, and when."""

    def __init__(self, stack: Stack) -> None:
        self.settings = stack.settings()
        self.publisher = KafkaPublisher(self.settings, client_id="disk-full-test")
        self.acked: list[tuple[str, int, float]] = []  # robot, event time, acknowledged (monotonic)
        self.errors: list[Exception] = []
        self.first_ms = int(time.time() * 1000)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="disk-full-poses", daemon=True)

    def _run(self) -> None:
        step_ms, tick = 1000 // RATE_HZ, 0
        while not self._stop.is_set():
            ts = self.first_ms + tick * step_ms
            for robot in ROBOTS:
                event = make_envelope(
                    robot,
                    ts,
                    ts + 5,
                    PoseReported((tick % 100 / 10, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0), 50.0),
                )

                def done(err, key=(robot, ts)) -> None:
                    if err is None:
                        self.acked.append((*key, time.monotonic()))
                    else:
                        self.errors.append(err)

                self.publisher.publish(
                    self.settings.topic_pose_events, kafka_key(event), encode(event), done
                )
            self.publisher.poll(0)
            tick += 1
            time.sleep(step_ms / 1000)

    def __enter__(self) -> Poses:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(10)
        try:
            assert self.publisher.flush(30) == 0
        finally:
            # Left open, its producer dials the stopped broker from its threads for the
            # rest of the session.
            self.publisher.close()

    def acked_between(self, start: float, end: float) -> int:
        return sum(1 for *_, at in self.acked if start <= at <= end)


def get(url: str) -> tuple[int, dict]:
    reply = httpx.get(url, timeout=10)
    return reply.status_code, reply.json()


def until(what: str, predicate, timeout_s: float = 60, last=lambda: None):
    """Waits for `predicate()` to be truthy and returns it; on timeout the message has
    `last()` (what there was instead)."""
    deadline = time.monotonic() + timeout_s
    while not (result := predicate()):
        assert time.monotonic() < deadline, (
            f"timed out after {timeout_s:.0f} s waiting for: {what}; last: {last()}"
        )
        time.sleep(0.5)
    return result


def gauge(stack: Stack, name: str) -> float:
    """The processors' gauge `name`, where the alert rule reads it (their /metrics)."""
    text = httpx.get(f"{processors_url(stack)}/metrics", timeout=10).text
    (line,) = [ln for ln in text.splitlines() if ln.startswith(name + " ")]
    return float(line.split()[1])


class Filler:
    """A file that takes every byte left on the disk under `directory`, and keeps taking
    what ClickHouse frees meanwhile (a failed insert's temporary part removed, merged
    parts cleaned up) until `free()`: a full disk stays full, as a real one does. Filled
    once only, the bytes freed let small inserts succeed now and then, each success said
    "storing again", and readiness could stay true for the whole wait."""

    def __init__(self, directory: Path) -> None:
        self.path = directory / "filler"
        self._file = open(self.path, "ab", buffering=0)
        self._stop = threading.Event()
        self.top_ups = 0  # times freed space was taken again
        self._take()
        self._thread = threading.Thread(target=self._keep_full, name="disk-filler", daemon=True)
        self._thread.start()

    def _take(self) -> bool:
        """Writes until ENOSPC, in ever smaller steps down to a byte; whether it wrote."""
        wrote = False
        for size in (1 << 20, 4096, 1):
            block = b"\0" * size
            try:
                while True:
                    self._file.write(block)
                    wrote = True
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc
        return wrote

    def _keep_full(self) -> None:
        while not self._stop.wait(0.05):
            if self._take():
                self.top_ups += 1

    def free(self) -> None:
        self._stop.set()
        self._thread.join(10)
        self._file.close()
        self.path.unlink()


def test_a_full_disk_makes_it_unready_with_the_reason_and_it_recovers_losing_nothing(
    stack, page
) -> None:
    """Readiness false naming NOT_ENOUGH_SPACE, the failing gauge, the status and the UI's
    banner while the disk is full; ready again once space is freed, the banner gone; every
    acknowledged pose stored once."""
    api = stack.api_url
    until("ready", lambda: get(f"{api}/readyz")[0] == 200)
    page.goto(f"{api}/?live=1")
    banner = page.locator('[data-testid="history-banner"]')
    with Poses(stack) as poses:
        until(
            "poses stored",
            lambda: (
                len(stored_keys(stack, "pose", "df-", poses.first_ms, poses.first_ms + 600_000))
                >= 50
            ),
        )
        assert get(f"{api}/readyz")[0] == 200
        filler = Filler(stack.data_dir / "clickhouse")
        full_at = time.monotonic()

        _code, body = until(
            "/readyz to say the history is not stored",
            lambda: (r := get(f"{api}/readyz"))[0] == 503 and r,
            timeout_s=30,
            last=lambda: get(f"{api}/readyz"),
        )
        assert body["checks"]["history_store"] is False, body
        assert body["checks"]["clickhouse"] is True  # reads and SELECT 1 still work
        reason = body["reasons"]["history_store"]
        assert reason.startswith("inserts failing since ") and "NOT_ENOUGH_SPACE" in reason, reason
        assert "free disk space" in reason
        assert gauge(stack, "mapservice_history_insert_failing") == 1.0
        since = gauge(stack, "mapservice_history_insert_failing_since_timestamp_seconds")
        if stack.apart:  # the processors' own probe says it too; the server lives on
            code, own = get(f"{processors_url(stack)}/readyz")
            assert code == 503 and "NOT_ENOUGH_SPACE" in str(own), own
            assert stack.is_alive("clickhouse"), "the ClickHouse server died of the full disk"
        assert abs(since - time.time()) < 120
        status = get(f"{api}/api/v1/status")[1]["history"]
        assert status["storing"] is False and status["failing_since_ms"] == int(since * 1000)
        assert "NOT_ENOUGH_SPACE" in status["reason"]
        banner.wait_for(timeout=30_000)  # the page polls every 5 s
        since_utc = time.strftime("%H:%M:%S", time.gmtime(since))
        assert banner.inner_text().strip() == f"⚠ history not stored since {since_utc} UTC"
        assert "NOT_ENOUGH_SPACE" in banner.get_attribute("title")
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "disk-full-banner.png"))
        time.sleep(2)  # robots go on publishing: acknowledged, waiting in Kafka
        # Still refused after a while, not a single failure's blip.
        assert get(f"{api}/readyz")[0] == 503

        filler.free()
        freed_at = time.monotonic()
        until(
            "ready again after the space was freed",
            lambda: get(f"{api}/readyz")[0] == 200,
            timeout_s=60,
            # Which check stayed false, and what the processors logged last.
            last=lambda: (get(f"{api}/readyz"), processors_log(stack)[-3000:]),
        )
        recovered_s = time.monotonic() - freed_at
        # A part the full disk left broken can fail one more insert (CORRUPTED_DATA, "empty
        # marks file") before it is set aside: the gauge settles at 0 within seconds.
        until(
            "the failing gauge back at 0",
            lambda: gauge(stack, "mapservice_history_insert_failing") == 0.0,
            timeout_s=30,
            last=lambda: processors_log(stack)[-2000:],
        )
        assert get(f"{api}/api/v1/status")[1]["history"]["storing"] is True
        banner.wait_for(state="detached", timeout=30_000)
        server_log = processors_log(stack)
        assert "history not stored: inserts fail" in server_log  # once, when it began
        assert "history stored again" in server_log
        assert not page.errors  # type: ignore[attr-defined]
        assert all(proc.poll() is None for proc in stack.procs.values()), stack.procs
        time.sleep(1)  # some poses after the recovery too
    during = poses.acked_between(full_at, freed_at)
    assert during > 50, f"only {during} poses acknowledged while the disk was full"
    assert not poses.errors
    expected = collections.Counter((robot, ts) for robot, ts, _ in poses.acked)
    window = (poses.first_ms, max(ts for _, ts, _ in poses.acked) + 1)

    def all_stored():
        keys = stored_keys(stack, "pose", "df-", *window)
        return len(keys) >= len(expected) and keys

    stored = collections.Counter(until("every acknowledged pose stored", all_stored))
    duplicated = sorted(k for k, n in stored.items() if n > 1)
    lost = sorted(set(expected) - set(stored))
    assert not lost and not duplicated, (len(lost), lost[:5], len(duplicated), duplicated[:5])
    assert set(stored) == set(expected)
    print(
        f"acknowledged {len(expected)} ({during} while full), stored once {len(stored)}, "
        f"ready {recovered_s:.1f} s after the space was freed"
    )
