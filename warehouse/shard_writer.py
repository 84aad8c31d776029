"""Immutable Parquet shards: checked against schemas.tables, written to a temporary name and
moved into place atomically, never over a different file."""

from __future__ import annotations

import errno
import hashlib
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from schemas.errors import Sim2ActError
from schemas.tables import SHARD_TABLES
from schemas.version import SCHEMA_VERSION
from warehouse.store import ShardConflict, ShardStore, ShardStoreRefused, ShardStoreUnreachable, write_new_file
from warehouse.store import sha256_of as store_sha256_of

__all__ = ["ShardConflict", "ShardFile", "SchemaMismatch", "ShardUnreadable", "DiskFull", "write_shard",
           "read_shard", "read_shard_rows", "inspect_shard", "check_schema", "sha256_of"]

# Rows per Parquet row group: DuckDB scans row groups in parallel and is 5-10x slower per row
# below ~5K rows; a shard of a few episodes is a single group.
ROW_GROUP_ROWS = 100_000
# zstd level 3 over raw frames: ~2 KB per rendered 84x84 frame (level 1: ~2.9 KB) and faster to
# decode, for a compression cost that rollouts never notice.
ZSTD_LEVEL = 3


class SchemaMismatch(ValueError):
    """A shard's columns differ from the declared schema; the message names the column."""


class ShardUnreadable(ValueError):
    """Not a whole Parquet file: truncated, corrupt, or gone."""


class DiskFull(Sim2ActError, OSError):
    """No space left on the device a shard is written to; the message is one line naming the
    shard, its unit and what to do. An OSError, so a worker pool hands it back as itself."""


@dataclass(frozen=True)
class ShardFile:
    table: str
    path: Path
    num_rows: int
    num_bytes: int
    sha256: str


def sha256_of(path: Path) -> str:
    """A local file's sha256 (a shard in a store: ShardStore.sha256)."""
    with pa.OSFile(str(path)) as handle:
        return store_sha256_of(handle)


def check_schema(table_name: str, schema: pa.Schema) -> None:
    """Refuse a schema that is not exactly the declared one, naming the first column that differs."""
    expected = SHARD_TABLES[table_name]
    got = {f.name: f.type for f in schema}
    for field in expected:
        if field.name not in got:
            raise SchemaMismatch(f"{table_name}: column {field.name!r} is missing (expected {field.type})")
        if got[field.name] != field.type:
            raise SchemaMismatch(
                f"{table_name}: column {field.name!r} is {got[field.name]}, expected {field.type}"
            )
    extra = [name for name in got if name not in expected.names]
    if extra:
        raise SchemaMismatch(f"{table_name}: column {extra[0]!r} is not in the schema (schemas/tables.py)")
    if schema.names != expected.names:
        raise SchemaMismatch(f"{table_name}: columns are out of order: {schema.names} (expected {expected.names})")


def _open_shard(table_name: str, path: Path, store: ShardStore | None) -> pq.ParquetFile:
    """A whole Parquet file of the declared schema, opened (its footer read, no data)."""
    where = path if store is None else store.location(store.rel(path))
    try:
        parquet = pq.ParquetFile(path) if store is None else store.parquet(where)
    except (ShardStoreUnreachable, ShardStoreRefused):
        raise  # the server, not the shard: nothing to quarantine
    except PermissionError as exc:  # this process may not read it: not a bad shard either
        raise ShardStoreRefused(f"{where}: {exc.strerror or exc}: this user may not read it; nothing was changed") \
            from None
    except (OSError, pa.ArrowException) as exc:
        raise ShardUnreadable(f"{where}: not a readable Parquet file ({exc})") from None
    check_schema(table_name, parquet.schema_arrow)
    return parquet


def is_disk_full(exc: OSError) -> bool:
    """No space (or quota) left where a file was being written: a DiskFull's cause."""
    return exc.errno in (errno.ENOSPC, errno.EDQUOT)


def inspect_shard(table_name: str, path: Path, store: ShardStore | None = None) -> int:
    """Check a shard file without reading its data. Returns its row count. `path` is the shard's path
    under the warehouse folder; with a `store`, the shard is read where the store keeps it."""
    return _open_shard(table_name, path, store).metadata.num_rows


def write_shard(table_name: str, rows: pa.Table, path: Path, store: ShardStore | None = None) -> ShardFile:
    """Write `rows` as the shard `path` (zstd), in the warehouse's `store` (the file `path` without one).
    Readers never see a partial file, and a file already at `path` is kept when it holds the same
    bytes (a unit computed twice) and refused otherwise."""
    check_schema(table_name, rows.schema)
    rows = rows.replace_schema_metadata(
        {b"sim2act.table": table_name.encode(), b"sim2act.schema_version": str(SCHEMA_VERSION).encode()}
    )
    sink = pa.BufferOutputStream()  # in memory first: hashed without reading the file back
    pq.write_table(rows, sink, compression="zstd", compression_level=ZSTD_LEVEL, row_group_size=ROW_GROUP_ROWS)
    data = sink.getvalue()
    sha = hashlib.sha256(data).hexdigest()
    try:
        if store is None:
            write_new_file(path, data, sha)
        else:
            store.put_new(store.rel(path), data, sha)
    except OSError as exc:  # a bare `[Errno 28]` names neither the shard nor what to do
        if not is_disk_full(exc):
            raise
        raise DiskFull(
            f"no space left on device writing the {table_name} shard of unit {path.stem} ({path}); the unit is not "
            "registered: free space on that disk, then run the same command again to resume at the first unfinished unit"
        ) from None
    return ShardFile(table_name, path, rows.num_rows, data.size, sha)


def read_shard(table_name: str, path: Path, columns: list[str] | None = None, store: ShardStore | None = None) -> pa.Table:
    return _open_shard(table_name, path, store).read(columns=columns)


def read_shard_rows(table_name: str, path: Path, start: int, stop: int, columns: list[str] | None = None,
                    store: ShardStore | None = None) -> pa.Table:
    """Rows `start` to `stop` (one past the last) of a shard file, reading only the row groups they fall in."""
    parquet = _open_shard(table_name, path, store)
    groups, first, skip = [], 0, None
    for group in range(parquet.num_row_groups):
        size = parquet.metadata.row_group(group).num_rows
        if first < stop and first + size > start:
            groups.append(group)
            skip = first if skip is None else skip
        first += size
    if not groups:
        return parquet.schema_arrow.empty_table().select(columns) if columns else parquet.schema_arrow.empty_table()
    return parquet.read_row_groups(groups, columns=columns).slice(start - skip, stop - start)
