"""What every process of the service reads first: its mode, state directory and logging."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, Field


class ProcessSettings(BaseModel):
    """The mode (local or production), embedded mode's state and the log's level and format."""

    mode: Literal["local", "production"] = Field(
        "local", description="`production` refuses default secrets."
    )
    data_dir: Path = Field(Path(".mapservice-data"), description="Embedded mode's state.")
    log_level: str = "INFO"
    log_format: Literal["console", "json"] = "console"
