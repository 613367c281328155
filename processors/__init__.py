"""The processors (a faust-streaming app): the history sink into ClickHouse, live views,
conflicts, snapshots and the live stream to the API processes.

May import: `mapservice.core`, `adapters`, `runtime`, `settings`; never the API or gateway.
"""
