"""Real MetaWorld v3 behind the common interface, rendered offscreen on the CPU."""

import numpy as np
import pyarrow.parquet as pq
import pytest

from envs.metaworld_env import MetaWorldEnv
from envs.observation import ACTION_DIM, PROPRIO_DIM
from envs.registry import make_expert
from envs.rollout import rollout
from envs.suite import generate_tasks
from schemas.config import CampaignConfig, RenderConfig
from schemas.config import TasksConfig
from schemas.workspace import Workspace
from stages.explore import plan_explore, run_explore_unit


@pytest.fixture(scope="module")
def pick_place():
    [task] = generate_tasks(TasksConfig(specs=["mw-pick-place"]), seed=0)
    env = MetaWorldEnv("pick-place-v3", RenderConfig(depth=True))  # the RGB-only path: the explore unit test
    yield env, task
    env.close()


def test_the_scripted_policy_solves_pick_place_through_our_interface(pick_place):
    env, task = pick_place
    act = make_expert(task, noise=0.1, rng=np.random.default_rng(0))
    rows, final, success = rollout(env, task, seed=4, act=act)
    assert success and len(rows) < task.horizon
    assert final.image.shape == (84, 84, 3) and final.image.dtype == np.uint8
    assert len(rows[0]["action"]) == ACTION_DIM and len(rows[0]["proprio"]) == PROPRIO_DIM
    assert all(r["action"][3:6] == [0.0, 0.0, 0.0] for r in rows)  # MetaWorld has no wrist rotation


def test_episodes_are_reproducible_from_their_seed(pick_place):
    env, task = pick_place

    def episode(seed):
        rows, _, _ = rollout(env, task, seed, make_expert(task, 0.1, np.random.default_rng(seed)))
        return [(r["qpos"], r["reward"]) for r in rows]

    first = episode(7)
    episode(8)
    assert episode(7) == first
    assert episode(8) != first


def test_fresh_placements_are_the_seeds_own_and_none_of_mt1s_fifty(pick_place):
    """evaluate.metaworld_placements=fresh: MT1's 50 fixed placements are what exploration starts from, so an
    evaluation on them mostly replays trained placements; a fresh one is drawn from the task's reset space by the
    episode's seed, reproducibly, and the expert still solves it (MetaWorld redraws a goal too near its object)."""
    import pickle

    env, task = pick_place
    benchmark = [pickle.loads(t.data)["rand_vec"] for t in env.benchmark.train_tasks]

    def placement(seed: int, placements: str) -> np.ndarray:
        env.reset(task, seed, None, placements=placements)
        return env.env._last_rand_vec.copy()

    assert np.array_equal(placement(7, "benchmark"), benchmark[7 % 50])
    fresh = {seed: placement(seed, "fresh") for seed in (7, 8, 57)}
    assert not any(np.allclose(vector, known) for vector in fresh.values() for known in benchmark)
    assert np.array_equal(placement(7, "fresh"), fresh[7]) and not np.allclose(fresh[7], fresh[57])  # 57 % 50 == 7
    assert np.array_equal(placement(7, "benchmark"), benchmark[7])  # and the next benchmark episode is as before
    for seed in (7, 8):
        _, _, success = rollout(env, task, seed, make_expert(task, 0.0, np.random.default_rng(seed)), placements="fresh")
        assert success
    with pytest.raises(ValueError, match="expected 'benchmark' or 'fresh', got 'new'"):
        env.reset(task, 7, None, placements="new")


def test_simplified_visual_meshes_change_pixels_not_physics(pick_place, tmp_path, monkeypatch):
    """As robosuite's (tests/envs/test_robosuite_env.py): the same episode, frames a little different."""
    env, task = pick_place
    monkeypatch.setenv("SIM2ACT_CACHE_DIR", str(tmp_path))
    coarse = MetaWorldEnv("pick-place-v3", RenderConfig(depth=True, mesh_detail=0.1))
    try:
        assert coarse.env.model.mesh_facenum.sum() < 0.6 * env.env.model.mesh_facenum.sum()
        full, fewer = (rollout(e, task, 4, make_expert(task, 0.1, np.random.default_rng(4)))[0] for e in (env, coarse))
    finally:
        coarse.close()
    assert [(r["qpos"], r["action"], r["reward"]) for r in full] == [(r["qpos"], r["action"], r["reward"]) for r in fewer]
    differences = [np.abs(a["image"].astype(int) - b["image"].astype(int)).mean() for a, b in zip(full, fewer)]
    assert 0 < max(differences) < 12
    assert list((tmp_path / "meshes").glob("*.npz"))


def test_colliding_meshes_are_drawn_decimated_and_stay_whole_for_physics(tmp_path, monkeypatch):
    """render.decimate_colliding: the gripper's colliding meshes reach the renderer decimated, and the model
    holds them whole again afterwards (physics reads their hulls): the same episode, a few pixels apart."""
    from envs.mesh_detail import colliding_meshes

    monkeypatch.setenv("SIM2ACT_CACHE_DIR", str(tmp_path))
    [task] = generate_tasks(TasksConfig(specs=["mw-pick-place"]), seed=0)
    envs = [MetaWorldEnv("pick-place-v3", RenderConfig(mesh_detail=0.1, decimate_colliding=decimate))
            for decimate in (False, True)]
    try:
        visual, both = (env.env.model for env in envs)
        meshes = colliding_meshes(both)
        assert sum(both.mesh_facenum[meshes]) > 10_000  # the gripper base and the last link, at least
        for name in ("mesh_vert", "mesh_normal", "mesh_face", "mesh_facenormal", "mesh_vertnum", "mesh_facenum",
                     "mesh_graphadr", "mesh_texcoordadr", "mesh_graph"):
            assert np.array_equal(getattr(visual, name), getattr(both, name)), name
        coarse, coarser = (rollout(env, task, 4, make_expert(task, 0.1, np.random.default_rng(4)))[0] for env in envs)
    finally:
        for env in envs:
            env.close()
    assert [(r["qpos"], r["action"], r["reward"]) for r in coarse] == [(r["qpos"], r["action"], r["reward"])
                                                                       for r in coarser]
    differences = [np.abs(a["image"].astype(int) - b["image"].astype(int)).mean() for a, b in zip(coarse, coarser)]
    assert 0 < max(differences) < 6


def test_colliding_meshes_are_decimated_only_below_full_detail():
    with pytest.raises(ValueError, match="decimate_colliding: expected render.mesh_detail below 1, got 1.0"):
        RenderConfig(decimate_colliding=True)


def test_frames_are_upright(pick_place):
    env, task = pick_place
    image = env.reset(task, seed=1).image.astype(int)
    # the table (brown wood) fills the bottom of the corner camera's view, not the top
    brown = (image[..., 0] > image[..., 2] + 30) & (image[..., 1] > image[..., 2])
    assert brown[42:].mean() > brown[:42].mean()


def test_depth_maps_line_up_with_the_frames(pick_place):
    env, task = pick_place
    obs = env.reset(task, seed=1)
    image = obs.image.astype(int)
    brown = (image[..., 0] > image[..., 2] + 30) & (image[..., 1] > image[..., 2])
    rows = np.nonzero(brown.any(1))[0]
    near, far = obs.depth[rows[-1]][brown[rows[-1]]], obs.depth[rows[0]][brown[rows[0]]]
    assert obs.depth.shape == (84, 84) and 0.3 < near.mean() < far.mean() < 5.0  # the table recedes upwards


def test_a_metaworld_explore_unit_writes_shards(tmp_path):
    config = CampaignConfig.model_validate(
        {"name": "mw", "tasks": {"specs": ["mw-reach"], "horizon": {"mw-reach": 40}},
         "explore": {"episodes_per_task": 1, "episodes_per_shard": 1}}
    )
    tasks = generate_tasks(config.tasks, config.seed)
    [unit] = plan_explore(config, 0, tasks, None, {}, Workspace.at(tmp_path).create())
    episodes = pq.read_table(run_explore_unit(unit)[0].path).to_pylist()
    assert episodes[0]["task_id"] == "mw-reach" and episodes[0]["num_steps"] > 0


def draw_metaworld_scenes(specs: list[str]) -> int:
    """Worker: make and draw one MetaWorld scene per spec, each on its own GL context."""
    from envs.rollout import worker_env

    tasks = generate_tasks(TasksConfig(specs=specs), seed=0)
    for task in {task.env_name: task for task in tasks}.values():
        worker_env(task, RenderConfig()).reset(task, 0)
    return len(tasks)


def test_a_worker_that_drew_metaworld_scenes_stops_without_gl_errors(capfd):
    """MetaWorld makes its GL context at the first draw, after the worker's environments registered
    their atexit close: MuJoCo's EGL display (its atexit hook, registered then) ended first, and every
    context's free printed a traceback as the worker exited, a dozen per worker of a MetaWorld campaign.
    A worker now closes its environments when told to stop, before the interpreter's teardown."""
    from envs.pool import WorkerPool

    with WorkerPool(1) as pool:
        drawn, _ = pool.run(draw_metaworld_scenes, ["mw-reach", "mw-push"])
    assert drawn >= 2
    err = capfd.readouterr().err
    assert "Exception ignored" not in err and "EGLError" not in err, err[-2000:]


def test_without_shadows_no_shadow_map_is_made_and_the_frames_are_the_same(pick_place, monkeypatch):
    """The shadow map (shadowsize², 4096² in MetaWorld's models: 64 MiB) is never read with shadows off."""
    import envs.metaworld_env as metaworld_env
    from envs.gl import size_offscreen

    env, task = pick_place
    assert env.env.model.vis.quality.shadowsize == 0
    shaded = MetaWorldEnv("reach-v3", RenderConfig(shadows=True))
    assert shaded.env.model.vis.quality.shadowsize == 4096  # the model's own, when shadows are drawn
    shaded.close()

    def with_the_map(model, render):
        size_offscreen(model, render)
        model.vis.quality.shadowsize = 4096

    monkeypatch.setattr(metaworld_env, "size_offscreen", with_the_map)
    mapped = MetaWorldEnv("pick-place-v3", RenderConfig(depth=True))
    try:
        assert mapped.env.model.vis.quality.shadowsize == 4096
        episodes = [rollout(e, task, 4, make_expert(task, 0.1, np.random.default_rng(4)))[0] for e in (env, mapped)]
        assert env._viewer().con.shadowFBO == 0 and mapped._viewer().con.shadowFBO != 0  # the map itself, made or not
    finally:
        mapped.close()
    assert len(episodes[0]) > 10 and all(np.array_equal(a["image"], b["image"]) and np.array_equal(a["depth"], b["depth"])
                                         for a, b in zip(*episodes))


def test_an_episode_longer_than_metaworlds_own_500_steps_runs_to_its_horizon(pick_place):
    """MetaWorld refuses a step past its max_path_length (500); tasks.horizon may ask for more."""
    env, task = pick_place
    longer = task.model_copy(update={"horizon": 503})
    rows, _, success = rollout(env, longer, seed=1, act=lambda obs: np.zeros(ACTION_DIM, np.float32))
    assert len(rows) == 503 and not success
    rollout(env, task, seed=1, act=lambda obs: np.zeros(ACTION_DIM, np.float32))  # and back to the task's own
    assert env.env.max_path_length == 500
