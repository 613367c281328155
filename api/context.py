"""What the API's routes and middlewares are given, typed and in one place: the settings,
the clock, the store by role, the event publisher, the live hub, the health checks and the
per-app caches and state. `create_app` (api/app.py) builds it once; routes ask for one part each
through the dependencies of api/deps.py, never for the context or the store as a whole.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from starlette.applications import Starlette

from mapservice.core.ports import Clock, EventPublisher
from mapservice.core.store_roles import StoreRoles
from mapservice.settings import Settings

from .annotation_state import RecentEdits
from .content_cache import ContentCache
from .credentials import Credentials
from .live_hub import LiveHub
from .posted_meta import PostedMeta

Check = Callable[[], bool]


@dataclass(frozen=True, eq=False)
class ApiContext:
    """One API app's collaborators. `roles` None: an app built only for its routes (the
    OpenAPI document), which serves no store read; `publisher` None: the 2019 REST and
    operator writes answer 503; `live` None: /api/v1/live has no stream to serve;
    `history_status` None: this process does not store the history."""

    settings: Settings
    clock: Clock
    roles: StoreRoles | None
    access: Credentials
    # Exports run in threads of their own, as many as the exports' pool admits
    # (api/admission.py, api/streaming.py): they never take the reads' threads.
    export_executor: ThreadPoolExecutor
    publisher: EventPublisher | None = None
    live: LiveHub | None = None
    readiness: Mapping[str, Check] = field(default_factory=dict)
    liveness: Mapping[str, Check] = field(default_factory=dict)
    advisory: Mapping[str, Check] = field(default_factory=dict)
    history_status: Callable[[], dict[str, Any]] | None = None
    content_cache: ContentCache = field(default_factory=ContentCache)
    recent_edits: RecentEdits = field(default_factory=RecentEdits)
    posted_meta: PostedMeta = field(default_factory=PostedMeta)


def context_of(app: Starlette) -> ApiContext:
    """The context `create_app` put on `app`: the one place it is read from the app."""
    context: ApiContext = app.state.context
    return context
