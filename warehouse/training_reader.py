"""Stream training samples from Parquet shards: row group by row group, through a shuffle
buffer, images decoded as they are drawn. Memory is bounded by the buffer, not the warehouse."""

from __future__ import annotations

import io
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from PIL import Image
from torch.utils.data import IterableDataset, get_worker_info

COLUMNS = ["episode_id", "instruction", "image", "proprio", "action"]


@dataclass
class Sample:
    image: np.ndarray  # uint8 (H, W, 3)
    language: np.ndarray  # float32 instruction embedding
    proprio: np.ndarray
    action: np.ndarray


def decode_png(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


class StepStream(IterableDataset):
    def __init__(
        self,
        shards: list[Path],
        kept_episodes: set[str],
        embeddings: dict[str, np.ndarray],
        shuffle_buffer: int,
        seed: int,
    ):
        self.shards, self.kept = sorted(shards), kept_episodes
        self.embeddings, self.shuffle_buffer, self.seed = embeddings, shuffle_buffer, seed
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = epoch

    def _rows(self, shards: list[Path]) -> Iterator[dict]:
        for path in shards:
            parquet = pq.ParquetFile(path)
            for group in range(parquet.num_row_groups):
                for row in parquet.read_row_group(group, columns=COLUMNS).to_pylist():
                    if row["episode_id"] in self.kept:
                        yield row

    def _sample(self, row: dict) -> Sample:
        return Sample(
            decode_png(row["image"]),
            self.embeddings[row["instruction"]],
            np.asarray(row["proprio"], dtype=np.float32),
            np.asarray(row["action"], dtype=np.float32),
        )

    def __iter__(self) -> Iterator[Sample]:
        worker = get_worker_info()
        index, count = (worker.id, worker.num_workers) if worker else (0, 1)
        rng = np.random.default_rng([self.seed, self.epoch, index])
        mine = self.shards[index::count]
        buffer: list[dict] = []
        for shard in rng.permutation(len(mine)):
            for row in self._rows([mine[shard]]):
                buffer.append(row)
                if len(buffer) >= self.shuffle_buffer:
                    pick = int(rng.integers(len(buffer)))
                    buffer[pick], buffer[-1] = buffer[-1], buffer[pick]
                    yield self._sample(buffer.pop())
        for pick in rng.permutation(len(buffer)):
            yield self._sample(buffer[pick])
