"""The SQL engine over a ClickHouse server's HTTP interface (the split deployment).

Statements go to the server as they came, with the service's ClickHouse credential; a
read-only request carries its allowed settings, then its limits and `readonly=1`, as
settings of that one request, which the server enforces. An analyst's own statement goes
with the analysts' ClickHouse credential where one is configured (`analyst_auth`): a user
the server itself holds read-only, its limits constant constraints of its profile
(infra/k8s/platform/clickhouse.yaml; `mapservice clickhouse-server` knows the analyst
too), so the server refuses what this process might have let through."""

from __future__ import annotations

from urllib.parse import urlsplit

import httpx

from mapservice.sql.engine import SqlError, SqlRequest, SqlResult, output_format
from mapservice.sql.settings_policy import apply_read_only

MAX_URL_PARAMS_BYTES = 4096


class ServerEngine:
    """`SqlEngine` over `http(s)://host:port` (a path after the port is the server's proxy path)."""

    def __init__(
        self,
        dsn: str,
        username: str = "default",
        password: str = "",
        read_only_settings: dict[str, str] | None = None,
        timeout_s: float = 300.0,
        verify: bool | str = True,
        analyst_auth: tuple[str, str] | None = None,
    ):
        parts = urlsplit(dsn)
        self.base_url = f"{parts.scheme}://{parts.hostname}:{parts.port or 8123}{parts.path}"
        self.read_only_settings = dict(read_only_settings or {})
        self._analyst_headers = (
            {"X-ClickHouse-User": analyst_auth[0], "X-ClickHouse-Key": analyst_auth[1]}
            if analyst_auth
            else None
        )
        self._http = httpx.Client(
            timeout=timeout_s,
            verify=verify,
            headers={
                "X-ClickHouse-User": parts.username or username,
                "X-ClickHouse-Key": parts.password or password,
            },
        )

    def _params(self, request: SqlRequest) -> dict[str, str]:
        params = {f"param_{k}": v for k, v in request.params.items()}
        if request.read_only:
            params.update(apply_read_only(request.settings, self.read_only_settings))
        else:
            params.update(request.settings)
        if request.database:
            params["database"] = request.database
        params["default_format"] = request.default_format
        return params

    def _post(
        self,
        params: dict[str, str],
        body: bytes | None,
        form: dict[str, str] | None = None,
        headers: dict[str, str] | None = None,
    ) -> httpx.Response:
        try:
            if form is not None:
                reply = self._http.post(
                    self.base_url,
                    params=params,
                    files={k: (None, v) for k, v in form.items()},
                    headers=headers,
                )
            else:
                reply = self._http.post(self.base_url, params=params, content=body, headers=headers)
        except httpx.HTTPError as exc:
            raise SqlError(f"ClickHouse server {self.base_url} unreachable: {exc}", 210) from exc
        if reply.status_code != 200:
            code = reply.headers.get("X-ClickHouse-Exception-Code")
            raise SqlError(reply.text.strip(), int(code) if code and code.isdigit() else None)
        return reply

    def execute(self, request: SqlRequest) -> SqlResult:
        params = self._params(request)
        headers = self._analyst_headers if request.analyst else None
        bound = {k: params.pop(k) for k in list(params) if k.startswith("param_")}
        if sum(len(k) + len(v) for k, v in bound.items()) > MAX_URL_PARAMS_BYTES:
            # Long parameters as multipart fields, as clickhouse-connect sends them: a URL
            # has a limit (uvicorn's request line: 16 KB, 1 MB on a ClickHouse server).
            reply = self._post(params, None, form={"query": request.sql, **bound}, headers=headers)
        else:
            reply = self._post({**params, **bound}, request.sql.encode(), headers=headers)
        return SqlResult(
            reply.content,
            reply.headers.get(
                "X-ClickHouse-Format", output_format(request.sql, request.default_format)
            ),
        )

    def insert(self, target: str, fmt: str, data: bytes, request: SqlRequest) -> SqlResult:
        params = self._params(request)
        params["query"] = f"INSERT INTO {target} FORMAT {fmt}"
        self._post(params, data)
        return SqlResult(b"", fmt)

    def ping(self) -> bool:
        try:
            return self._http.get(self.base_url.rstrip("/") + "/ping", timeout=5).status_code == 200
        except httpx.HTTPError:
            return False

    def close(self) -> None:
        self._http.close()
