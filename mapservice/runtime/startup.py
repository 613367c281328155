"""What every process does first: read its settings, refuse bad ones clearly, configure logs."""

from __future__ import annotations

import sys

from mapservice.runtime.logs import configure
from mapservice.settings import Settings


def settings_for(component: str) -> Settings:
    """The process's settings, with logs configured under `component`; exits with the
    validation message (which names the variable to fix) when the environment is wrong."""
    try:
        settings = Settings()
    except ValueError as exc:
        sys.exit(f"configuration error: {exc}")
    configure(settings.log_level, settings.log_format, component)
    return settings
