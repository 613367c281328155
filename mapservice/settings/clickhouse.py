"""ClickHouse: the history store's connection and schema, and the analysts' read-only SQL."""

from __future__ import annotations

from pathlib import Path

from pydantic import BaseModel, Field, SecretStr

from mapservice.settings.credentials import DEFAULT_CLICKHOUSE_PASSWORD


class ClickHouseSettings(BaseModel):
    """Where the history is stored (chDB or a server), and the analysts' limits on it."""

    # chdb:///dir (embedded) or http(s)://host:8123
    clickhouse_dsn: str = Field("", description="Empty means chdb:///<data_dir>/clickhouse.")
    clickhouse_database: str = "mapservice"
    clickhouse_username: str = "default"
    clickhouse_password: SecretStr = SecretStr(DEFAULT_CLICKHOUSE_PASSWORD)
    clickhouse_ca_file: Path | None = Field(
        None,
        description=(
            "CA bundle (PEM) that signs the ClickHouse server's certificate, for an https:// DSN; "
            "empty: the system's CAs."
        ),
    )
    clickhouse_cert_file: Path | None = Field(
        None,
        description=(
            "Client certificate (PEM) presented to ClickHouse over https (mutual TLS); needs "
            "MAPSERVICE_CLICKHOUSE_KEY_FILE."
        ),
    )
    clickhouse_key_file: Path | None = Field(
        None, description=("Private key (PEM, unencrypted) of MAPSERVICE_CLICKHOUSE_CERT_FILE.")
    )
    clickhouse_timeout_s: float = Field(
        60.0,
        gt=0,
        description=(
            "A request to a ClickHouse server that has not answered in this long fails and is "
            "retried (clickhouse-connect's own default, 300 s, let one hung insert stall the "
            "pipeline); not used by embedded chDB."
        ),
    )
    chdb_merge_nice: int = Field(
        19,
        ge=0,
        le=19,
        description=(
            "Embedded chDB only: the nice value (0-19) of ClickHouse's merge threads in the "
            "process holding the chDB directory, so that merges use idle CPU and give way to "
            "the inserts (0: the process's own). A ClickHouse server has its own setting: "
            "os_threads_nice_value_merge_mutate."
        ),
    )
    clickhouse_cluster: str = Field(
        "",
        description=(
            "A ClickHouse cluster name: schema statements run ON CLUSTER and tables are "
            "Replicated*MergeTree (one shard, N replicas). Empty: one server or chDB."
        ),
    )
    migrate_on_start: bool | None = Field(
        None,
        description=(
            "Apply schema migrations when a component starts. Empty: yes in local mode; no in "
            "production mode, where `mapservice migrate` runs once per release (a Job) and the "
            "components wait for the schema."
        ),
    )

    clickhouse_analyst_username: str = Field(
        "",
        description=(
            "The ClickHouse server's read-only user for analysts' statements (readonly and "
            "the limits constant in its profile). Empty: in local mode the analyst's own "
            "credential (mapservice clickhouse-server knows it), else the service's user "
            "with readonly=1 and the limits as settings of each request."
        ),
    )
    clickhouse_analyst_password: SecretStr = Field(
        SecretStr(""), description="Its password (secret)."
    )

    # Analysts: read-only SQL over the ClickHouse HTTP protocol at the API's /clickhouse
    analyst_username: str = Field("analyst", description="The read-only SQL user.")
    analyst_password: SecretStr = Field(
        SecretStr(""),
        description=(
            "Its password. Empty: generated on first start in local mode (DATA_DIR/secrets/"
            "analyst-password); analyst SQL is off in production mode."
        ),
    )
    analyst_max_execution_s: int = Field(30, ge=1, le=3600, description="Time limit per statement.")
    analyst_max_result_rows: int = Field(1_000_000, ge=1, description="Row limit per result.")
    analyst_max_memory_bytes: int = Field(
        2 * 1024**3,
        ge=64 * 1024**2,
        description=(
            "Memory limit per statement (at most ANALYST_MAX_MEMORY_TOTAL_BYTES / "
            "ANALYST_MAX_CONCURRENT_QUERIES)."
        ),
    )
    analyst_max_memory_total_bytes: int = Field(
        2 * 1024**3,
        ge=64 * 1024**2,
        description=(
            "Memory of all analysts' statements together: each runs with at most this divided "
            "by ANALYST_MAX_CONCURRENT_QUERIES."
        ),
    )
    analyst_max_concurrent_queries: int = Field(
        2,
        ge=1,
        le=64,
        description=(
            "Analysts' statements running at once, on threads of their own (not the API's)."
        ),
    )
    analyst_max_queued_queries: int = Field(
        8,
        ge=0,
        le=1000,
        description=(
            "Analysts' statements waiting for a thread; beyond them: HTTP 503 'too many "
            "queries' with Retry-After."
        ),
    )
    analyst_queue_timeout_s: float = Field(
        5.0,
        gt=0,
        le=600,
        description=("How long a waiting analyst statement waits for a thread before its 503."),
    )
    analyst_max_threads: int = Field(
        1,
        ge=1,
        le=64,
        description=(
            "Threads one analyst statement may use (ClickHouse max_threads): analysts together "
            "use at most ANALYST_MAX_CONCURRENT_QUERIES x this many cores."
        ),
    )

    def clickhouse_tls(self) -> dict[str, str]:
        """clickhouse-connect's TLS arguments (`get_client(**...)`) for an https:// DSN."""
        conf: dict[str, str] = {}
        if self.clickhouse_ca_file:
            conf["ca_cert"] = str(self.clickhouse_ca_file)
        if self.clickhouse_cert_file and self.clickhouse_key_file:
            conf["client_cert"] = str(self.clickhouse_cert_file)
            conf["client_cert_key"] = str(self.clickhouse_key_file)
        return conf
