"""Immutable Parquet shards, written to a temporary name and moved into place atomically."""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from schemas.tables import SHARD_TABLES
from schemas.version import SCHEMA_VERSION


class SchemaMismatch(ValueError):
    pass


@dataclass(frozen=True)
class ShardFile:
    table: str
    path: Path
    num_rows: int
    num_bytes: int
    sha256: str


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def check_schema(table_name: str, schema: pa.Schema) -> None:
    expected = SHARD_TABLES[table_name]
    if not schema.remove_metadata().equals(expected):
        got = {f.name: str(f.type) for f in schema}
        want = {f.name: str(f.type) for f in expected}
        diff = sorted(set(got.items()) ^ set(want.items()))
        raise SchemaMismatch(f"{table_name}: schema differs from schemas.tables ({diff[:4]})")


def write_shard(table_name: str, rows: pa.Table, path: Path) -> ShardFile:
    """Write `rows` as the shard `path` (zstd). Readers never see a partial file."""
    check_schema(table_name, rows.schema)
    rows = rows.replace_schema_metadata(
        {b"sim2act.table": table_name.encode(), b"sim2act.schema_version": str(SCHEMA_VERSION).encode()}
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        pq.write_table(rows, tmp, compression="zstd")
        with tmp.open("rb") as handle:
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return ShardFile(table_name, path, rows.num_rows, path.stat().st_size, _sha256(path))


def read_shard(table_name: str, path: Path) -> pa.Table:
    rows = pq.read_table(path)
    check_schema(table_name, rows.schema)
    return rows
