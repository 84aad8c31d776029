"""Real robosuite, real offscreen rendering (EGL on the CPU)."""

import numpy as np
import pyarrow.parquet as pq
import pytest

from envs.experts import CLOSED, Phase, PickPlaceExpert
from envs.observation import PROPRIO_DIM
from envs.robosuite_env import RobosuiteEnv
from envs.rollout import rollout
from envs.suite import generate_tasks
from schemas.config import CampaignConfig, RenderConfig, TasksConfig
from schemas.frames import decode_frame
from schemas.tables import EPISODES, STEPS
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from stages.evaluate import ended_doing, others_of
from stages.explore import plan_explore, run_explore_unit


def _lift(colour: str) -> TaskRecord:
    return TaskRecord(task_id=f"lift-{colour}", spec="lift", family="robosuite", env_name="Lift", object_colours={"target": colour},
                      instructions=[f"pick up the {colour} block", "b", "c"], split="seen", horizon=60)


@pytest.fixture(scope="module")
def lift_env():
    env = RobosuiteEnv("Lift", RenderConfig())
    yield env
    env.close()


def test_reset_is_reproducible_from_the_seed(lift_env):
    first = lift_env.reset(_lift("red"), seed=7)
    qpos = lift_env.mujoco_state().qpos
    again = lift_env.reset(_lift("red"), seed=7)
    assert np.array_equal(first.image, again.image)
    assert np.array_equal(qpos, lift_env.mujoco_state().qpos)
    lift_env.reset(_lift("red"), seed=8)
    assert not np.array_equal(qpos, lift_env.mujoco_state().qpos)


def test_frames_are_84px_rgb_and_show_the_task_colour(lift_env):
    def dominant(colour: str, channel: int) -> int:
        image = lift_env.reset(_lift(colour), seed=3).image.astype(int)
        others = [c for c in range(3) if c != channel]
        return int(((image[..., channel] - image[..., others].max(-1)) > 60).sum())

    obs = lift_env.reset(_lift("blue"), seed=3)
    assert obs.image.shape == (84, 84, 3) and obs.image.dtype == np.uint8
    assert obs.proprio.shape == (PROPRIO_DIM,)
    assert dominant("blue", 2) > 5 and dominant("red", 2) == 0
    assert dominant("red", 0) > 5


def test_depth_maps_line_up_with_the_frames_they_were_drawn_with(lift_env):
    env = RobosuiteEnv("Lift", RenderConfig(depth=True))
    obs = env.reset(_lift("red"), seed=3)
    env.close()
    assert lift_env.reset(_lift("red"), seed=3).depth is None
    assert np.array_equal(obs.image, lift_env.reset(_lift("red"), seed=3).image)  # depth leaves the frame alone
    image, depth = obs.image.astype(int), obs.depth
    assert depth.shape == (84, 84) and depth.dtype == np.float32
    # the cube stands up from the table: its pixels are nearer than the table's around it
    cube = (image[..., 0] - image[..., 1:].max(-1)) > 60
    rows, cols = np.nonzero(cube)
    around = depth[rows.min() - 4: rows.max() + 5, cols.min() - 4: cols.max() + 5]
    assert depth[cube].mean() < np.median(around) - 0.01
    # the table recedes from the bottom of the frame (near the camera) upwards, 0.5-2 m away
    assert 0.4 < depth[-1].mean() < depth[60].mean() < depth[40].mean() < 2.0


def test_the_scripted_expert_lifts_the_cube(lift_env):
    task = _lift("green")
    expert = PickPlaceExpert(noise=0.1, rng=np.random.default_rng(0))
    rows, _, success = rollout(lift_env, task, seed=11, act=expert.act)
    assert success and rows[-1]["done"] and len(rows) < task.horizon


def test_a_labeller_joining_at_the_grasp_labels_it_closed(lift_env):
    """DAgger: the noiseless expert labels the states another explorer reaches. One that meets the
    hand already at the cube (it never stopped at its own waypoint above it) labels the grasp and
    the lift "closed", as the explorer itself does, not "open, go back up"."""
    task = _lift("red")
    actor = PickPlaceExpert(noise=0.1, rng=np.random.default_rng(2))
    obs, labeller, labels, success = lift_env.reset(task, seed=4), None, [], False
    for _ in range(task.horizon):
        action = actor.act(obs)
        if labeller is None and actor.phase is Phase.GRASP:
            labeller = PickPlaceExpert(noise=0.0, rng=np.random.default_rng(0))
        if labeller is not None:
            labels.append(labeller.act(obs)[6])
        obs, _, success = lift_env.step(action)
        if success:
            break
    assert success and len(labels) > 5
    assert labels == [CLOSED] * len(labels)


def test_an_explore_unit_writes_triplet_shards(tmp_path):
    config = CampaignConfig.model_validate(
        {"name": "t", "tasks": {"specs": ["lift"], "colours": ["red", "blue"], "horizon": {"lift": 50}},
         "explore": {"episodes_per_task": 2, "episodes_per_shard": 2}}
    )
    workspace = Workspace.at(tmp_path).create()
    tasks = generate_tasks(config.tasks, config.seed)
    [unit, _] = plan_explore(config, 0, tasks, None, {}, workspace)
    shards = {s.table: s for s in run_explore_unit(unit)}
    episodes = pq.read_table(shards["episodes"].path)
    steps = pq.read_table(shards["steps"].path)
    assert episodes.schema.remove_metadata().equals(EPISODES) and steps.schema.remove_metadata().equals(STEPS)
    assert episodes.num_rows == 2 and set(episodes["explorer"].to_pylist()) == {"expert"}
    for episode in episodes.to_pylist():
        rows = [r for r in steps.to_pylist() if r["episode_id"] == episode["episode_id"]]
        assert [r["step"] for r in rows] == list(range(episode["num_steps"]))
        assert [r["next_image"] is not None for r in rows] == [False] * (len(rows) - 1) + [True]
        assert [r["done"] for r in rows][-1] and not any(r["done"] for r in rows[:-1])
        assert decode_frame(rows[0]["image"]).shape == (84, 84, 3)
        assert len(rows[0]["action"]) == 7 and rows[0]["instruction"] in unit.task.instructions
        assert episode["episode_return"] == pytest.approx(sum(r["reward"] for r in rows), rel=1e-5)
    # same unit, same seeds: the same data
    again = pq.read_table(run_explore_unit(unit)[1].path)
    assert again["action"].to_pylist() == steps["action"].to_pylist()


def test_an_episode_depends_on_its_seed_only_not_on_what_the_worker_ran_before(lift_env):
    """Workers reuse environments across units; a resumed run hands units to other workers."""

    def episode(env: RobosuiteEnv) -> list:
        expert = PickPlaceExpert(noise=0.1, rng=np.random.default_rng(5))
        rows, _, _ = rollout(env, _lift("red"), seed=5, act=expert.act)
        return [(r["qpos"], r["action"], r["reward"]) for r in rows]

    rollout(lift_env, _lift("blue"), seed=1, act=lambda obs: np.ones(7))  # something else first
    fresh = RobosuiteEnv("Lift", RenderConfig())
    try:
        assert episode(lift_env) == episode(fresh)
    finally:
        fresh.close()


def test_the_stack_expert_turns_its_fingers_away_from_a_close_neighbour():
    """These seeds put the two cubes ~5 cm apart along the fingers' opening line: without
    turning the wrist, a finger lands on the other cube and the grasp never closes."""
    from envs.randomisation import sample_randomisation
    from schemas.config import RandomiseConfig
    from schemas.keys import derive_seed

    task = TaskRecord(task_id="stack-blue-red", spec="stack", family="robosuite", env_name="Stack",
                      object_colours={"pick": "blue", "place": "red"}, instructions=["a", "b", "c"], split="seen",
                      horizon=160)
    env = RobosuiteEnv("Stack", None)
    try:
        for episode in (2, 6):
            seed = derive_seed("expert-check", task.task_id, episode)
            expert = PickPlaceExpert(noise=0.1, rng=np.random.default_rng(seed))
            draw = sample_randomisation(RandomiseConfig(), seed, env.RANDOMISES)
            start = env.reset(task, seed, draw).privileged
            assert np.linalg.norm((start["grasp"] - start["goal"])[:2]) < 0.08
            rows, _, success = rollout(env, task, seed, expert.act, draw)
            assert success, episode
            assert abs(np.mean([r["action"][5] for r in rows[:10]])) > 0.3  # it turned the wrist first
    finally:
        env.close()


@pytest.mark.parametrize(("spec", "task_id"), [("door", "door-blue"), ("nut-round", "nut-round-green"),
                                              ("pick-place-cereal", "pick-place-cereal")])
def test_the_scene_experts_solve_door_nut_and_bin_tasks_under_randomisation(spec, task_id):
    """The door expert turns the latched handle before pulling; the nut expert turns the nut to
    fit and lets go over the peg; the bin expert closes on the cereal box's narrow side."""
    from envs.randomisation import sample_randomisation
    from envs.registry import make_expert
    from schemas.config import RandomiseConfig, TasksConfig

    task = next(t for t in generate_tasks(TasksConfig(specs=[spec], weak_experts="keep"), 0) if t.task_id == task_id)
    env = RobosuiteEnv(task.env_name, None)
    try:
        draw = sample_randomisation(RandomiseConfig(), 3, env.RANDOMISES)
        rows, _, success = rollout(env, task, 3, make_expert(task, 0.1, np.random.default_rng(3)), draw)
        assert success and len(rows) < task.horizon
        if task.env_name == "Door":
            assert env.env.sim.data.qpos[env.env.hinge_qpos_addr] > 0.3
    finally:
        env.close()


def test_simplified_visual_meshes_change_pixels_not_physics(lift_env, tmp_path, monkeypatch):
    """render.mesh_detail < 1: the visual-only meshes are decimated in place (and cached), the
    collision geometry is not, so an expert's episode has the same states, actions and rewards; its
    frames differ a little (the same scene, fewer triangles)."""
    import mujoco

    from envs.mesh_detail import simplify_visual_meshes, visual_only_meshes
    from schemas.config import RENDER_LEGACY_VALUES
    from schemas.keys import key_fields

    monkeypatch.setenv("SIM2ACT_CACHE_DIR", str(tmp_path))

    def episode(env: RobosuiteEnv) -> list:
        expert = PickPlaceExpert(noise=0.1, rng=np.random.default_rng(3))
        rows, _, _ = rollout(env, _lift("green"), seed=3, act=expert.act)
        return rows

    full_model = lift_env.env.sim.model._model
    simplified = visual_only_meshes(full_model)
    assert simplified and all(full_model.geom_contype[g] == 0 for g in range(full_model.ngeom)
                              if full_model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
                              and full_model.geom_dataid[g] in simplified)  # never a colliding geom's mesh
    coarse = RobosuiteEnv("Lift", RenderConfig(mesh_detail=0.1))
    try:
        model = coarse.env.sim.model._model
        assert sum(model.mesh_facenum[simplified]) < 0.2 * sum(full_model.mesh_facenum[simplified])
        others = [m for m in range(model.nmesh) if m not in simplified]
        assert list(model.mesh_facenum[others]) == list(full_model.mesh_facenum[others])
        full, fewer = episode(lift_env), episode(coarse)
    finally:
        coarse.close()
    assert [(r["qpos"], r["action"], r["reward"]) for r in full] == [(r["qpos"], r["action"], r["reward"]) for r in fewer]
    differences = [np.abs(a["image"].astype(int) - b["image"].astype(int)).mean() for a, b in zip(full, fewer)]
    assert 0 < max(differences) < 12  # grey levels of 255 per pixel, on average: the same scene
    cached = sorted((tmp_path / "meshes").glob("*.npz"))
    assert len(cached) == len(simplified)
    # another worker's model reuses the cache: the same files, none written again
    stamps = [p.stat().st_mtime_ns for p in cached]
    again = mujoco.MjModel.from_xml_string(lift_env.env.sim.model.get_xml())
    before, after = simplify_visual_meshes(again, 0.1, tmp_path / "meshes")
    assert [p.stat().st_mtime_ns for p in cached] == stamps and 0 < after < 0.2 * before
    # a campaign at full detail keys its units as before the field existed
    added = {"mesh_detail", "wrist_camera", "decimate_colliding"}  # render fields newer than the stages that key on them
    assert key_fields(RenderConfig(), set(), RENDER_LEGACY_VALUES) == RenderConfig().model_dump(exclude=added)


def test_the_wrist_camera_is_drawn_beside_the_main_view(lift_env):
    """render.wrist_camera: the frame is the agent view (as without it) and the hand's view to its right,
    which moves with the hand while the agent view keeps its framing."""
    env = RobosuiteEnv("Lift", RenderConfig(wrist_camera=True))
    try:
        obs = env.reset(_lift("red"), seed=3)
        assert obs.image.shape == (84, 168, 3) and obs.image.dtype == np.uint8
        assert np.array_equal(obs.image[:, :84], lift_env.reset(_lift("red"), seed=3).image)  # the main view as it was
        lowered = obs
        for _ in range(15):
            lowered, _, _ = env.step(np.array([0.0, 0.0, -0.6, 0.0, 0.0, 0.0, -1.0]))
        hand_moved = np.abs(lowered.image[:, 84:].astype(int) - obs.image[:, 84:].astype(int)).mean()
        assert hand_moved > 5  # the table comes nearer in the hand's view
    finally:
        env.close()


def test_a_wrist_camera_is_refused_for_families_without_one():
    from envs.registry import check_render
    from schemas.config import ConfigError

    tasks = generate_tasks(TasksConfig(specs=["lift", "nav-room"]), 0)
    with pytest.raises(ConfigError, match=r"^render.wrist_camera: expected robosuite tasks only .*got "):
        check_render(RenderConfig(wrist_camera=True), tasks)
    check_render(RenderConfig(wrist_camera=True), [t for t in tasks if t.family == "robosuite"])
    check_render(RenderConfig(), tasks)


def test_a_camera_some_scene_lacks_is_refused_before_the_run():
    """The bins arena (PickPlace) has no sideview: its workers failed making the scene, late in the run."""
    from envs.registry import check_render
    from schemas.config import ConfigError

    tasks = generate_tasks(TasksConfig(specs=["lift", "pick-place-can"], weak_experts="keep"), 0)
    with pytest.raises(ConfigError, match=r"^render.camera: pick-place-can\S*'s scene has no 'sideview' \(it has "):
        check_render(RenderConfig(camera="sideview"), tasks)
    check_render(RenderConfig(camera="sideview"), [t for t in tasks if t.spec == "lift"])


def _stack(picked: str, base: str) -> TaskRecord:
    return TaskRecord(task_id=f"stack-{picked}-{base}", spec="stack", family="robosuite", env_name="Stack",
                      object_colours={"pick": picked, "place": base}, instructions=["a", "b", "c"], split="seen",
                      horizon=160)


def test_a_stack_that_ended_the_other_way_round_did_the_reversed_task():
    """Hindsight relabelling's test on Stack: the episode's base cube put on its picked cube (placed there
    here, released) is the reversed pair's success; a pair of other colours, or the episode's own task, is not."""
    red_on_green, green_on_red, blue_on_green = _stack("red", "green"), _stack("green", "red"), _stack("blue", "green")
    env = RobosuiteEnv("Stack", None)
    try:
        assert env.achieved([green_on_red]) is None  # before any reset: no episode to ask about
        env.reset(red_on_green, seed=3)
        assert env.achieved([blue_on_green, green_on_red, red_on_green]) is None  # both cubes on the table
        sim = env.env.sim
        picked = sim.data.body_xpos[env.env.cubeA_body_id].copy()
        sim.data.set_joint_qpos("cubeB_joint0", np.r_[picked + [0.0, 0.0, 0.044], 1.0, 0.0, 0.0, 0.0])
        sim.forward()  # the base cube (2.5 cm half-size) resting on the picked one (2 cm)
        assert env.achieved([blue_on_green, red_on_green, green_on_red]) == green_on_red
        assert env.achieved([blue_on_green, red_on_green]) is None
        # evaluation asks the same: the episode's other cases in its scene
        cases = [(task, "seen", "a") for task in (red_on_green, blue_on_green, green_on_red)]
        assert ended_doing(env, others_of(red_on_green, cases)) == green_on_red.task_id
    finally:
        env.close()


def test_without_shadows_no_shadow_map_is_made_and_the_frames_are_the_same(lift_env, monkeypatch):
    """robosuite's models get MuJoCo's default 4096² shadow map (64 MiB a scene), never read with shadows off."""
    import envs.robosuite_env as robosuite_env
    from envs.gl import size_offscreen

    assert lift_env.env.sim.model._model.vis.quality.shadowsize == 0
    assert lift_env.env.sim._render_context_offscreen.con.shadowFBO == 0  # the context was made after the setting

    def with_the_map(model, render):
        size_offscreen(model, render)
        model.vis.quality.shadowsize = 4096

    monkeypatch.setattr(robosuite_env, "size_offscreen", with_the_map)
    mapped = RobosuiteEnv("Lift", RenderConfig())
    try:
        assert mapped.env.sim._render_context_offscreen.con.shadowFBO != 0
        frames = [[r["image"] for r in rollout(e, _lift("green"), seed=3,
                                                act=PickPlaceExpert(noise=0.1, rng=np.random.default_rng(3)).act)[0]]
                  for e in (lift_env, mapped)]
    finally:
        mapped.close()
    assert len(frames[0]) > 10 and all(np.array_equal(a, b) for a, b in zip(*frames))
