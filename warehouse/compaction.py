"""Compaction: an iteration's small shards, concatenated into a few large files.

Every unit writes its own small shard per table (an explore unit: tens of `episodes` rows, a few
thousand `steps`), so at a million triplets a table is thousands of files and a query pays for
each one it opens: `task_success` over 10M steps took 480 ms in explore-sized shards and 57 ms
over the same rows in large files. `compact` concatenates them; the catalog keeps every shard's
row (path, unit, sha256: lineage, dataset digests and `--as-of-iteration` hold) and records where
its rows went (`shards.stored_in`, `shards.row_offset`), so quarantine stays per unit and the
training reader finds the same rows in the same order (warehouse/training_reader.RowRange).
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import pyarrow as pa
import pyarrow.parquet as pq

from schemas.tables import SHARD_TABLES
from schemas.version import SCHEMA_VERSION
from warehouse.catalog import Catalog
from warehouse.shard_writer import (ROW_GROUP_ROWS, ZSTD_LEVEL, DiskFull, SchemaMismatch, ShardUnreadable,
                                    check_schema, is_disk_full)
from warehouse.store import ShardStoreRefused, ShardStoreUnreachable

log = logging.getLogger("sim2act.warehouse.compaction")

COMPACT_FILE_ROWS = 1_000_000  # rows per compacted file at most
# bytes of a compacted file's sources at most: the file is built in memory and written whole (a
# reader never sees half of it), and its frames decompress to ~10x that one source at a time
COMPACT_FILE_BYTES = 256 << 20
# Row groups of the compacted small tables: DuckDB scans 100k-row groups 5-10x faster than the
# shards' few-row ones. `steps` keeps one row group per source shard instead: the training reader
# reads a piece's row group whole, and a 100k-row group of frames would be ~200 MB per 1,024 rows.
SMALL_TABLE_GROUP_ROWS = 100_000


@dataclass(frozen=True)
class Source:
    path: str  # relative to the warehouse folder
    unit_key: str
    num_rows: int
    num_bytes: int
    sha256: str  # as registered: a source is compacted only when its bytes still hash to it


class BadSource(ShardUnreadable):
    """A source that is not what the catalog registered; `source` is it (its unit is the one to quarantine)."""

    def __init__(self, source: Source, reason: str):
        super().__init__(reason)
        self.source = source


@dataclass(frozen=True)
class CompactionPlan:
    """One file to write: `sources` of one table, campaign and iteration, in path order."""
    table: str
    campaign: str
    iteration: int
    sources: tuple[Source, ...]

    @property
    def num_rows(self) -> int:
        return sum(source.num_rows for source in self.sources)


@dataclass
class CompactionSummary:
    files: int = 0  # compacted files written
    sources: int = 0  # shard files they replaced
    rows: int = 0
    bytes_before: int = 0
    bytes_after: int = 0
    quarantined: list[tuple[str, str]] = field(default_factory=list)  # (path, reason): sources found bad
    wall_s: float = 0.0


def plan_compaction(catalog: Catalog, iterations: Sequence[int] | None = None) -> list[CompactionPlan]:
    """The files a compaction writes: per table, campaign and iteration (all, or `iterations`), the
    shards still their own files, in path order, cut at COMPACT_FILE_ROWS rows or COMPACT_FILE_BYTES;
    a cut of one shard is left as it is (nothing to gain)."""
    rows = catalog.query(
        "SELECT table_name, campaign, iteration, path, unit_key, num_rows, num_bytes, sha256 FROM shards "
        "WHERE stored_in IS NULL AND (?::INTEGER[] IS NULL OR list_contains(?, iteration)) "
        "ORDER BY table_name, campaign, iteration, path", [iterations, iterations])
    plans: list[CompactionPlan] = []

    def close(key: tuple[str, str, int], sources: list[Source]) -> None:
        if len(sources) > 1:
            plans.append(CompactionPlan(*key, tuple(sources)))

    key, run = None, []
    for table, campaign, iteration, path, unit, num_rows, num_bytes, sha in rows:
        source = Source(path, unit, num_rows, num_bytes, sha)
        full = (sum(s.num_rows for s in run) + num_rows > COMPACT_FILE_ROWS
                or sum(s.num_bytes for s in run) + num_bytes > COMPACT_FILE_BYTES)
        if (table, campaign, iteration) != key or (run and full):
            if key is not None:
                close(key, run)
            key, run = (table, campaign, iteration), []
        run.append(source)
    if key is not None:
        close(key, run)
    return plans


def _concatenated(catalog: Catalog, plan: CompactionPlan) -> Iterator[pa.Table]:
    """The plan's sources' rows in path order, each read by `_source_rows`."""
    for source in plan.sources:
        yield _source_rows(catalog, plan.table, source)


def _source_rows(catalog: Catalog, table: str, source: Source) -> pa.Table:
    """A source's rows, from its bytes read once: they hash to its registered sha256, decode as a
    Parquet file of the table's schema and hold its registered row count. The hash first: a flipped
    bit inside a frame decodes without complaint, and once rewritten into a compacted file (a new
    hash, registered) it could never be told from the data explored.

    Raises:
        BadSource: naming the source and which check it failed.
        ShardStoreUnreachable, ShardStoreRefused: the store, not the source (nothing to quarantine).
    """
    where = catalog.store.location(source.path)
    try:
        with catalog.store.read(source.path) as handle:
            data = handle.read_buffer()
    except (ShardStoreUnreachable, ShardStoreRefused):
        raise
    except PermissionError as exc:  # this user may not read it: the file is not the fault
        raise ShardStoreRefused(f"{where}: {exc.strerror or exc}: this user may not read it; nothing was changed") \
            from None
    except OSError as exc:
        raise BadSource(source, f"{where}: not readable ({exc})") from None
    sha = hashlib.sha256(data).hexdigest()
    if sha != source.sha256:
        raise BadSource(source, f"{where}: its bytes hash to {sha[:16]}…, expected the registered {source.sha256[:16]}…")
    try:
        parquet = pq.ParquetFile(pa.BufferReader(data))
        check_schema(table, parquet.schema_arrow)
        rows = parquet.read()
    except SchemaMismatch as exc:
        raise BadSource(source, f"{where}: {exc}") from None
    except (OSError, pa.ArrowException) as exc:
        raise BadSource(source, f"{where}: not a readable Parquet file ({exc})") from None
    if rows.num_rows != source.num_rows:
        raise BadSource(source, f"{where}: {source.num_rows} rows registered, the file has {rows.num_rows}")
    return rows


def write_compacted(catalog: Catalog, plan: CompactionPlan) -> tuple[str, int, str]:
    """Write the plan's file into the warehouse's store under a name made of its content (a rerun
    after a kill writes the same name and bytes). -> (path relative to the warehouse, bytes, sha256).

    Raises:
        BadSource: a source is not what the catalog registered (naming it)."""
    schema = SHARD_TABLES[plan.table].with_metadata(
        {b"sim2act.table": plan.table.encode(), b"sim2act.schema_version": str(SCHEMA_VERSION).encode()})
    sink = pa.BufferOutputStream()
    with pq.ParquetWriter(sink, schema, compression="zstd", compression_level=ZSTD_LEVEL) as writer:
        pending: list[pa.Table] = []
        for rows in _concatenated(catalog, plan):
            rows = rows.replace_schema_metadata(schema.metadata)
            if plan.table == "steps":  # one row group per source (the training reader's unit of reading)
                writer.write_table(rows, row_group_size=ROW_GROUP_ROWS)
                continue
            pending.append(rows)
            if sum(t.num_rows for t in pending) >= SMALL_TABLE_GROUP_ROWS:
                writer.write_table(pa.concat_tables(pending), row_group_size=SMALL_TABLE_GROUP_ROWS)
                pending = []
        if pending:
            writer.write_table(pa.concat_tables(pending), row_group_size=SMALL_TABLE_GROUP_ROWS)
    data = sink.getvalue()
    sha = hashlib.sha256(data).hexdigest()
    path = f"shards/{plan.table}/iteration={plan.iteration}/compacted-{sha[:16]}.parquet"
    try:
        catalog.store.put_new(path, data, sha)  # the same bytes already there (a rerun after a kill) are kept
    except OSError as exc:  # a bare `[Errno 28]` names neither the file nor what to do
        if not is_disk_full(exc):
            raise
        raise DiskFull(f"no space left on device writing the compacted {plan.table} file of iteration {plan.iteration} "
                       f"({catalog.store.location(path)}); nothing of it is registered and its sources are kept: free "
                       "space there, then run the compaction again") from None
    return path, data.size, sha


def compact(catalog: Catalog, iterations: Sequence[int] | None = None,
            progress: Callable[[int, int, CompactionPlan], None] | None = None) -> CompactionSummary:
    """Compact the warehouse's shards (of `iterations`, or all).

    Run it where nothing else writes the warehouse or reads its files at length (`sim2act warehouse
    compact` holds the workspace's run lock and its shard-files lock, flows/run_lock.py): a training
    that listed a source before it was deleted could not read it.

    Steps:
        1. Plan the files (`plan_compaction`): per table, campaign and iteration, the shards still
           their own files, in path order, at most COMPACT_FILE_ROWS rows / COMPACT_FILE_BYTES each.
        2. Write each file (`write_compacted`): its sources read, checked against the catalog and
           concatenated; `steps` keeps one row group per source, the other tables get 100k-row ones.
        3. Register it in one transaction (`Catalog.register_compacted`): its `compacted` row, its
           sources' `stored_in` / `row_offset`, the table's views. A kill before this leaves an
           unregistered file that the next run's orphan sweep removes; after it, the sources.
        4. Delete the sources' files.
        A source that is not what the catalog registered (its sha256, its schema, its rows, or it does
        not decode) is quarantined with its unit, the unit's other shards too (the next run redoes it),
        and what is left is planned again.

    Args:
        catalog: the warehouse's catalog.
        iterations: the iterations to compact; None: every iteration.
        progress: called (files done, files planned, the plan just done) after each file.

    Returns:
        What was compacted: files, sources, rows, bytes before and after, quarantined sources.
    """
    started = time.monotonic()
    summary = CompactionSummary()
    done, plans = 0, plan_compaction(catalog, iterations)
    while plans:
        plan = plans.pop(0)
        try:
            path, size, sha = write_compacted(catalog, plan)
        except BadSource as exc:
            if not catalog.quarantine(exc.source.path, str(exc), checked_file=True):
                raise  # not a file the catalog reads any more: planning again would meet it again, forever
            summary.quarantined.append((exc.source.path, str(exc)))
            log.warning("compaction: quarantined unit %s (%s); the next run redoes it", exc.source.unit_key, exc)
            # planned again: its unit's shards of the other tables went with it, out of the plans still to do
            plans = plan_compaction(catalog, iterations)
            continue
        offsets, at = [], 0
        for source in plan.sources:
            offsets.append((source.path, at))
            at += source.num_rows
        catalog.register_compacted(path=path, table=plan.table, campaign=plan.campaign, iteration=plan.iteration,
                                   num_rows=plan.num_rows, num_bytes=size, sha256=sha, offsets=offsets)
        for source in plan.sources:
            catalog.store.delete(source.path)
        done += 1
        summary.files += 1
        summary.sources += len(plan.sources)
        summary.rows += plan.num_rows
        summary.bytes_before += sum(source.num_bytes for source in plan.sources)
        summary.bytes_after += size
        if progress is not None:
            progress(done, done + len(plans), plan)
    summary.wall_s = time.monotonic() - started
    return summary
