"""The HTTP API (FastAPI): the floor at any instant, replay windows, the 2019 REST contract,
exports, the analysts' SQL endpoint and the live WebSocket (`app.create_app`).

One router per resource in `routers/`; `deps` hands them the store, publisher and clock.
May import: `mapservice.core`, `adapters`, `sql`, `runtime`, `settings`; never the
processors or the gateway (an API process loads only what it runs).
"""
