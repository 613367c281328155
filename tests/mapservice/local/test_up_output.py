"""`up`'s output where it is not a terminal: whole lines, and progress as log lines."""

from __future__ import annotations

import io

import structlog
from rich.console import Console

from mapservice.local.up_output import ProgressLog, print_addresses, step


def test_the_address_table_to_a_file_is_never_cut(capsys):
    """A value far wider than 80 columns is printed whole, on one line with its name."""
    long_path = "/data/" + "a-very-long-directory-name/" * 8 + "secrets/analyst-password"
    print_addresses(
        Console(file=io.StringIO()),
        "mapservice is up",
        [("API", "http://127.0.0.1:8080"), ("SQL (analysts)", f"password in {long_path}")],
    )
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == "mapservice is up"
    assert any(line.strip() == f"SQL (analysts)  password in {long_path}" for line in lines)


def test_the_address_table_on_a_terminal_folds_instead_of_cutting():
    """On an 80-column terminal the long value wraps, and every character of it is shown."""
    long_path = "/data/" + "a-very-long-directory-name/" * 8 + "secrets/analyst-password"
    out = io.StringIO()
    print_addresses(
        Console(file=out, force_terminal=True, width=80, color_system=None),
        "mapservice is up",
        [("SQL (analysts)", long_path)],
    )
    text = out.getvalue()
    assert "…" not in text
    cells = "".join(
        line.split("│")[2].strip() for line in text.splitlines() if line.count("│") == 3
    )
    assert cells == long_path


def test_progress_is_logged_at_the_start_and_then_at_most_every_period():
    """Updates every second for 12 s with a 5 s period: lines at 0, 5 and 10 s."""
    now = [0.0]
    progress = ProgressLog("simulating", 5.0, clock=lambda: now[0])
    with structlog.testing.capture_logs() as logs:
        for second in range(13):
            now[0] = float(second)
            progress.update(second / 12)
    assert [(e["event"], e["elapsed_s"], e["done_percent"]) for e in logs] == [
        ("simulating", 0, 0),
        ("simulating", 5, 42),
        ("simulating", 10, 83),
    ]


def test_a_start_step_not_on_a_terminal_logs_its_start_and_end():
    with structlog.testing.capture_logs() as logs:
        with step(Console(file=io.StringIO()), "starting the gateway"):
            pass
    assert [e["event"] for e in logs] == ["starting the gateway", "starting the gateway: done"]
