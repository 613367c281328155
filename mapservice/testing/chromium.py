"""Debian's Chromium under Playwright (no browser download): UI browser tests and `bench ui`."""

from __future__ import annotations

import shutil
from pathlib import Path

from playwright.sync_api import Browser, Playwright

ARGS = ["--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"]


def chromium_path() -> str | None:
    for p in ("/usr/bin/chromium", "/usr/lib/chromium/chromium"):
        if Path(p).exists():
            return p
    return shutil.which("chromium")


def launch(pw: Playwright) -> Browser:
    exe = chromium_path()
    if exe is None:
        raise SystemExit(
            "Chromium is missing: apt-get install chromium (`make system-deps` as root)"
        )
    return pw.chromium.launch(executable_path=exe, headless=True, args=ARGS)
