"""What the ingest tests share."""

from __future__ import annotations

import logging

import pytest
import structlog


@pytest.fixture(scope="module")
def quiet_rejection_logs():
    """Only warnings and above while a module runs: a fuzzer's thousands of rejections
    would otherwise each log an info line."""
    before = structlog.get_config()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(logging.WARNING))
    yield
    structlog.configure(**before)
