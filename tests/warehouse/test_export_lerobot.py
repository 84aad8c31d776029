"""The LeRobot v3.0 export, read back file by file against LeRobot's documented layout
(lerobot/datasets/utils.py path templates, dataset_writer.py episode metadata, compute_stats.py
stats shapes), on a small real warehouse: 3 episodes over 2 tasks, one rejected by the filter."""

import json

import cv2
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from schemas.frames import encode_frame
from schemas.tables import CATALOG_TABLES, EPISODES, FILTER_DECISIONS, STEPS
from schemas.workspace import Workspace
from warehouse.catalog import Catalog
from warehouse.export_lerobot import CAMERA, WRIST_CAMERA, ExportError, _Videos, export_lerobot
from warehouse.shard_writer import write_shard

SIZE = 84  # not a multiple of 16: the encoder must not pad it
LIFT, STACK = "lift the red cube", "stack the blue block"
# episode_id -> (task_id, instruction, steps, kept, action dim)
EPISODES_SPEC = {
    "ep-a": ("lift-red", LIFT, 6, True, 7),
    "ep-b": ("lift-red", LIFT, 8, False, 7),
    "ep-c": ("stack-blue", STACK, 5, True, 7),
}


def _row(schema: pa.Schema, **values) -> dict:
    """A row of `schema`: the given values, None in every other (nullable) column, so columns
    added to the schema later leave this test working."""
    unknown = set(values) - set(schema.names)
    assert not unknown, f"not in the schema: {unknown}"
    return {f.name: values.get(f.name) for f in schema}


def _frame(episode: int, step: int) -> np.ndarray:
    """A distinct flat colour per frame, with a white square that moves with the step."""
    g = episode * 16 + step + 1
    img = np.empty((SIZE, SIZE, 3), np.uint8)
    img[:] = ((37 * g) % 200 + 30, (91 * g) % 200 + 30, (151 * g) % 200 + 30)
    img[10 + 4 * step : 26 + 4 * step, 20:36] = 255
    return img


def _build(root, spec=EPISODES_SPEC, wrist: set[str] = frozenset()) -> tuple[Catalog, dict]:
    """Write and register one unit of episodes, steps and filter decisions; -> the catalog and
    the frames and actions written, by episode_id. Episodes in `wrist` have two-view frames (render.wrist_camera):
    the hand's view a step further on."""
    ws = Workspace.at(root).create()
    catalog = Catalog(ws.catalog)
    catalog.initialise()
    rng = np.random.default_rng(0)
    episodes, steps, decisions, truth = [], [], [], {}
    for e, (episode_id, (task_id, instruction, n, kept, action_dim)) in enumerate(spec.items()):
        common = dict(campaign="t", iteration=0, episode_id=episode_id, task_id=task_id)
        # ep-b succeeded and was rejected all the same (its return): an export must select on the filter, not success
        succeeded = kept or episode_id == "ep-b"
        frames = [np.concatenate([_frame(e, s), _frame(e, s + 1)], axis=1) if episode_id in wrist else _frame(e, s)
                  for s in range(n)]
        actions = rng.uniform(-1, 1, (n, action_dim)).astype(np.float32)
        proprio = rng.uniform(-1, 1, (n, 9)).astype(np.float32)
        truth[episode_id] = {"frames": frames, "actions": actions, "proprio": proprio}
        episodes.append(_row(EPISODES, **common, instruction=instruction, explorer="expert", seed=e,
                             shard_key="explore-0", num_steps=n, episode_return=float(n), success=succeeded))
        for s in range(n):
            steps.append(_row(
                STEPS, **common, step=s, instruction=instruction, image=encode_frame(frames[s]),
                proprio=proprio[s].tolist(), action=actions[s].tolist(), reward=float(s) / n, done=s == n - 1,
                success=succeeded and s == n - 1, next_image=encode_frame(frames[s]) if s == n - 1 else None,
                sim_time=s * 0.05,
            ))
        decisions.append(_row(FILTER_DECISIONS, **common, kept=kept, reason="kept" if kept else "low_return",
                              episode_return=float(n), filter_key="filter-0"))
    shards = [
        write_shard(name, pa.Table.from_pylist(rows, schema=schema), ws.shard_path(name, 0, key))
        for name, rows, schema, key in [
            ("episodes", episodes, EPISODES, "explore-0"), ("steps", steps, STEPS, "explore-0"),
            ("filter_decisions", decisions, FILTER_DECISIONS, "filter-0"),
        ]
    ]
    tasks = [
        _row(CATALOG_TABLES["tasks"].schema, campaign="t", task_id=task_id, unit_key="u0",
             family={"nav": "navigation", "mw-": "metaworld"}.get(task_id[:3], "robosuite"))
        for task_id in sorted({task_id for task_id, *_ in spec.values()})
    ]
    catalog.register_unit(unit_key="u0", stage="explore", campaign="t", iteration=0, summary={}, shards=shards,
                          rows={"tasks": tasks})
    return catalog, truth


@pytest.fixture(scope="module")
def warehouse(tmp_path_factory):
    return _build(tmp_path_factory.mktemp("ws"))


def _decode(path) -> list[np.ndarray]:
    video = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = video.read()
        if not ok:
            break
        frames.append(frame[..., ::-1])  # BGR -> RGB
    video.release()
    return frames


def test_export_writes_a_lerobot_v3_dataset(warehouse, tmp_path):
    catalog, truth = warehouse
    out = tmp_path / "lerobot"
    calls = []
    summary = export_lerobot(catalog, out, progress=lambda done, total: calls.append((done, total)))
    kept = ["ep-a", "ep-c"]  # ep-b was rejected by the filter
    lengths = [len(truth[e]["actions"]) for e in kept]
    total = sum(lengths)
    assert (summary.episodes, summary.frames, summary.tasks, summary.out_dir) == (2, total, 2, out)
    assert calls == [(1, 2), (2, 2)]
    assert [p.name for p in tmp_path.iterdir()] == ["lerobot"]  # no temporary folder left beside it

    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file())
    assert files == [
        "README.md", "data/chunk-000/file-000.parquet", "meta/episodes/chunk-000/file-000.parquet",
        "meta/info.json", "meta/sim2act_episodes.parquet", "meta/stats.json", "meta/tasks.parquet",
        f"videos/{CAMERA}/chunk-000/file-000.mp4",
    ]
    assert summary.bytes == sum((out / f).stat().st_size for f in files)

    info = json.loads((out / "meta/info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["robot_type"] == "panda"  # robosuite's arm
    assert (info["total_episodes"], info["total_frames"], info["total_tasks"], info["fps"]) == (2, total, 2, 20)
    assert info["splits"] == {"train": "0:2"}
    assert info["data_path"] == "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
    assert info["video_path"] == "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
    assert (info["chunks_size"], info["data_files_size_in_mb"], info["video_files_size_in_mb"]) == (1000, 100, 200)
    features = info["features"]
    assert list(features) == [CAMERA, "observation.state", "action", "next.reward", "next.done", "next.success",
                              "timestamp", "frame_index", "episode_index", "index", "task_index"]
    assert features[CAMERA]["dtype"] == "video" and features[CAMERA]["shape"] == [SIZE, SIZE, 3]
    assert features[CAMERA]["names"] == ["height", "width", "channels"]
    assert features[CAMERA]["info"]["video.codec"] in ("h264", "mpeg4")
    assert features[CAMERA]["info"]["video.fps"] == 20 and features[CAMERA]["info"]["video.pix_fmt"] == "yuv420p"
    assert features["action"] == {"dtype": "float32", "shape": [7], "names": [f"action_{i}" for i in range(7)]}
    assert features["observation.state"]["shape"] == [9]
    assert features["index"] == {"dtype": "int64", "shape": [1], "names": None}

    tasks = pd.read_parquet(out / "meta/tasks.parquet")
    assert tasks.index.name == "task" and tasks["task_index"].to_dict() == {LIFT: 0, STACK: 1}

    episodes = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    starts = np.cumsum([0, *lengths])
    for i, ep in enumerate(episodes):
        assert ep["episode_index"] == i and ep["length"] == lengths[i]
        assert ep["tasks"] == [[LIFT], [STACK]][i]
        assert (ep["dataset_from_index"], ep["dataset_to_index"]) == (starts[i], starts[i + 1])
        assert (ep["data/chunk_index"], ep["data/file_index"], ep["meta/episodes/chunk_index"]) == (0, 0, 0)
        assert (ep[f"videos/{CAMERA}/chunk_index"], ep[f"videos/{CAMERA}/file_index"]) == (0, 0)
        assert ep[f"videos/{CAMERA}/from_timestamp"] == pytest.approx(starts[i] / 20)
        assert ep[f"videos/{CAMERA}/to_timestamp"] == pytest.approx(starts[i + 1] / 20)
        assert np.asarray(ep[f"stats/{CAMERA}/mean"]).shape == (3, 1, 1)
        assert ep["stats/action/min"] == pytest.approx(truth[kept[i]]["actions"].min(0).tolist())
        assert ep["stats/action/count"] == [lengths[i]]
    ids = pq.read_table(out / "meta/sim2act_episodes.parquet").to_pydict()
    assert ids == {"episode_index": [0, 1], "episode_id": kept}

    data_file = pq.ParquetFile(out / "data/chunk-000/file-000.parquet")
    assert data_file.num_row_groups == 2  # one per episode, as LeRobot writes them
    assert data_file.schema_arrow.field("action").type == pa.list_(pa.float32(), 7)
    assert b"huggingface" in data_file.schema_arrow.metadata
    data = data_file.read().to_pydict()
    assert list(data) == [k for k in features if k != CAMERA]
    assert data["index"] == list(range(total))
    assert data["frame_index"] == [f for n in lengths for f in range(n)]
    assert data["episode_index"] == [i for i, n in enumerate(lengths) for _ in range(n)]
    assert data["timestamp"] == pytest.approx([f / 20 for f in data["frame_index"]])
    assert data["task_index"] == [i for i, n in enumerate(lengths) for _ in range(n)]
    assert np.array_equal(np.array(data["action"], np.float32), np.concatenate([truth[e]["actions"] for e in kept]))
    assert np.array_equal(np.array(data["observation.state"], np.float32),
                          np.concatenate([truth[e]["proprio"] for e in kept]))
    assert data["next.done"] == [f == n - 1 for n in lengths for f in range(n)]
    assert data["next.success"] == data["next.done"]

    stats = json.loads((out / "meta/stats.json").read_text())
    assert set(stats) == set(features)
    actions = np.concatenate([truth[e]["actions"] for e in kept])
    assert stats["action"]["mean"] == pytest.approx(actions.mean(0).tolist(), abs=1e-6)
    assert stats["action"]["std"] == pytest.approx(actions.std(0).tolist(), abs=1e-6)
    assert stats["action"]["min"] == pytest.approx(actions.min(0).tolist())
    assert stats["action"]["count"] == [total]
    assert set(stats["action"]) == {"min", "max", "mean", "std", "count", "q01", "q10", "q50", "q90", "q99"}
    # each quantile: the episodes' own, weighted by their frames (LeRobot's aggregate_feature_stats)
    episode_q50 = np.stack([np.quantile(truth[e]["actions"], 0.5, axis=0) for e in kept])
    weights = np.array([len(truth[e]["actions"]) for e in kept], np.float64)[:, None]
    assert stats["action"]["q50"] == pytest.approx(((episode_q50 * weights).sum(0) / weights.sum()).tolist(), abs=1e-5)
    assert stats["index"]["max"] == [total - 1]
    pixels = np.stack([f for e in kept for f in truth[e]["frames"]]).reshape(-1, 3) / 255
    assert np.asarray(stats[CAMERA]["mean"]).shape == (3, 1, 1)
    assert np.asarray(stats[CAMERA]["mean"]).ravel() == pytest.approx(pixels.mean(0), abs=1e-6)

    # Every frame of the video is its step's stored frame, within the codec's loss, at its timestamp.
    decoded = _decode(out / f"videos/{CAMERA}/chunk-000/file-000.mp4")
    assert len(decoded) == total and decoded[0].shape == (SIZE, SIZE, 3)
    for i, episode_id in enumerate(kept):
        first = round(episodes[i][f"videos/{CAMERA}/from_timestamp"] * 20)
        for step, frame in enumerate(truth[episode_id]["frames"]):
            error = np.abs(decoded[first + step].astype(int) - frame.astype(int)).mean()
            assert error < 6, (episode_id, step, error)


def test_rejected_episodes_on_request_and_where_selects(warehouse, tmp_path):
    catalog, truth = warehouse
    every = export_lerobot(catalog, tmp_path / "all", include_rejected=True)
    assert (every.episodes, every.frames) == (3, 19)
    ids = pq.read_table(tmp_path / "all/meta/sim2act_episodes.parquet")["episode_id"].to_pylist()
    assert ids == ["ep-a", "ep-b", "ep-c"]

    stack = export_lerobot(catalog, tmp_path / "stack", where="task_id LIKE 'stack%' AND step >= 3")
    assert (stack.episodes, stack.frames, stack.tasks) == (1, 5, 1)  # the whole episode, not its matching steps
    tasks = pd.read_parquet(tmp_path / "stack/meta/tasks.parquet")
    assert tasks["task_index"].to_dict() == {STACK: 0}


def test_the_fetch_size_bounds_reads_not_the_dataset(warehouse, tmp_path, monkeypatch):
    """--fetch-mb: episodes read a few at a time (here one per query) make the same dataset."""
    catalog, _ = warehouse
    queries = []
    real = catalog.query_arrow
    monkeypatch.setattr(catalog, "query_arrow", lambda sql, params=(), **kw: queries.append(params) or real(sql, params, **kw))
    export_lerobot(catalog, tmp_path / "big")
    big = len(queries)
    export_lerobot(catalog, tmp_path / "small", fetch_mb=1e-6)
    assert (big, len(queries) - big) == (1, 2)  # the two kept episodes: in one query, then one each
    for name in ("data/chunk-000/file-000.parquet", "meta/episodes/chunk-000/file-000.parquet"):
        assert pq.read_table(tmp_path / "big" / name).equals(pq.read_table(tmp_path / "small" / name)), name


def test_files_roll_over_past_the_size_limits(warehouse, tmp_path, monkeypatch):
    catalog, truth = warehouse
    out = tmp_path / "small"
    # An open mp4 shows its size on disk only once the encoder flushes (every few tens of kB):
    # these tiny videos never would, so the test says the open file is full.
    monkeypatch.setattr(_Videos, "current_bytes", lambda self: 1 << 30)
    export_lerobot(catalog, out, data_files_size_in_mb=1e-4, video_files_size_in_mb=1e-4)
    episodes = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert [(e["data/file_index"], e[f"videos/{CAMERA}/file_index"]) for e in episodes] == [(0, 0), (1, 1)]
    assert episodes[1][f"videos/{CAMERA}/from_timestamp"] == 0.0  # a new file starts at 0
    second = pq.read_table(out / "data/chunk-000/file-001.parquet").to_pydict()
    assert second["index"][0] == episodes[1]["dataset_from_index"] == 6
    frames = _decode(out / f"videos/{CAMERA}/chunk-000/file-001.mp4")
    assert len(frames) == 5
    assert np.abs(frames[0].astype(int) - truth["ep-c"]["frames"][0].astype(int)).mean() < 6


def test_refusals_write_nothing(warehouse, tmp_path):
    catalog, _ = warehouse
    with pytest.raises(ExportError, match=r"--where 'no_such_column = 1': .*no_such_column"):
        export_lerobot(catalog, tmp_path / "a", where="no_such_column = 1")
    with pytest.raises(ExportError, match=r"--where 'task_id = ': Parser Error"):
        export_lerobot(catalog, tmp_path / "a", where="task_id = ")
    with pytest.raises(ExportError, match=r"file system operations are disabled"):
        export_lerobot(catalog, tmp_path / "outside", where="task_id IN (SELECT column0 FROM read_csv('/etc/passwd'))")
    with pytest.raises(ExportError, match="no episode matches .* among the episodes the filter kept"):
        export_lerobot(catalog, tmp_path / "a", where="task_id = 'nope'")
    with pytest.raises(ExportError, match="no episode matches"):
        export_lerobot(catalog, tmp_path / "a", where="episode_id = 'ep-b'")  # rejected
    used = tmp_path / "used"
    used.mkdir()
    (used / "keep.txt").write_text("mine")
    with pytest.raises(ExportError, match="is a folder with files in it: export into a new one"):
        export_lerobot(catalog, used)
    assert [p.name for p in used.iterdir()] == ["keep.txt"]
    with pytest.raises(ExportError, match=r"used/keep.txt is a file: export into a new folder"):
        export_lerobot(catalog, used / "keep.txt")
    with pytest.raises(ExportError, match=r"cannot make .*keep.txt/out: .*keep.txt is a file"):  # before the selection
        export_lerobot(catalog, used / "keep.txt" / "out", where="no_such_column = 1")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["used"]


def test_a_crash_leaves_no_partial_dataset(warehouse, tmp_path, monkeypatch):
    catalog, _ = warehouse
    import warehouse.export_lerobot as module

    def crash(done, total):
        raise RuntimeError("killed")

    with pytest.raises(RuntimeError, match="killed"):
        module.export_lerobot(catalog, tmp_path / "out", progress=crash)
    assert list(tmp_path.iterdir()) == []


def test_a_killed_exports_folder_is_removed_by_the_next_export_and_a_live_ones_kept(warehouse, tmp_path):
    """A SIGKILLed export runs no clean-up: its folder beside the output (a full-size copy) stays. The next
    export into the same place removes those whose process is gone on this host; a live one's is its own."""
    import subprocess
    import sys

    from warehouse.export_lerobot import _partial_folder

    catalog, _ = warehouse
    out = tmp_path / "out"
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    killed, live = _partial_folder(out, gone.pid), _partial_folder(out, 1)
    for folder in (killed, live):
        (folder / "data").mkdir(parents=True)
        (folder / "data" / "file-000.parquet").write_bytes(b"half")
    export_lerobot(catalog, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["out", live.name])


def test_mixed_action_shapes_are_refused_naming_both(tmp_path):
    spec = {"nav-1": ("nav-find-ball", "find the ball", 4, True, 1), **EPISODES_SPEC}
    catalog, _ = _build(tmp_path / "ws", spec)
    with pytest.raises(ExportError, match=r"mixes action shapes \(1,\) \(tasks nav-find-ball\) and \(7,\) "
                                          r"\(tasks lift-red, stack-blue\).*--where"):
        export_lerobot(catalog, tmp_path / "out")
    assert export_lerobot(catalog, tmp_path / "out", where="task_id LIKE 'nav%'").frames == 4
    assert json.loads((tmp_path / "out/meta/info.json").read_text())["fps"] == 10  # navigation's control rate


def test_each_family_plays_at_its_control_rate_and_a_mix_of_rates_asks_for_one(tmp_path):
    """MetaWorld steps at 80 Hz (frame_skip 5 of 2.5 ms), robosuite at 20: one dataset has one fps, so a
    selection of both is refused unless --fps says which; each alone takes its own."""
    spec = {"ep-mw": ("mw-reach", "reach the goal", 5, True, 7), **EPISODES_SPEC}
    catalog, _ = _build(tmp_path / "ws", spec)
    with pytest.raises(ExportError, match=r"mixes families of other control rates \(metaworld, robosuite: 80 Hz, "
                                          r"20 Hz\); pass --fps"):
        export_lerobot(catalog, tmp_path / "mixed")
    assert not (tmp_path / "mixed").exists()
    export_lerobot(catalog, tmp_path / "mw", where="task_id LIKE 'mw-%'")
    info = json.loads((tmp_path / "mw/meta/info.json").read_text())
    assert info["fps"] == 80 and info["features"][CAMERA]["info"]["video.fps"] == 80
    assert export_lerobot(catalog, tmp_path / "both", fps=20).frames == 5 + 6 + 5  # the kept episodes, at 20
    assert json.loads((tmp_path / "both/meta/info.json").read_text())["fps"] == 20


def test_two_view_frames_go_out_as_two_cameras(tmp_path):
    """render.wrist_camera frames (84x168: the main view, the hand's) become LIBERO's two cameras, each
    its own 84x84 video, stats and episode entries; a selection mixing one and two views is refused."""
    catalog, truth = _build(tmp_path / "ws", wrist=set(EPISODES_SPEC))
    out = tmp_path / "lerobot"
    summary = export_lerobot(catalog, out)
    kept = ["ep-a", "ep-c"]
    info = json.loads((out / "meta/info.json").read_text())
    assert list(info["features"])[:2] == [CAMERA, WRIST_CAMERA]
    assert all(info["features"][c]["shape"] == [SIZE, SIZE, 3] for c in (CAMERA, WRIST_CAMERA))
    stats = json.loads((out / "meta/stats.json").read_text())
    for side, camera in enumerate((CAMERA, WRIST_CAMERA)):
        views = [f[:, side * SIZE:(side + 1) * SIZE] for e in kept for f in truth[e]["frames"]]
        assert np.asarray(stats[camera]["mean"]).ravel() == pytest.approx(
            np.stack(views).reshape(-1, 3).mean(0) / 255, abs=1e-6)
        decoded = _decode(out / f"videos/{camera}/chunk-000/file-000.mp4")
        assert len(decoded) == summary.frames == len(views)
        assert max(np.abs(d.astype(int) - v.astype(int)).mean() for d, v in zip(decoded, views)) < 6
    [first, _] = pq.read_table(out / "meta/episodes/chunk-000/file-000.parquet").to_pylist()
    assert first[f"videos/{WRIST_CAMERA}/to_timestamp"] == first[f"videos/{CAMERA}/to_timestamp"] > 0

    mixed, _ = _build(tmp_path / "mixed", wrist={"ep-c"})
    with pytest.raises(ExportError, match=r"episode ep-c has 84x168 images \(2 camera view\(s\)\), earlier ones 1"):
        export_lerobot(mixed, tmp_path / "out-mixed")
    assert not (tmp_path / "out-mixed").exists()
