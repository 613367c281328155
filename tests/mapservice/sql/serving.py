"""Serving an ASGI app from a test (a ClickHouse HTTP app, the API): uvicorn in a thread on a
free port."""

from __future__ import annotations

import threading
import time

import uvicorn

from mapservice.local import embedded


class ServedApp:
    def __init__(self, app, config: uvicorn.Config | None = None):
        if config is None:
            config = uvicorn.Config(
                app,
                host="127.0.0.1",
                port=embedded.free_port(),
                log_config=None,
                log_level=None,
                access_log=False,
            )
        self.port = config.port
        self.url = f"http://127.0.0.1:{self.port}"
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self) -> ServedApp:
        self.thread.start()
        deadline = time.monotonic() + 20
        while not self.server.started:
            if time.monotonic() > deadline or not self.thread.is_alive():
                raise RuntimeError("the test's HTTP server did not start")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=10)


class ServedApi(ServedApp):
    """ServedApp with the API's own uvicorn configuration (`serve`'s protocol settings and
    access log), on `settings.api_port`. (A uvicorn.Config configures logging as it is
    made: only the API's own is made here, so its access log stays as `serve` has it.)"""

    def __init__(self, app, settings):
        from mapservice.api.composition import api_server_config

        super().__init__(app, api_server_config(app, settings))
