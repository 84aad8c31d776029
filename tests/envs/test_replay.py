"""sim2act replay: episodes explored for real (robosuite Lift, navigation, MetaWorld reach; domain
randomisation on), stored and registered, then re-rendered from the MuJoCo states their steps keep."""

import imageio.v2 as iio
import numpy as np
import pytest

from envs.replay import load_episode, replay_frames, replay_render
from envs.suite import generate_tasks
from flows.cli import main
from schemas.config import CampaignConfig
from schemas.frames import decode_frame
from schemas.workspace import Workspace
from tests.explored import explored_workspace
from warehouse.catalog import Catalog
from warehouse.tasks import task_rows

STEPS = 8
TASKS = {"robosuite": "lift-red", "navigation": "nav-ball-blue", "metaworld": "mw-reach"}
CONFIG = CampaignConfig.model_validate({
    "name": "replay",
    "tasks": {"specs": ["lift", "nav-ball", "mw-reach"], "include": list(TASKS.values()), "weak_experts": "keep",
              "horizon": {"lift": STEPS, "nav-ball": STEPS, "mw-reach": STEPS}},
    "explore": {"episodes_per_task": 1, "episodes_per_shard": 1},
})


@pytest.fixture(scope="module")
def workspace(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    """One real explore unit per family (84 px agentview, default randomisation), registered."""
    return explored_workspace(tmp_path_factory.mktemp("replay"), CONFIG)


def _episode_id(workspace: Workspace, family: str) -> str:
    [(episode_id,)] = Catalog(workspace.catalog).query(
        "SELECT episode_id FROM episodes WHERE task_id = ?", [TASKS[family]])
    return episode_id


def _stored_frames(workspace: Workspace, episode_id: str) -> list[np.ndarray]:
    rows = Catalog(workspace.catalog).query("SELECT image FROM steps WHERE episode_id = ? ORDER BY step", [episode_id])
    return [decode_frame(image) for (image,) in rows]


def _video_frames(path) -> list[np.ndarray]:
    with iio.get_reader(path, format="FFMPEG") as reader:
        return list(reader.iter_data())


@pytest.mark.parametrize("family", TASKS)
def test_replay_reproduces_every_stored_frame_pixel_for_pixel(workspace, family):
    episode = load_episode(Catalog(workspace.catalog), _episode_id(workspace, family))
    assert episode.randomisation is not None and episode.randomisation.light is not None
    stored = _stored_frames(workspace, episode.episode_id)
    replayed = list(replay_frames(episode, replay_render(episode)))
    assert len(replayed) == len(stored) == len(episode.states) > 1
    for step, (frame, original) in enumerate(zip(replayed, stored)):
        differing = int((frame != original).any(-1).sum())
        assert differing == 0, f"step {step}: {differing} pixels differ"
    assert min(frame.mean() for frame in stored) > 20  # real frames, not two black ones alike


def test_replay_at_another_size_gives_frames_of_that_size(workspace):
    episode = load_episode(Catalog(workspace.catalog), _episode_id(workspace, "robosuite"))
    frames = list(replay_frames(episode, replay_render(episode, size=64)))
    assert [f.shape for f in frames] == [(64, 64, 3)] * len(episode.states)
    assert min(f.mean() for f in frames) > 20


@pytest.mark.parametrize(("family", "camera"), [("robosuite", "frontview"), ("navigation", "birdview")])
def test_another_camera_gives_other_frames(workspace, family, camera):
    episode = load_episode(Catalog(workspace.catalog), _episode_id(workspace, family))
    stored = _stored_frames(workspace, episode.episode_id)
    frames = list(replay_frames(episode, replay_render(episode, camera=camera)))
    assert len(frames) == len(stored)
    for frame, original in zip(frames, stored):
        assert frame.shape == original.shape and (frame != original).any(-1).mean() > 0.2


def test_the_cli_writes_an_mp4_with_one_frame_per_step(workspace, tmp_path, capsys, monkeypatch):
    episode_id, root = _episode_id(workspace, "navigation"), str(workspace.root)
    out = tmp_path / "x.mp4"
    assert main(["replay", episode_id, "--workspace", root, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"{STEPS} frames of {episode_id}" in printed and str(out) in printed
    frames = _video_frames(out)
    stored = _stored_frames(workspace, episode_id)
    assert len(frames) == len(stored) == STEPS
    # H.264 is lossy: the video is near the stored frames, not equal to them
    assert max(np.abs(f.astype(int) - s.astype(int)).mean() for f, s in zip(frames, stored)) < 8
    import cv2

    assert cv2.VideoCapture(str(out)).get(cv2.CAP_PROP_FPS) == 10  # navigation's 10 steps a second, in real time

    monkeypatch.chdir(tmp_path)  # no --out: a file named after the episode, in the current folder
    assert main(["replay", episode_id, "--workspace", root, "--camera", "birdview", "--size", "64"]) == 0
    default = tmp_path / f"{episode_id}_birdview_64px.mp4"
    assert str(default.name) in capsys.readouterr().out
    assert [f.shape for f in _video_frames(default)] == [(64, 64, 3)] * STEPS


@pytest.mark.parametrize(("args", "message"), [
    (["no-such-episode"], "sim2act: replay: no episode 'no-such-episode' in "),
    (["{robosuite}", "--camera", "wrist"],
     "sim2act: replay: robosuite environment Lift has no camera 'wrist' (valid: agentview, frontview, birdview, "
     "sideview)"),
    (["{navigation}", "--size", "85"], "sim2act: replay: --size must be even for an MP4 (yuv420p), got 85"),
    (["{navigation}", "--size", "8"], "sim2act: replay: --size 8: Input should be greater than or equal to 32"),
])
def test_a_bad_request_is_one_line_before_anything_is_rendered(workspace, tmp_path, capsys, monkeypatch, args,
                                                               message):
    def must_not_render(*_):
        raise AssertionError("rendered before every check passed")

    monkeypatch.setattr("envs.replay.replay_frames", must_not_render)
    args = [a.format(**{family: _episode_id(workspace, family) for family in TASKS}) for a in args]
    out = tmp_path / "x.mp4"
    assert main(["replay", *args, "--workspace", str(workspace.root), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.parametrize(("family", "setting", "field"), [
    ("robosuite", {"mesh_detail": 0.1}, "mesh_detail"), ("robosuite", {"wrist_camera": True}, "wrist_camera"),
    ("metaworld", {"mesh_detail": 0.1, "decimate_colliding": True}, "decimate_colliding")])
def test_an_episode_explored_with_later_render_settings_replays_with_them(tmp_path, monkeypatch, family, setting,
                                                                          field):
    """render.mesh_detail, render.wrist_camera and render.decimate_colliding are not columns of episodes.render
    (a shard schema older than them): the explore stage records them in its unit's summary, and replay reads
    them there, so the frames are the stored ones (with the wrist camera, the hand's view beside the main one)."""
    from schemas.config import RenderConfig
    from stages.explore import run_explore

    monkeypatch.setenv("SIM2ACT_CACHE_DIR", str(tmp_path / "cache"))
    config = CONFIG.model_copy(update={"render": RenderConfig(**setting),
                                       "explore": CONFIG.explore.model_copy(update={"workers": 1})})
    workspace = Workspace.at(tmp_path / "explored").create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    tasks = [t for t in generate_tasks(config.tasks, config.seed) if t.task_id == TASKS[family]]
    catalog.register_unit(unit_key="tasks", stage="generate_tasks", campaign=config.name, iteration=0, summary={},
                          rows={"tasks": task_rows(tasks, config.name, "tasks")})
    run_explore(workspace, config, 0, tasks, None, {})
    [(episode_id,)] = catalog.query("SELECT episode_id FROM episodes")
    episode = load_episode(catalog, episode_id)
    assert episode.render == config.render
    stored, replayed = _stored_frames(workspace, episode_id), list(replay_frames(episode, replay_render(episode)))
    assert stored[0].shape == (84, 84 * config.render.views, 3)
    assert len(replayed) == len(stored) > 1 and all(np.array_equal(a, b) for a, b in zip(replayed, stored))
    default = {field: RenderConfig.model_fields[field].default}
    plain = list(replay_frames(episode, replay_render(episode).model_copy(update=default)))
    assert not all(np.array_equal(a, b) for a, b in zip(plain, stored))  # that field at its default: other pixels


def test_a_relabelled_episode_replays_as_the_task_it_set_out_for(tmp_path):
    """A relabelled episode is filed as the task it ended doing; its scene was laid out for the one it set
    out for (navigation's rooms and start depend on the goal), so replay resets as that one."""
    config = CampaignConfig.model_validate({
        "name": "replay-relabel",
        "tasks": {"specs": ["nav-room"], "colours": ["red", "green", "blue", "yellow"], "unseen_colours": ["yellow"],
                  "horizon": {"nav-room": 6}},
        "explore": {"episodes_per_task": 6, "episodes_per_shard": 6, "workers": 1, "relabel": True},
    })
    workspace = explored_workspace(tmp_path, config)
    rows = Catalog(workspace.catalog).query(
        "SELECT episode_id, task_id, json_extract_string(explorer_stats, '$.relabelled_from') FROM episodes "
        "WHERE explorer_stats LIKE '%relabelled_from%' ORDER BY episode_id")
    assert rows, "no episode ended in another seen task's room"
    episode_id, filed_as, intended = rows[0]
    episode = load_episode(Catalog(workspace.catalog), episode_id)
    assert episode.task.task_id == intended != filed_as
    stored = _stored_frames(workspace, episode_id)
    replayed = list(replay_frames(episode, replay_render(episode)))
    assert all(np.array_equal(frame, original) for frame, original in zip(replayed, stored)) and len(replayed) == len(stored)
