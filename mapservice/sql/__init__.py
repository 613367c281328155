"""SQL access to the history for people and for the split deployment.

- `engine`: the port (`SqlEngine`, `SqlRequest`, `SqlError`) every engine adapter serves;
- `chdb_engine`: runs statements on the embedded chDB of this process;
- `server_engine`: forwards them to a ClickHouse server over its HTTP interface;
- `read_only`: what an analyst's statement may be, and the limits it runs under;
- `allow_list`: the functions, table functions and tables analysts may use;
- `settings_policy`: the settings a read-only user may send, by any channel, and the
  order the engines apply them in (the request's, the limits, `readonly = 1` last);
- `http_protocol`: the ClickHouse HTTP interface in front of an engine, so
  clickhouse-connect, Grafana's ClickHouse data source or curl work unchanged;
- `credentials`: the analyst credential (generated in local mode).

May depend on: `mapservice.settings`; never on the processors, the API or the gateway.
"""
