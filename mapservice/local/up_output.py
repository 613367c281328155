"""What `mapservice up` and `demo-history` print: on a terminal spinners, progress bars and
a table; to a file or a pipe (where those print nothing or are cut at 80 columns) log lines
and whole plain lines."""

from __future__ import annotations

import sys
import time
from contextlib import contextmanager

import structlog

log = structlog.get_logger("mapservice.up")


@contextmanager
def step(console, what: str):
    """A start-up step: a spinner on a terminal; else (output to a file or a pipe, where the
    spinner prints nothing) a log line when it begins and one when it is done."""
    if console.is_terminal:
        with console.status(what + "..."):
            yield
        return
    started = time.monotonic()
    log.info(what)
    yield
    log.info(what + ": done", seconds=round(time.monotonic() - started, 1))


def print_addresses(console, title: str, rows: list[tuple[str, str]]) -> None:
    """`up`'s address table, never cut: on a terminal a table whose values wrap (fold) at its
    width; else one plain `name  value` line per row, as long as it needs to be."""
    if not console.is_terminal:
        width = max(len(name) for name, _ in rows)
        sys.stdout.write(
            title + "\n" + "".join(f"  {name:<{width}}  {value}\n" for name, value in rows)
        )
        sys.stdout.flush()
        return
    from rich.table import Table

    table = Table(title=title, show_header=False)
    table.add_column(no_wrap=True)
    table.add_column(overflow="fold")
    for name, value in rows:
        table.add_row(name, value)
    console.print(table)


PROGRESS_LOG_S = 5.0


class ProgressLog:
    """Logs `what` and how far it got (0..1) at most every `every_s`, and once at the start."""

    def __init__(self, what: str, every_s: float, clock=time.monotonic) -> None:
        self.what, self.every_s, self.clock = what, every_s, clock
        self.started = clock()
        self.last: float | None = None

    def update(self, done: float) -> None:
        now = self.clock()
        if self.last is None or now - self.last >= self.every_s:
            self.last = now
            log.info(self.what, done_percent=round(100 * done), elapsed_s=round(now - self.started))
