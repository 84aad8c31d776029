"""Export a selection of the warehouse as a LeRobotDataset v3.0, the layout LeRobot trains on.

    meta/info.json                      schema, fps, totals, path templates
    meta/stats.json                     per feature: min, max, mean, std, count, q01 ... q99
    meta/tasks.parquet                  task string (the index) -> task_index
    meta/episodes/chunk-000/file-000.parquet   per episode: length, tasks, where its rows and frames lie, its stats
    data/chunk-000/file-000.parquet     one row per step, one row group per episode
    videos/observation.images.image/chunk-000/file-000.mp4   many episodes' frames back to back
    videos/observation.images.wrist_image/...   the hand camera's, where frames hold two views (render.wrist_camera)

Files roll over to file-001, ... past `data_files_size_in_mb` / `video_files_size_in_mb`, as
LeRobot's own writer does. The format follows lerobot's datasets/{utils,io_utils,dataset_writer,
dataset_metadata,compute_stats}.py; see tests/warehouse/test_export_lerobot.py for what is checked.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import socket
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import duckdb
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from schemas.errors import Sim2ActError
from schemas.frames import decode_frame
from schemas.settings import process_alive
from schemas.tasks import CONTROL_HZ
from warehouse.catalog import Catalog
from warehouse.store import fsync_path
from warehouse.video import CONTROL_FPS, VIDEO_CODEC, video_writer

CODEBASE_VERSION = "v3.0"
CAMERA = "observation.images.image"  # LeRobot's name for a single robosuite/LIBERO agent-view camera
WRIST_CAMERA = "observation.images.wrist_image"  # LIBERO's for the hand camera: the right view of a two-view frame
CHUNKS_SIZE = 1000  # files per chunk folder
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
FETCH_MB = 64.0  # encoded frame bytes fetched per query (default): bounds memory, however many episodes
ROBOT_TYPES = {"robosuite": "panda", "metaworld": "sawyer"}
STEP_COLUMNS = "episode_id, step, instruction, image, proprio, action, reward, done, success"


class ExportError(Sim2ActError, ValueError):
    """An export refused before writing: a bad --where, an empty or mixed selection, a used folder."""


@dataclass(frozen=True)
class ExportSummary:
    episodes: int
    frames: int
    tasks: int
    bytes: int
    out_dir: Path


@dataclass(frozen=True)
class _Episode:
    episode_id: str
    task_id: str
    frames: int
    image_bytes: int
    action_dims: tuple[int, int]  # (min, max) over its steps
    state_dims: tuple[int, int]


def export_lerobot(
    catalog: Catalog,
    out_dir: Path,
    where: str | None = None,
    *,
    fps: int | None = None,
    include_rejected: bool = False,
    repo_id: str = "sim2act/export",
    progress: Callable[[int, int], None] | None = None,
    data_files_size_in_mb: float = 100,
    video_files_size_in_mb: float = 200,
    fetch_mb: float = FETCH_MB,
) -> ExportSummary:
    """Write the whole episodes whose steps match `where` (SQL over the steps view; by default
    only episodes the filter kept) to `out_dir` as a LeRobotDataset v3.0. `progress(done, total)`
    is called after each episode. Memory is bounded by `fetch_mb`: the episodes are read in groups of
    about that many MB of encoded frames (one episode at least), whatever the selection's size. `fps`:
    the selection's family's control rate by default (schemas.tasks.CONTROL_HZ; a mix of rates asks for one)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ExportError(f"{out_dir} is a file: export into a new folder")
    if out_dir.exists() and any(out_dir.iterdir()):
        raise ExportError(f"{out_dir} is a folder with files in it: export into a new one")
    above = next(p for p in out_dir.absolute().parents if p.exists())
    if not above.is_dir() or not os.access(above, os.W_OK):  # found now, not after the selection is read
        raise ExportError(f"cannot make {out_dir}: {above} is {'a file' if not above.is_dir() else 'not writable'}")
    episodes = _select(catalog, where, include_rejected)
    action_dim = _one_dim(episodes, "action", lambda e: e.action_dims)
    state_dim = _one_dim(episodes, "proprio", lambda e: e.state_dims)
    if action_dim == 0:
        raise ExportError("the selected steps have no action")
    families = _families(catalog, episodes)
    if fps is None:
        rates = {CONTROL_HZ.get(family, CONTROL_FPS) for family in families} or {CONTROL_FPS}
        if len(rates) > 1:
            raise ExportError(f"the selection mixes families of other control rates ({', '.join(sorted(families))}: "
                              f"{', '.join(f'{CONTROL_HZ[f]} Hz' for f in sorted(families))}); pass --fps, or "
                              "export each family apart")
        fps = rates.pop()

    # A crash leaves no half-written dataset at out_dir: all is written beside it, then renamed.
    tmp = _partial_folder(out_dir, os.getpid())
    _remove_killed_exports(out_dir)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        writer = _Writer(tmp, fps, state_dim, action_dim, data_files_size_in_mb, video_files_size_in_mb)
        done = 0
        for group in _groups(episodes, int(fetch_mb * (1 << 20))):
            # the range beside the list: DuckDB prunes row groups by a range's min/max, not by a long IN
            # list (past 50 values it scans everything: the million's export read all its frames per group)
            steps = catalog.query_arrow(
                f"SELECT {STEP_COLUMNS} FROM steps WHERE episode_id IN ({', '.join('?' * len(group))}) "
                "AND episode_id BETWEEN ? AND ? ORDER BY episode_id, step",
                [e.episode_id for e in group] + [group[0].episode_id, group[-1].episode_id],
            )
            if steps.num_rows != sum(e.frames for e in group):
                raise ExportError("the warehouse changed during the export (steps of an episode differ); run it again")
            offset = 0
            for episode in group:
                writer.add_episode(steps.slice(offset, episode.frames))
                offset += episode.frames
                done += 1
                if progress is not None:
                    progress(done, len(episodes))
        writer.finish(repo_id, _robot_type(families))
        _fsync_tree(tmp)  # on disk before the name says finished: past a power loss, whole or absent
        if out_dir.exists():
            out_dir.rmdir()
        tmp.rename(out_dir)
        fsync_path(out_dir.parent)  # the rename itself
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    size = sum(p.stat().st_size for p in out_dir.rglob("*") if p.is_file())
    return ExportSummary(len(episodes), writer.frames, len(writer.tasks), size, out_dir)


def _partial_folder(out_dir: Path, pid: int) -> Path:
    """Where export `pid` on this host writes before its rename onto `out_dir`."""
    return out_dir.parent / f".{out_dir.name}.partial-{socket.gethostname()}-{pid}"


def _remove_killed_exports(out_dir: Path) -> None:
    """The folders that exports into `out_dir` on this host left when killed (a SIGKILL runs no clean-up),
    each a full-size copy nothing else would remove; a live export's is left to it."""
    prefix = _partial_folder(out_dir, 0).name[:-1]
    for folder in out_dir.parent.glob(glob.escape(prefix) + "*"):
        pid = folder.name[len(prefix):]
        if pid.isdigit() and not process_alive(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)


def _fsync_tree(folder: Path) -> None:
    for path in [*sorted(folder.rglob("*"), key=lambda p: -len(p.parts)), folder]:  # files before their folders
        fsync_path(path)


# -- selection -----------------------------------------------------------------------------------


def _select(catalog: Catalog, where: str | None, include_rejected: bool) -> list[_Episode]:
    kept = "" if include_rejected else "AND episode_id IN (SELECT episode_id FROM filter_decisions WHERE kept)"
    sql = f"""
        SELECT episode_id, any_value(task_id), count(*), coalesce(sum(octet_length(image)), 0),
               min(coalesce(len(action), 0)), max(coalesce(len(action), 0)),
               min(coalesce(len(proprio), 0)), max(coalesce(len(proprio), 0))
        FROM steps
        WHERE episode_id IN (SELECT episode_id FROM steps WHERE ({where or "TRUE"})) {kept}
        GROUP BY episode_id ORDER BY episode_id"""
    try:
        rows = catalog.query(sql, confined=True)  # --where is a user's SQL: the warehouse's files only
    except duckdb.Error as exc:
        what = f"--where {where!r}" if where else "selecting the episodes"
        raise ExportError(f"{what}: {str(exc).splitlines()[0]}") from None
    if not rows:
        which = "" if include_rejected else " among the episodes the filter kept (see --include-rejected)"
        raise ExportError(f"no episode matches --where {where!r}{which}" if where else
                          f"no episode to export{which or ' (the warehouse holds none)'}")
    return [_Episode(r[0], r[1], r[2], r[3], (r[4], r[5]), (r[6], r[7])) for r in rows]


def _one_dim(episodes: list[_Episode], column: str, dims: Callable[[_Episode], tuple[int, int]]) -> int:
    """LeRobot gives a feature one shape: a selection mixing sizes is refused, naming two of them."""
    tasks: dict[int, set[str]] = {}
    for episode in episodes:
        for dim in set(dims(episode)):
            tasks.setdefault(dim, set()).add(episode.task_id)
    if len(tasks) > 1:
        (a, tasks_a), (b, tasks_b) = sorted(tasks.items())[:2]
        raise ExportError(
            f"the selection mixes {column} shapes ({a},) (tasks {', '.join(sorted(tasks_a)[:3])}) and ({b},) "
            f"(tasks {', '.join(sorted(tasks_b)[:3])}); a LeRobot dataset has one shape per feature: "
            f"narrow it with --where, e.g. --where \"task_id = '{min(tasks_b)}'\""
        )
    return next(iter(tasks))


def _groups(episodes: list[_Episode], fetch_bytes: int) -> Iterator[list[_Episode]]:
    """Consecutive episodes, about `fetch_bytes` of images each (one episode at least)."""
    group: list[_Episode] = []
    size = 0
    for episode in episodes:
        if group and size + episode.image_bytes > fetch_bytes:
            yield group
            group, size = [], 0
        group.append(episode)
        size += episode.image_bytes
    if group:
        yield group


def _families(catalog: Catalog, episodes: list[_Episode]) -> set[str]:
    """The selection's task families (none where the catalog has no tasks rows)."""
    task_ids = sorted({e.task_id for e in episodes})
    rows = catalog.query("SELECT DISTINCT family FROM tasks WHERE list_contains(?, task_id)", [task_ids])
    return {family for (family,) in rows}


def _robot_type(families: set[str]) -> str | None:
    if len(families) != 1:
        return None  # unknown (no tasks rows) or mixed
    family = next(iter(families))
    return ROBOT_TYPES.get(family, family)


# -- writing -------------------------------------------------------------------------------------


def _next_file(chunk: int, file: int) -> tuple[int, int]:
    return (chunk + 1, 0) if file + 1 == CHUNKS_SIZE else (chunk, file + 1)


class _RollingParquet:
    """Parquet files along a chunk/file template; a new file once the next table would pass the
    limit (uncompressed Arrow bytes, so files stay under it)."""

    def __init__(self, root: Path, template: str, limit_mb: float):
        self.root, self.template, self.limit = root, template, limit_mb * (1 << 20)
        self.chunk = self.file = self.size = 0
        self.writer: pq.ParquetWriter | None = None

    def place(self, nbytes: int) -> tuple[int, int]:
        """The (chunk, file) the next table of `nbytes` goes to."""
        if self.writer is not None and self.size + nbytes > self.limit:
            self.close()
            self.chunk, self.file = _next_file(self.chunk, self.file)
        return self.chunk, self.file

    def write(self, table: pa.Table) -> tuple[int, int]:
        """Write `table` as one row group (an episode reads as one); -> its (chunk, file)."""
        self.place(table.nbytes)
        if self.writer is None:
            path = self.root / self.template.format(chunk_index=self.chunk, file_index=self.file)
            path.parent.mkdir(parents=True, exist_ok=True)
            self.writer = pq.ParquetWriter(path, table.schema, compression="snappy")
            self.size = 0
        self.writer.write_table(table)
        self.size += table.nbytes
        return self.chunk, self.file

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


class _Videos:
    """One mp4 per chunk/file with episodes back to back (LeRobot v3 finds an episode by its
    from/to timestamps); a new file once the current one has passed the limit."""

    def __init__(self, root: Path, fps: int, limit_mb: float, video_key: str = CAMERA):
        self.root, self.fps, self.limit, self.video_key = root, fps, limit_mb * (1 << 20), video_key
        self.chunk = self.file = self.frames = 0
        self.path: Path | None = None
        self.encoder = None  # imageio's ffmpeg writer of the open file
        self.shape: tuple[int, int] | None = None

    def start_episode(self) -> tuple[int, int, float]:
        """(chunk, file, from_timestamp) of the episode about to be written."""
        if self.encoder is not None and self.current_bytes() >= self.limit:
            self.close()
            self.chunk, self.file = _next_file(self.chunk, self.file)
        return self.chunk, self.file, self.frames / self.fps

    def current_bytes(self) -> int:
        """The open file's size on disk: short of the encoder's unflushed buffer (tens of kB)."""
        return self.path.stat().st_size if self.path is not None and self.path.exists() else 0

    def write(self, frame: np.ndarray, episode_id: str) -> None:
        if self.shape is None:
            self.shape = frame.shape[:2]
            if self.shape[0] % 2 or self.shape[1] % 2:
                raise ExportError(f"images are {self.shape[0]}x{self.shape[1]}: yuv420p video needs even sizes")
        if frame.shape[:2] != self.shape:
            raise ExportError(
                f"episode {episode_id} has {frame.shape[0]}x{frame.shape[1]} images, earlier ones "
                f"{self.shape[0]}x{self.shape[1]}: narrow the selection with --where"
            )
        if self.encoder is None:
            self.path = self.root / VIDEO_PATH.format(video_key=self.video_key, chunk_index=self.chunk,
                                                      file_index=self.file)
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self.encoder = video_writer(self.path, self.fps)
        self.encoder.append_data(frame)
        self.frames += 1

    def close(self) -> None:
        if self.encoder is not None:
            self.encoder.close()
            self.encoder = None
            self.frames = 0  # the next file's timestamps start at 0


def _stats(x: np.ndarray, count: int) -> dict[str, np.ndarray]:
    """LeRobot's per-episode stats of samples x (n, dims), per dimension; min and max keep x's
    dtype (int, bool) as LeRobot's do, so its tools can merge these files with its own."""
    q = np.quantile(x.astype(np.float64), list(QUANTILES.values()), axis=0)
    return {
        "min": x.min(0), "max": x.max(0), "mean": x.mean(0, dtype=np.float64), "std": x.std(0, dtype=np.float64),
        "count": np.array([count]),
        **{name: q[i] for i, name in enumerate(QUANTILES)},
    }


def _image_stats(frames: np.ndarray) -> dict[str, np.ndarray]:
    """LeRobot's image stats: per channel, pixels scaled to [0, 1], shaped (3, 1, 1), count in
    frames. Exact, from 256-bin histograms of the uint8 pixels (sorting them is 20x slower)."""
    hist = np.zeros((3, 256), np.int64)
    for first in range(0, len(frames), 64):  # a few frames at a time: bincount widens to int64
        for c in range(3):
            hist[c] += np.bincount(frames[first : first + 64, ..., c].ravel(), minlength=256)
    levels = np.arange(256) / 255.0
    n = hist[0].sum()
    cum = hist.cumsum(1)

    def sorted_at(k: np.ndarray) -> np.ndarray:  # the k-th smallest pixel of each channel
        return levels[[np.searchsorted(cum[c], k[c], side="right") for c in range(3)]]

    mean = hist @ levels / n
    stats = {
        "min": sorted_at(np.zeros(3)), "max": sorted_at(np.full(3, n - 1)), "mean": mean,
        "std": np.sqrt(np.maximum(hist @ levels**2 / n - mean**2, 0.0)), "count": np.array([len(frames)]),
    }
    for name, q in QUANTILES.items():  # numpy's default ("linear") quantile
        low = np.floor(q * (n - 1))
        stats[name] = sorted_at(np.full(3, low)) + (q * (n - 1) - low) * (
            sorted_at(np.full(3, min(low + 1, n - 1))) - sorted_at(np.full(3, low)))
    return {k: v if k == "count" else v.reshape(3, 1, 1) for k, v in stats.items()}


class _Aggregate:
    """Dataset stats from episode stats as LeRobot's aggregate_stats makes them: count-weighted
    mean and variance, min of mins, max of maxes, and each quantile the count-weighted mean of the
    episodes' (an estimate, as LeRobot's: not the pooled frames' quantile)."""

    def __init__(self) -> None:
        self.acc: dict[str, dict[str, np.ndarray]] = {}

    def add(self, stats: dict[str, dict[str, np.ndarray]]) -> None:
        for feature, s in stats.items():
            n = float(s["count"][0])
            new = {"n": np.array(n), "sum": s["mean"] * n, "sumsq": (s["std"] ** 2 + s["mean"] ** 2) * n,
                   "min": s["min"], "max": s["max"], **{q: s[q] * n for q in QUANTILES}}
            a = self.acc.setdefault(feature, new)
            if a is new:
                continue
            for key in ("n", "sum", "sumsq", *QUANTILES):
                a[key] = a[key] + new[key]
            a["min"], a["max"] = np.minimum(a["min"], new["min"]), np.maximum(a["max"], new["max"])

    def result(self) -> dict[str, dict[str, list]]:
        out = {}
        for feature, a in self.acc.items():
            mean = a["sum"] / a["n"]
            std = np.sqrt(np.maximum(a["sumsq"] / a["n"] - mean**2, 0.0))
            out[feature] = {"min": a["min"].tolist(), "max": a["max"].tolist(), "mean": mean.tolist(),
                            "std": std.tolist(), "count": [int(a["n"])],
                            **{q: (a[q] / a["n"]).tolist() for q in QUANTILES}}
        return out


def _hf_feature(dtype: str, shape: tuple[int, ...]) -> dict:
    """The `datasets` feature LeRobot declares for a column (schema metadata of its parquet)."""
    value = {"dtype": dtype, "_type": "Value"}
    return value if shape == (1,) else {"feature": value, "length": shape[0], "_type": "List"}


class _Writer:
    def __init__(self, root: Path, fps: int, state_dim: int, action_dim: int, data_mb: float, video_mb: float):
        self.root, self.fps = root, fps
        self.features: dict[str, dict] = {}  # filled below, the camera's once its size is known
        if state_dim:
            self.features["observation.state"] = _vector("float32", state_dim, "state")
        self.features["action"] = _vector("float32", action_dim, "action")
        for name, dtype in [("next.reward", "float32"), ("next.done", "bool"), ("next.success", "bool"),
                            ("timestamp", "float32"), ("frame_index", "int64"), ("episode_index", "int64"),
                            ("index", "int64"), ("task_index", "int64")]:
            self.features[name] = {"dtype": dtype, "shape": (1,), "names": None}
        hf = {k: _hf_feature(f["dtype"], f["shape"]) for k, f in self.features.items()}
        self.hf_metadata = {b"huggingface": json.dumps({"info": {"features": hf}}).encode()}
        self.data = _RollingParquet(root, DATA_PATH, data_mb)
        self.meta = _RollingParquet(root, EPISODES_PATH, data_mb)
        self.videos: dict[str, _Videos] = {}  # camera -> its files, once the first episode shows one view or two
        self.limits = (data_mb, video_mb)
        self.tasks: dict[str, int] = {}
        self.stats = _Aggregate()
        self.rows: list[dict] = []  # episodes metadata not yet written
        self.episode_ids: list[str] = []  # by episode_index, for meta/sim2act_episodes.parquet
        self.frames = self.episodes = 0

    def add_episode(self, steps: pa.Table) -> None:
        n = steps.num_rows
        episode_id = steps["episode_id"][0].as_py()
        views = self._views(np.stack([decode_frame(b) for b in steps["image"].to_pylist()]), episode_id)
        placed = {}  # camera -> (chunk, file, from_timestamp)
        for camera, frames in views.items():
            placed[camera] = self.videos[camera].start_episode()
            for frame in frames:
                self.videos[camera].write(np.ascontiguousarray(frame), episode_id)

        # One task per instruction said; an episode's frames may carry more than one.
        instructions = steps["instruction"].to_pylist()
        for text in instructions:
            self.tasks.setdefault(text, len(self.tasks))
        columns: dict[str, np.ndarray] = {}
        if "observation.state" in self.features:
            columns["observation.state"] = _matrix(steps["proprio"], n)
        columns["action"] = _matrix(steps["action"], n)
        columns["next.reward"] = pc.fill_null(steps["reward"], 0.0).to_numpy().astype(np.float32)
        columns["next.done"] = pc.fill_null(steps["done"], False).to_numpy(zero_copy_only=False)
        columns["next.success"] = pc.fill_null(steps["success"], False).to_numpy(zero_copy_only=False)
        columns["timestamp"] = (np.arange(n) / self.fps).astype(np.float32)  # the frame's time in its video
        columns["frame_index"] = np.arange(n, dtype=np.int64)
        columns["episode_index"] = np.full(n, self.episodes, dtype=np.int64)
        columns["index"] = np.arange(self.frames, self.frames + n, dtype=np.int64)
        columns["task_index"] = np.array([self.tasks[t] for t in instructions], dtype=np.int64)

        # Vectors as fixed-size lists, the arrow type `datasets` gives LeRobot's fixed-length features.
        arrays = {k: pa.FixedSizeListArray.from_arrays(pa.array(v.ravel()), v.shape[1]) if v.ndim == 2 else pa.array(v)
                  for k, v in columns.items()}
        table = pa.table(arrays).replace_schema_metadata(self.hf_metadata)
        data_chunk, data_file = self.data.write(table)

        stats = {camera: _image_stats(frames) for camera, frames in views.items()}
        for name, values in columns.items():
            stats[name] = _stats(values.reshape(n, -1), n)
        self.stats.add(stats)
        row = {
            "episode_index": self.episodes, "tasks": list(dict.fromkeys(instructions)), "length": n,
            "data/chunk_index": data_chunk, "data/file_index": data_file,
            "dataset_from_index": self.frames, "dataset_to_index": self.frames + n,
            **{key: value for camera, (chunk, file, from_ts) in placed.items() for key, value in (
                (f"videos/{camera}/chunk_index", chunk), (f"videos/{camera}/file_index", file),
                (f"videos/{camera}/from_timestamp", from_ts), (f"videos/{camera}/to_timestamp", from_ts + n / self.fps))},
            **{f"stats/{feature}/{k}": v.tolist() for feature, s in stats.items() for k, v in s.items()},
            "meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0,  # set when written
        }
        self.rows.append(row)
        self.episode_ids.append(episode_id)
        self.frames += n
        self.episodes += 1
        if len(self.rows) >= 1000:
            self._flush_rows()

    def _views(self, images: np.ndarray, episode_id: str) -> dict[str, np.ndarray]:
        """An episode's frames (n, H, W, 3) by camera: one square view, or the main and the hand's side by side."""
        height, width = images.shape[1:3]
        cameras = [CAMERA] if width != 2 * height else [CAMERA, WRIST_CAMERA]
        if not self.videos:
            self.videos = {camera: _Videos(self.root, self.fps, self.limits[1], camera) for camera in cameras}
        elif list(self.videos) != cameras:
            raise ExportError(f"episode {episode_id} has {height}x{width} images ({len(cameras)} camera view(s)), "
                              f"earlier ones {len(self.videos)}: narrow the selection with --where")
        return {camera: images[:, :, i * height:(i + 1) * height] for i, camera in enumerate(cameras)}

    def _flush_rows(self) -> None:
        if not self.rows:
            return
        schema = self.meta.writer.schema if self.meta.writer is not None else None
        table = pa.Table.from_pylist(self.rows, schema=schema)
        chunk, file = self.meta.place(table.nbytes)
        for name, value in (("meta/episodes/chunk_index", chunk), ("meta/episodes/file_index", file)):
            column = pa.array([value] * len(self.rows), pa.int64())
            table = table.set_column(table.schema.get_field_index(name), name, column)
        self.meta.write(table)
        self.rows = []

    def finish(self, repo_id: str, robot_type: str | None) -> None:
        self._flush_rows()
        for part in (self.data, self.meta, *self.videos.values()):
            part.close()
        cameras = {camera: videos.shape or (0, 0) for camera, videos in self.videos.items()} or {CAMERA: (0, 0)}
        features = {camera: _video_feature(height, width, self.fps) for camera, (height, width) in cameras.items()}
        features |= {k: {**f, "shape": list(f["shape"])} for k, f in self.features.items()}
        info = {
            "codebase_version": CODEBASE_VERSION, "robot_type": robot_type, "total_episodes": self.episodes,
            "total_frames": self.frames, "total_tasks": len(self.tasks), "chunks_size": CHUNKS_SIZE,
            "data_files_size_in_mb": self.limits[0], "video_files_size_in_mb": self.limits[1], "fps": self.fps,
            "splits": {"train": f"0:{self.episodes}"}, "data_path": DATA_PATH, "video_path": VIDEO_PATH,
            "features": features,
        }
        meta = self.root / "meta"
        (meta / "info.json").write_text(json.dumps(info, indent=4))
        (meta / "stats.json").write_text(json.dumps(self.stats.result(), indent=4))
        tasks = pd.DataFrame({"task_index": list(self.tasks.values())}, index=pd.Index(list(self.tasks), name="task"))
        tasks.to_parquet(meta / "tasks.parquet")
        # Not LeRobot's (it reads only the files above): where each episode came from.
        pq.write_table(pa.table({"episode_index": pa.array(range(self.episodes), pa.int64()),
                                 "episode_id": pa.array(self.episode_ids, pa.string())}),
                       meta / "sim2act_episodes.parquet")
        (self.root / "README.md").write_text(
            f"---\ntags: [LeRobot, sim2act]\ntask_categories: [robotics]\nconfigs:\n- config_name: default\n"
            f"  data_files: data/*/*.parquet\n---\n\n# {repo_id}\n\nLeRobotDataset {CODEBASE_VERSION} exported by "
            f"sim2act: {self.episodes} episodes, {self.frames} frames, {len(self.tasks)} tasks. "
            "meta/sim2act_episodes.parquet maps episode_index to the warehouse's episode_id.\n"
        )


def _video_feature(height: int, width: int, fps: int) -> dict:
    return {
        "dtype": "video", "shape": [height, width, 3], "names": ["height", "width", "channels"],
        "info": {"video.height": height, "video.width": width, "video.codec": VIDEO_CODEC,
                 "video.pix_fmt": "yuv420p", "video.is_depth_map": False, "is_depth_map": False,
                 "video.fps": fps, "video.channels": 3, "has_audio": False},
    }


def _vector(dtype: str, dim: int, prefix: str) -> dict:
    return {"dtype": dtype, "shape": (dim,), "names": [f"{prefix}_{i}" for i in range(dim)]}


def _matrix(column: pa.ChunkedArray, n: int) -> np.ndarray:
    return pc.list_flatten(column).to_numpy().astype(np.float32).reshape(n, -1)



