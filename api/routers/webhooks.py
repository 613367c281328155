"""Webhooks for the incident alerts: an operator registers a URL (and which incident kinds it
wants), and every processors replica POSTs each incident finding there, signed
(processors/webhook_delivery.py; docs/history.md#incident-alerts says how a receiver checks
it). Everything here needs the `operator` scope (an operator token or the admin's): a
webhook's URL and state are the plant's integration, and its secret signs what the plant's
systems trust.

The registry is kept in the store; the processors re-read it every
MAPSERVICE_WEBHOOK_REGISTRY_POLL_S, so a new, removed or resumed webhook takes effect within
that long, and report each webhook's deliveries there, which the list shows. A webhook's
secret is derived from the service's signing key (mapservice/core/webhooks.py:
`derived_secret`), shown when it is registered and on request, never stored.
"""

from __future__ import annotations

import secrets
from typing import Annotated, Literal

import msgspec
from fastapi import APIRouter, Depends, HTTPException, Path, Response
from pydantic import BaseModel, Field

from mapservice.adapters.webhook_destinations import Unresolved, destination_policy
from mapservice.adapters.webhook_urls import URL_MAX_CHARS, check_url
from mapservice.core.ports import WebhookRegistry
from mapservice.core.webhook_registry import (
    WEBHOOK_ID,
    RegisteredWebhook,
    WebhookState,
    combined_state,
)
from mapservice.core.webhooks import derived_secret
from mapservice.settings import Settings

from ..access import OPERATE
from ..deps import ClockDep, OperatorCaller, SettingsDep, WebhooksDep
from .incidents import Kind

router = APIRouter(prefix="/api/v1/webhooks", tags=["webhooks"])

IdPath = Annotated[
    str, Path(description="The webhook's id (wh- and 16 hex digits)", pattern=WEBHOOK_ID.pattern)
]


class WebhookIn(BaseModel):
    """Where to POST the incident alerts (http or https, no credentials in it: each delivery
    is signed), and which incident kinds (none: all)."""

    url: str = Field(max_length=URL_MAX_CHARS)
    kinds: list[Kind] = Field(default_factory=list, max_length=10)


class WebhookOut(BaseModel):
    id: str
    url: str
    kinds: list[str]  # empty: every kind
    createdBy: str  # the credential's name, never the token
    created_ms: int
    resumed_ms: int | None  # the latest resume asked for
    state: Literal["active", "paused"]  # paused: a delivery failed every try; resume it
    pausedReason: str
    lastTry_ms: int | None  # when the last try ended (None: none yet)
    lastResult: str  # that try's result: delivered, or its error
    lastError: str  # the last failed try's error
    delivered: int  # counts since each processors replica started
    failedTries: int
    dropped: int  # dropped unsent: the queues' bound
    queued: int  # waiting to be sent
    replicas: int  # processors replicas that reported it lately (0: none yet)


class WebhookList(BaseModel):
    webhooks: list[WebhookOut]
    max: int  # MAPSERVICE_WEBHOOKS_MAX


class WebhookSecret(BaseModel):
    id: str
    secret: str  # HMAC-SHA256 key of its deliveries' X-Mapservice-Signature


class WebhookCreated(WebhookOut):
    secret: str  # keep it where the receiver checks signatures; GET .../secret shows it again


def signing_key(settings: Settings) -> str:
    """The service's signing key, or a 503 saying how to set one."""
    key = settings.webhook_signing_key.get_secret_value()
    if not key:
        raise HTTPException(
            503,
            "webhooks need MAPSERVICE_WEBHOOK_SIGNING_KEY (the key their secrets are derived "
            "from, at least 32 characters: openssl rand -hex 32), the same for the API and "
            "the processors",
        )
    return key


def _out(webhook: RegisteredWebhook, state: WebhookState) -> WebhookOut:
    return WebhookOut(
        id=webhook.webhook_id,
        url=webhook.url,
        kinds=list(webhook.kinds),
        createdBy=webhook.created_by,
        created_ms=webhook.created_ms,
        resumed_ms=webhook.resumed_ms or None,
        state=state.state,
        pausedReason=state.paused_reason,
        lastTry_ms=state.last_try_ms,
        lastResult=state.last_result,
        lastError=state.last_error,
        delivered=state.delivered,
        failedTries=state.failed_tries,
        dropped=state.dropped,
        queued=state.queued,
        replicas=state.replicas,
    )


def _states(
    store: WebhookRegistry, webhooks: list[RegisteredWebhook], settings: Settings, now_ms: int
) -> list[WebhookOut]:
    """Each webhook with its replicas' fresh reports folded: a report older than three
    polls (at least a minute) is of a replica gone."""
    fresh_ms = int(max(60.0, 3 * settings.webhook_registry_poll_s) * 1000)
    reports = store.webhook_reports()
    return [
        _out(
            w,
            combined_state([r for r in reports if r.webhook_id == w.webhook_id], now_ms, fresh_ms),
        )
        for w in webhooks
    ]


def _registered(store: WebhookRegistry, webhook_id: str) -> RegisteredWebhook:
    for w in store.webhooks():
        if w.webhook_id == webhook_id:
            return w
    raise HTTPException(404, f"no webhook {webhook_id!r} is registered (GET /api/v1/webhooks)")


@router.post("", operation_id="registerWebhook", response_model=WebhookCreated, status_code=201)
def register_webhook(
    body: WebhookIn,
    caller: OperatorCaller,
    store: WebhooksDep,
    settings: SettingsDep,
    clock: ClockDep,
) -> WebhookCreated:
    """Registers a webhook: every incident finding (new, changed, ended, retracted) of its
    kinds is POSTed to it, signed with the secret this answer holds. The processors take it
    up within MAPSERVICE_WEBHOOK_REGISTRY_POLL_S."""
    key = signing_key(settings)
    try:
        url = check_url(body.url)
        # Where it resolves now (a thread of the pool: this route is sync); each delivery
        # checks again where it connects. A name this API cannot resolve is taken: the
        # processors may see another DNS, and the webhook's state will say if they cannot.
        destination_policy(settings).check_url(url)
    except Unresolved:
        pass
    except ValueError as exc:
        raise HTTPException(422, f"url: {exc}") from None
    registered = store.webhooks()
    if len(registered) >= settings.webhooks_max:
        raise HTTPException(
            409,
            f"{len(registered)} webhooks are registered, the most MAPSERVICE_WEBHOOKS_MAX "
            "allows; remove one first (DELETE /api/v1/webhooks/{id})",
        )
    now = clock.now_ms()
    webhook = RegisteredWebhook(
        webhook_id=f"wh-{secrets.token_hex(8)}",
        url=url,
        kinds=tuple(sorted(set(body.kinds))),
        created_ms=now,
        created_by=caller.name,
    )
    store.save_webhook(webhook, now)
    out = _out(webhook, combined_state([], now, 0))
    return WebhookCreated(**out.model_dump(), secret=derived_secret(key, webhook.webhook_id))


@router.get(
    "", operation_id="listWebhooks", response_model=WebhookList, dependencies=[Depends(OPERATE)]
)
def list_webhooks(store: WebhooksDep, settings: SettingsDep, clock: ClockDep) -> WebhookList:
    """The registered webhooks, oldest first, each with how its deliveries fare: active or
    paused (and why), the last try, the counts, over the processors replicas."""
    webhooks = _states(store, store.webhooks(), settings, clock.now_ms())
    return WebhookList(webhooks=webhooks, max=settings.webhooks_max)


@router.get(
    "/{webhook_id}/secret",
    operation_id="showWebhookSecret",
    response_model=WebhookSecret,
    dependencies=[Depends(OPERATE)],
)
def show_webhook_secret(
    webhook_id: IdPath, store: WebhooksDep, settings: SettingsDep
) -> WebhookSecret:
    """The webhook's secret again (derived, never stored: the same as when it was
    registered, while MAPSERVICE_WEBHOOK_SIGNING_KEY stays)."""
    key = signing_key(settings)
    webhook = _registered(store, webhook_id)
    return WebhookSecret(id=webhook.webhook_id, secret=derived_secret(key, webhook.webhook_id))


@router.delete(
    "/{webhook_id}",
    operation_id="removeWebhook",
    status_code=204,
    response_class=Response,
    dependencies=[Depends(OPERATE)],
)
def remove_webhook(webhook_id: IdPath, store: WebhooksDep, clock: ClockDep) -> Response:
    """Removes the webhook: the processors stop delivering to it (what they had queued for
    it is dropped) within MAPSERVICE_WEBHOOK_REGISTRY_POLL_S."""
    _registered(store, webhook_id)
    store.remove_webhook(webhook_id, clock.now_ms())
    return Response(status_code=204)


@router.post(
    "/{webhook_id}/resume",
    operation_id="resumeWebhook",
    response_model=WebhookOut,
    status_code=202,
    dependencies=[Depends(OPERATE)],
)
def resume_webhook(
    webhook_id: IdPath, store: WebhooksDep, settings: SettingsDep, clock: ClockDep
) -> WebhookOut:
    """Resumes a paused webhook once its receiver is fixed: the processors send what waited
    for it, oldest first, within MAPSERVICE_WEBHOOK_REGISTRY_POLL_S (202: asked; the list
    shows when it is active again). Send `{}` as the JSON body."""
    webhook = _registered(store, webhook_id)
    now = clock.now_ms()
    resumed = msgspec.structs.replace(webhook, resumed_ms=now)
    store.save_webhook(resumed, now)
    (out,) = _states(store, [resumed], settings, now)
    return out
