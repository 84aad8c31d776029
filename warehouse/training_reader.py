"""Stream training samples out of the warehouse: a SQL WHERE over the steps picks the rows, the
rows stream from the Parquet shards row group by row group, split across DataLoader workers,
through a shuffle buffer, images decoded in the workers as they are drawn.

Memory is bounded by configuration (the shuffle buffer plus one row group per worker), never
by the warehouse: the selection itself is held as row ranges (an episode is one range).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import duckdb
import numpy as np
import pyarrow.parquet as pq
from torch.utils.data import IterableDataset, get_worker_info

from schemas.frames import decode_frame
from warehouse.catalog import Catalog

COLUMNS = ["instruction", "image", "proprio", "action"]


class SelectionError(ValueError):
    """A training selection that does not parse, bind, or match anything."""


@dataclass(frozen=True)
class RowRange:
    path: str
    start: int  # first file row number
    stop: int  # one past the last


@dataclass
class Sample:
    image: np.ndarray  # uint8 (H, W, 3)
    language: np.ndarray  # float32 instruction embedding
    proprio: np.ndarray
    action: np.ndarray


def select_rows(
    catalog: Catalog, where: str = "TRUE", params: Sequence[Any] = (), as_of_iteration: int | None = None
) -> list[RowRange]:
    """The registered steps rows matching `where` (SQL over the steps columns; subqueries may use
    any catalog table or view), as runs of consecutive rows per shard file."""
    with catalog.connect(read_only=True, as_of_iteration=as_of_iteration) as con:
        paths = [
            (catalog.warehouse / p).as_posix()
            for (p,) in con.execute("SELECT path FROM shards WHERE table_name = 'steps' ORDER BY path").fetchall()
        ]
        if not paths:
            raise SelectionError("the warehouse holds no steps yet")
        try:
            rows = con.execute(
                f"""
                WITH picked AS (
                    SELECT filename, file_row_number AS n
                    FROM read_parquet({paths!r}, filename = true, file_row_number = true) AS steps
                    WHERE ({where}))
                SELECT filename, min(n), max(n) + 1 FROM (
                    SELECT filename, n, n - row_number() OVER (PARTITION BY filename ORDER BY n) AS run FROM picked)
                GROUP BY filename, run ORDER BY filename, 2""",
                list(params),
            ).fetchall()
        except duckdb.Error as exc:
            raise SelectionError(f"training selection {where!r}: {str(exc).splitlines()[0]}") from None
    return [RowRange(path, int(start), int(stop)) for path, start, stop in rows]


class StepStream(IterableDataset):
    def __init__(
        self, ranges: list[RowRange], embeddings: dict[str, np.ndarray], shuffle_buffer: int, seed: int
    ):
        by_file: dict[str, list[tuple[int, int]]] = {}
        for r in ranges:
            by_file.setdefault(r.path, []).append((r.start, r.stop))
        self.files = sorted(by_file.items())
        self.rows = sum(r.stop - r.start for r in ranges)
        self.embeddings, self.shuffle_buffer, self.seed = embeddings, shuffle_buffer, seed
        self.epoch = 0

    def __len__(self) -> int:
        return self.rows

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    @staticmethod
    def _rows(path: str, spans: list[tuple[int, int]]) -> Iterator[dict]:
        """The selected rows of one file, reading only the row groups they fall in."""
        parquet = pq.ParquetFile(Path(path))
        first = 0
        for group in range(parquet.num_row_groups):
            last = first + parquet.metadata.row_group(group).num_rows
            wanted = [(max(a, first) - first, min(b, last) - first) for a, b in spans if a < last and b > first]
            if wanted:
                table = parquet.read_row_group(group, columns=COLUMNS)
                for a, b in wanted:
                    yield from table.slice(a, b - a).to_pylist()
            first = last

    def _sample(self, row: dict) -> Sample:
        return Sample(
            decode_frame(row["image"]),
            self.embeddings[row["instruction"]],
            np.asarray(row["proprio"], dtype=np.float32),
            np.asarray(row["action"], dtype=np.float32),
        )

    def __iter__(self) -> Iterator[Sample]:
        worker = get_worker_info()
        index, count = (worker.id, worker.num_workers) if worker else (0, 1)
        rng = np.random.default_rng([self.seed, self.epoch, index])
        mine = self.files[index::count]
        buffer: list[dict] = []
        for pick in rng.permutation(len(mine)):
            for row in self._rows(*mine[pick]):
                buffer.append(row)
                if len(buffer) >= self.shuffle_buffer:
                    chosen = int(rng.integers(len(buffer)))
                    buffer[chosen], buffer[-1] = buffer[-1], buffer[chosen]
                    yield self._sample(buffer.pop())
        for chosen in rng.permutation(len(buffer)):
            yield self._sample(buffer[chosen])
