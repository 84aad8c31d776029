"""The DuckDB catalog: the single point of truth for what the warehouse holds.

One process writes (the registrar, inside the flow); readers open it read-only. A unit of
work is done exactly when its key is in `stage_runs`; its shards are visible exactly when
they are in `shards`. Files the catalog does not know are ignored and cleaned up.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import duckdb
import pyarrow as pa

from schemas.tables import CATALOG_DDL, DERIVED_VIEWS, SHARD_TABLES
from schemas.version import SCHEMA_VERSION
from warehouse.shard_writer import ShardFile

LOCK_WAIT_S = 60.0


class CatalogMissing(FileNotFoundError):
    pass


class CatalogVersionError(RuntimeError):
    """The warehouse was written by another layout version; nothing is touched."""


def _is_lock_error(exc: Exception) -> bool:
    return "lock" in str(exc).lower()


class Catalog:
    def __init__(self, path: Path):
        self.path = path
        self.warehouse = path.parent

    @contextmanager
    def connect(self, read_only: bool = False) -> Iterator[duckdb.DuckDBPyConnection]:
        """Open briefly and close: DuckDB lets one process write, so nobody holds it for long."""
        if read_only and not self.path.exists():
            raise CatalogMissing(f"no warehouse catalog at {self.path} (run `sim2act run` first)")
        deadline = time.monotonic() + LOCK_WAIT_S
        while True:
            try:
                con = duckdb.connect(str(self.path), read_only=read_only)
                break
            except duckdb.IOException as exc:
                if not _is_lock_error(exc) or time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        try:
            yield con
        finally:
            con.close()

    # -- writer side -----------------------------------------------------------------------

    def initialise(self) -> None:
        self.check_version()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self.connect() as con:
            con.execute(CATALOG_DDL)
            con.execute(
                "INSERT INTO catalog_meta VALUES ('schema_version', ?) ON CONFLICT DO NOTHING", [str(SCHEMA_VERSION)]
            )
            for name, schema in SHARD_TABLES.items():
                con.register("empty_shard", pa.Table.from_batches([], schema=schema))
                con.execute(f"CREATE TABLE IF NOT EXISTS _empty_{name} AS SELECT * FROM empty_shard")
                con.unregister("empty_shard")
            self._refresh_views(con)

    def check_version(self) -> None:
        """Refuse a warehouse of another layout version, before any work (no-op if none exists)."""
        if not self.path.exists():
            return
        with self.connect(read_only=True) as con:
            if not con.execute("SELECT 1 FROM duckdb_tables() WHERE table_name = 'catalog_meta'").fetchone():
                return  # a first initialise that did not finish
            stamped = con.execute("SELECT value FROM catalog_meta WHERE key = 'schema_version'").fetchone()
        if stamped is not None and int(stamped[0]) != SCHEMA_VERSION:
            raise CatalogVersionError(
                f"the warehouse at {self.warehouse} has layout version {stamped[0]}, this sim2act writes "
                f"{SCHEMA_VERSION}: use a new --workspace (the old one stays readable with `sim2act sql`)"
            )

    def is_registered(self, unit_key: str) -> bool:
        if not self.path.exists():
            return False
        with self.connect(read_only=True) as con:
            return con.execute("SELECT 1 FROM stage_runs WHERE unit_key = ?", [unit_key]).fetchone() is not None

    def registered_keys(self, keys: Sequence[str]) -> set[str]:
        if not keys or not self.path.exists():
            return set()
        with self.connect(read_only=True) as con:
            rows = con.execute("SELECT unit_key FROM stage_runs WHERE list_contains(?, unit_key)", [list(keys)])
            return {row[0] for row in rows.fetchall()}

    def register_unit(
        self,
        *,
        unit_key: str,
        stage: str,
        campaign: str,
        iteration: int,
        summary: Mapping[str, Any],
        wall_s: float = 0.0,
        shards: Sequence[ShardFile] = (),
        rows: Mapping[str, Sequence[Mapping[str, Any]]] | None = None,
    ) -> bool:
        """Commit one finished unit: its stage_runs row, its shards and its catalog rows, atomically.

        Registering a key twice is a no-op and returns False.
        """
        with self.connect() as con:
            con.execute("BEGIN TRANSACTION")
            try:
                if con.execute("SELECT 1 FROM stage_runs WHERE unit_key = ?", [unit_key]).fetchone():
                    con.execute("ROLLBACK")
                    return False
                con.execute(
                    "INSERT INTO stage_runs VALUES (?, ?, ?, ?, ?, ?, ?)",
                    [unit_key, stage, campaign, iteration, datetime.now(timezone.utc), wall_s, json.dumps(summary)],
                )
                for shard in shards:
                    con.execute(
                        "INSERT INTO shards VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                        [
                            shard.path.relative_to(self.warehouse).as_posix(),
                            shard.table,
                            unit_key,
                            campaign,
                            iteration,
                            shard.num_rows,
                            shard.num_bytes,
                            shard.sha256,
                            SCHEMA_VERSION,
                        ],
                    )
                for table, table_rows in (rows or {}).items():
                    for row in table_rows:
                        columns = ", ".join(row)
                        marks = ", ".join("?" for _ in row)
                        con.execute(f"INSERT INTO {table} ({columns}) VALUES ({marks})", list(row.values()))
                if shards:
                    self._refresh_views(con)
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise
        return True

    def _refresh_views(self, con: duckdb.DuckDBPyConnection) -> None:
        """Views over exactly the registered shards: unregistered files are invisible."""
        for name in SHARD_TABLES:
            paths = [
                (self.warehouse / row[0]).as_posix()
                for row in con.execute(
                    "SELECT path FROM shards WHERE table_name = ? ORDER BY path", [name]
                ).fetchall()
            ]
            source = f"read_parquet({paths!r})" if paths else f"_empty_{name}"
            con.execute(f"CREATE OR REPLACE VIEW {name} AS SELECT * FROM {source}")
        for name, query in DERIVED_VIEWS.items():
            con.execute(f"CREATE OR REPLACE VIEW {name} AS {query}")

    def clean_orphans(self) -> list[Path]:
        """Delete shard files (and temporaries) that no catalog row names: leftovers of a killed run."""
        shards_root = self.warehouse / "shards"
        if not shards_root.exists():
            return []
        known: set[str] = set()
        if self.path.exists():
            with self.connect(read_only=True) as con:
                known = {row[0] for row in con.execute("SELECT path FROM shards").fetchall()}
        removed = []
        for path in shards_root.rglob("*"):
            if path.is_file() and path.relative_to(self.warehouse).as_posix() not in known:
                path.unlink()
                removed.append(path)
        return removed

    # -- reader side -----------------------------------------------------------------------

    def query(self, sql: str, params: Sequence[Any] = ()) -> list[tuple]:
        with self.connect(read_only=True) as con:
            return con.execute(sql, list(params)).fetchall()

    def query_arrow(self, sql: str, params: Sequence[Any] = ()) -> pa.Table:
        with self.connect(read_only=True) as con:
            return con.execute(sql, list(params)).to_arrow_table()

    def shard_paths(self, table: str, where: str = "TRUE", params: Sequence[Any] = ()) -> list[tuple[Path, str]]:
        rows = self.query(
            f"SELECT path, sha256 FROM shards WHERE table_name = ? AND ({where}) ORDER BY path", [table, *params]
        )
        return [(self.warehouse / path, sha) for path, sha in rows]
