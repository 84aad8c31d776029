"""Stream training batches out of the warehouse: a SQL WHERE over the steps picks the rows, the
rows stream from the Parquet shards row group by row group, split across DataLoader workers,
through a shuffle buffer, and are made into batches (frames decoded) in the workers.

Memory is bounded by configuration (the shuffle buffer plus one row group per worker), never
by the warehouse: the selection itself is held as row ranges (an episode is one range).

For a chunked model (`chunk` > 1) each row also carries the actions of the next chunk-1 steps of its
episode (`action_chunk`, `expert_chunk`: this step's first, shorter at the episode's end), read
from the same file whether or not the selection holds those steps.

The batch sequence is a pure function of (selection, seed, batch size, workers): batch g comes
from worker g % W, every worker yields the same number per epoch, so a training resumed at batch
g reads exactly what it would have read (`start_batch`).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import torch
from torch.utils.data import DataLoader, IterableDataset, default_convert, get_worker_info

from schemas.errors import Sim2ActError
from schemas.frames import decode_depth, decode_frame
from warehouse.catalog import Catalog
from warehouse.store import ShardStore

COLUMNS = ["instruction", "image", "depth", "proprio", "action", "expert_action", "qpos"]
LOOKAHEAD_COLUMNS = ["episode_id", "action", "expert_action"]  # what a chunk's later steps are read for


class SelectionError(Sim2ActError, ValueError):
    """A training selection that does not parse, bind, or match anything."""


@dataclass(frozen=True)
class RowRange:
    """Consecutive selected rows of one shard, numbered within the shard. A compacted shard's rows
    live in `file` from row `offset` on: the selection, its order and so every batch are the same
    before and after `sim2act compact`; only where the rows are read from differs."""
    path: str  # the shard's location
    start: int  # first row number within the shard
    stop: int  # one past the last
    file: str = ""  # where its rows are read ("": the shard's own file, `path`)
    offset: int = 0  # the shard's first row in `file`


Segment = tuple[str, int, int]  # (path, first row, one past the last)
Piece = list[Segment]  # consecutive selected rows, the unit the shuffle permutes
Collate = Callable[[list[dict]], dict[str, Any]]  # rows (COLUMNS, raw) -> a batch


def select_rows(
    catalog: Catalog, where: str = "TRUE", params: Sequence[Any] = (), as_of_iteration: int | None = None,
    units: Sequence[str] | None = None,
) -> list[RowRange]:
    """The registered steps rows matching `where` (SQL over the steps columns; subqueries may use
    any catalog table or view), as runs of consecutive rows per shard; with `units`, only the steps
    shards those units wrote are read. A compacted shard's rows are found in its compacted file and
    numbered within the shard again (RowRange)."""
    location = catalog.store.location
    with catalog.connect(read_only=True, as_of_iteration=as_of_iteration, confined=True) as con:  # `where`: a user's SQL
        shards = [
            (location(path), location(stored_in or path), offset or 0, rows)
            for path, stored_in, offset, rows in con.execute(
                "SELECT path, stored_in, row_offset, num_rows FROM shards WHERE table_name = 'steps' "
                "AND (?::VARCHAR[] IS NULL OR list_contains(?, unit_key)) ORDER BY path", [units, units]).fetchall()
        ]
        if not shards:
            raise SelectionError("the warehouse holds no steps yet")
        files = sorted({file for _, file, _, _ in shards})
        con.register("selected_shards", pa.table({name: column for name, column in zip(
            ["shard", "file", "row_offset", "num_rows"], map(list, zip(*shards)))}))
        try:
            rows = con.execute(
                f"""
                WITH picked AS (
                    SELECT filename, file_row_number AS n
                    FROM read_parquet({files!r}, filename = true, file_row_number = true) AS steps
                    WHERE ({where})),
                placed AS (  -- the shard each picked row belongs to (a compacted file holds many, in row order)
                    SELECT s.shard, s.file, s.row_offset, p.n - s.row_offset AS n
                    FROM picked p ASOF JOIN selected_shards s ON p.filename = s.file AND p.n >= s.row_offset
                    WHERE p.n < s.row_offset + s.num_rows)
                SELECT shard, min(n), max(n) + 1, any_value(file), any_value(row_offset) FROM (
                    SELECT *, n - row_number() OVER (PARTITION BY shard ORDER BY n) AS run FROM placed)
                GROUP BY shard, run ORDER BY shard, 2""",
                list(params),
            ).fetchall()
        except duckdb.Error as exc:
            raise SelectionError(f"training selection {where!r}: {str(exc).splitlines()[0]}") from None
    return [RowRange(path, int(start), int(stop), "" if file == path else file, int(offset))
            for path, start, stop, file, offset in rows]


def partition(ranges: list[RowRange], workers: int, piece_rows: int) -> list[list[Piece]]:
    """Each worker's pieces: the selection in order, cut into pieces of at most `piece_rows` rows
    dealt round-robin, every worker getting exactly total // workers rows (so every worker yields
    as many batches; the last total % workers rows of the selection are left out). Pieces are cut
    in shard order and numbering; their segments name the file and rows the rows are read from."""
    stored = {r.path: (r.file or r.path, r.offset) for r in ranges}
    quota = sum(r.stop - r.start for r in ranges) // workers
    remaining, parts = [quota] * workers, [[] for _ in range(workers)]
    spans = iter(sorted((r.path, r.start, r.stop) for r in ranges))
    path, start, stop = next(spans, ("", 0, 0))
    worker = 0
    while any(remaining):
        want, piece = min(piece_rows, remaining[worker]), []
        remaining[worker] -= want
        while want:
            if start == stop:
                path, start, stop = next(spans)
                continue
            take = min(want, stop - start)
            file, offset = stored[path]
            piece.append((file, offset + start, offset + start + take))
            start, want = start + take, want - take
        if piece:
            parts[worker].append(piece)
        worker = (worker + 1) % workers
    return parts


def decode_rows(rows: list[dict]) -> dict[str, Any]:
    """The plain batch: frames (and depth maps, where recorded) decoded and stacked, the other
    columns as read."""
    depths = {} if rows[0]["depth"] is None else {"depth": np.stack([decode_depth(r["depth"]) for r in rows])}
    chunks = {} if "action_chunk" not in rows[0] else {
        "action_chunk": [r["action_chunk"] for r in rows], "expert_chunk": [r["expert_chunk"] for r in rows]}
    return {
        "image": np.stack([decode_frame(r["image"]) for r in rows]),
        **depths,
        "instruction": [r["instruction"] for r in rows],
        "proprio": np.asarray([r["proprio"] for r in rows], dtype=np.float32),
        "action": [r["action"] for r in rows],
        "expert_action": [r["expert_action"] for r in rows],
        "qpos": [r["qpos"] for r in rows],
        **chunks,
    }


def check_where(where: str | None) -> None:
    """Refuse a selection that does not parse or bind, before any work: bound against empty
    tables of the warehouse's schemas (steps columns; subqueries over any table or view)."""
    if where is None:
        return
    from schemas.tables import CATALOG_TABLES, EPISODES, FILTER_DECISIONS, INSTRUCTIONS, STEPS, VIEWS, catalog_ddl

    with duckdb.connect(config={"enable_external_access": False, "lock_configuration": True}) as con:  # no files
        for name, schema in (("steps", STEPS), ("episodes", EPISODES), ("filter_decisions", FILTER_DECISIONS),
                             ("instructions", INSTRUCTIONS)):
            con.register(name, schema.empty_table())
        for name in CATALOG_TABLES:
            con.execute(catalog_ddl(name))
        for name, sql in VIEWS.items():
            con.execute(f"CREATE VIEW {name} AS {sql}")
        try:
            con.execute(f"SELECT count(*) FROM steps WHERE ({where})").fetchall()
        except duckdb.Error as exc:
            raise SelectionError(f"train.where: {where!r}: {str(exc).splitlines()[0]}") from None


class StepBatches(IterableDataset):
    """Batches (dicts from `collate`, plus `batch`: the global batch number) over `epochs` epochs,
    for a DataLoader with batch_size=None and num_workers=`workers` (0: in the calling process)."""

    def __init__(
        self, ranges: list[RowRange], batch_size: int, shuffle_buffer: int, seed: int, epochs: int,
        workers: int = 0, collate: Collate = decode_rows, start_batch: int = 0, piece_rows: int = 1024,
        chunk: int = 1, store: ShardStore | None = None,
    ):
        self.store = store  # where the ranges' locations are read (None: local files)
        self.streams = max(1, workers)
        self.parts = partition(ranges, self.streams, piece_rows)
        rows = sum(stop - start for piece in self.parts[0] for _, start, stop in piece)
        if rows == 0:
            raise SelectionError(f"{sum(r.stop - r.start for r in ranges)} selected rows cannot feed {self.streams} workers")
        self.worker_batches = math.ceil(rows / batch_size)  # per worker per epoch
        self.rows_per_epoch = rows * self.streams
        self.batch_size, self.shuffle_buffer, self.seed, self.epochs = batch_size, shuffle_buffer, seed, epochs
        self.collate, self.start_batch, self.chunk = collate, start_batch, chunk

    @property
    def batches_per_epoch(self) -> int:
        return self.worker_batches * self.streams

    def __len__(self) -> int:
        return max(0, self.epochs * self.batches_per_epoch - self.start_batch)

    def _rows(self, path: str, spans: list[tuple[int, int]]) -> Iterator[dict]:
        """The selected rows of one file, reading only the row groups they fall in (and, for chunks,
        the look-ahead columns of the rows up to chunk-1 past them)."""
        parquet = pq.ParquetFile(Path(path)) if self.store is None else self.store.parquet(path)
        # S3's ranged reads are waited for as its footer reads are: a blip does not end a training
        read = (lambda action, *args: action(*args)) if self.store is None else self.store.patiently
        sizes = [parquet.metadata.row_group(g).num_rows for g in range(parquet.num_row_groups)]
        starts = np.concatenate([[0], np.cumsum(sizes)]).astype(int)
        for group, first in enumerate(starts[:-1]):
            last = int(starts[group + 1])
            wanted = [(max(a, first) - first, min(b, last) - first) for a, b in spans if a < last and b > first]
            if not wanted:
                continue
            table = read(lambda: parquet.read_row_group(group, columns=COLUMNS))
            ahead = None
            if self.chunk > 1:
                low, high = min(a for a, _ in wanted), max(b for _, b in wanted) + self.chunk - 1
                ahead = read(self._lookahead, parquet, starts, group, low, high)
            for a, b in wanted:
                rows = table.slice(a, b - a).to_pylist()
                if ahead is not None:
                    for offset, row in enumerate(rows, start=a - low):
                        self._attach_chunk(row, ahead, offset)
                yield from rows

    @staticmethod
    def _lookahead(parquet: pq.ParquetFile, starts: np.ndarray, group: int, low: int, high: int) -> dict[str, list]:
        """LOOKAHEAD_COLUMNS of the file's rows `low` to `high` (counted from row group `group`'s first
        row; the file may end first), as lists from row `low`."""
        first = int(starts[group])
        groups = [g for g in range(group, len(starts) - 1) if starts[g] < first + high]
        table = parquet.read_row_groups(groups, columns=LOOKAHEAD_COLUMNS).slice(low, high - low)
        return {name: table[name].to_pylist() for name in LOOKAHEAD_COLUMNS}

    def _attach_chunk(self, row: dict, ahead: dict[str, list], offset: int) -> None:
        """`action_chunk`, `expert_chunk`: the actions of the row's step and the next chunk-1 steps of
        its episode (fewer where the episode ends first)."""
        episode = ahead["episode_id"][offset]
        stop = offset + 1
        while stop < min(offset + self.chunk, len(episode_ids := ahead["episode_id"])) and episode_ids[stop] == episode:
            stop += 1
        row["action_chunk"] = ahead["action"][offset:stop]
        row["expert_chunk"] = ahead["expert_action"][offset:stop]

    def _piece_rows(self, piece: Piece) -> Iterator[dict]:
        """A piece's rows in order, each of its files opened once."""
        for path, segments in itertools.groupby(piece, key=lambda segment: segment[0]):
            yield from self._rows(path, [(start, stop) for _, start, stop in segments])

    def _shuffled(self, rng: np.random.Generator, pieces: list[Piece]) -> Iterator[dict]:
        """The pieces in a seeded order, their rows through the shuffle buffer."""
        buffer: list[dict] = []
        for pick in rng.permutation(len(pieces)):
            for row in self._piece_rows(pieces[pick]):
                buffer.append(row)
                if len(buffer) >= self.shuffle_buffer:
                    chosen = int(rng.integers(len(buffer)))
                    buffer[chosen], buffer[-1] = buffer[-1], buffer[chosen]
                    yield buffer.pop()
        for chosen in rng.permutation(len(buffer)):
            yield buffer[chosen]

    def _epoch(self, stream: int, epoch: int) -> Iterator[list[dict]]:
        """One worker's batches of rows for one epoch."""
        rows = self._shuffled(np.random.default_rng([self.seed, epoch, stream]), self.parts[stream])
        while batch := list(itertools.islice(rows, self.batch_size)):
            yield batch

    def first_batch(self) -> dict[str, Any]:
        """The first `batch_size` rows in file order, collated into tensors as a DataLoader yields them: a
        batch of this training's shape and content for timing a step (policies/precision.py), without
        filling the shuffle buffer."""
        rows = (row for piece in self.parts[0] for row in self._piece_rows(piece))
        return default_convert(self.collate(list(itertools.islice(rows, self.batch_size))))

    def __iter__(self) -> Iterator[dict[str, Any]]:
        worker = get_worker_info()
        index, count = (worker.id, worker.num_workers) if worker else (0, 1)
        # The DataLoader takes batches from its workers round-robin starting at worker 0, so that
        # worker plays the stream whose turn is next
        stream = (index + self.start_batch) % count
        if count != self.streams:
            raise RuntimeError(f"StepBatches was split for {self.streams} workers, the DataLoader runs {count}")
        per_epoch = self.worker_batches
        skip = max(0, -(-(self.start_batch - stream) // count))  # this worker's batches before start_batch
        for epoch in range(skip // per_epoch, self.epochs):
            for k, rows in enumerate(self._epoch(stream, epoch)):
                if epoch * per_epoch + k >= skip:  # skipped batches are read, never decoded
                    yield {**self.collate(rows), "batch": (epoch * per_epoch + k) * count + stream}


def training_loader(
    batches: StepBatches, workers: int, pin_memory: bool = False, persistent: bool = False,
) -> DataLoader:
    """The DataLoader a training reads `batches` through (stages/train.py), and `sim2act bench warehouse`
    times: `workers` processes (0: in the calling process), each prefetching 4 batches. `persistent` keeps
    the workers from one pass over the loader to the next (the bench times a pass apart from their start;
    a training makes one pass over all its epochs); they keep `batches` as it was when they started, so a
    later `start_batch` or `epochs` never reaches them.

    The workers are spawned, not forked: a process forked from one that ran a Prefect flow exits with
    code 1 and prints nothing. Prefect's queue services register a thread-exit hook
    (`threading._register_atexit`) that asserts on state its own after-fork reset clears, and the
    DataLoader treats the worker's code 1 as a crash when the epoch ends.
    """
    if max(1, workers) != batches.streams:  # StepBatches reads 0 workers as one stream
        raise ValueError(f"expected the {batches.streams} worker(s) the batches were split for, got {workers}")
    return DataLoader(
        batches, batch_size=None, num_workers=workers, pin_memory=pin_memory,
        multiprocessing_context="spawn" if workers else None, prefetch_factor=4 if workers else None,
        persistent_workers=persistent and workers > 0,
        # its own generator: each start of a loader drew its workers' base seed from torch's global one, and a
        # resumed training starts one more loader than a straight one, so the dropout of a trainable language
        # encoder (MiniLM's 0.1) drew other masks after a resume (the batches are seeded apart, not by this)
        generator=torch.Generator().manual_seed(0),
    )
