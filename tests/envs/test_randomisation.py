"""Per-episode domain randomisation: drawn from the seed, applied to real MuJoCo models,
undone exactly, recorded with the episode and queryable in the warehouse."""

import duckdb
import numpy as np
import pytest

from envs.experts import PickPlaceExpert
from envs.navigation_env import NavigationEnv
from envs.randomisation import ASPECTS, Randomisation, sample_randomisation
from envs.robosuite_env import RobosuiteEnv
from envs.rollout import rollout
from envs.suite import generate_tasks
from schemas.config import CampaignConfig, ConfigError, RandomiseConfig, RenderConfig, TasksConfig, load_config
from schemas.tables import RANDOMISATION
from schemas.tasks import TaskRecord
from schemas.workspace import Workspace
from stages.explore import plan_explore, run_explore_unit

LIFT = TaskRecord(task_id="lift-red", spec="lift", family="robosuite", env_name="Lift", object_colours={"target": "red"},
                  instructions=["pick up the red block", "b", "c"], split="seen", horizon=60)


@pytest.fixture(scope="module")
def lift_env():
    env = RobosuiteEnv("Lift", RenderConfig())
    yield env
    env.close()


def test_draws_follow_the_seed_and_record_only_what_a_family_applies():
    config = RandomiseConfig()
    full = sample_randomisation(config, 11, ASPECTS)
    assert full == sample_randomisation(config, 11, ASPECTS)
    assert full != sample_randomisation(config, 12, ASPECTS)
    visual = sample_randomisation(config, 11, {"light", "tint"})
    assert visual.light == full.light and visual.tint == full.tint  # independent of what else applies
    assert visual.mass is None and visual.size is None and visual.camera_shift is None
    assert config.light[0] <= full.light <= config.light[1]
    assert all(abs(v) <= config.camera_shift_m for v in full.camera_shift)
    assert sample_randomisation(RandomiseConfig(enabled=False), 11, ASPECTS) is None
    assert [f.name for f in RANDOMISATION] == list(ASPECTS)  # the warehouse column holds every aspect


def test_a_reversed_range_is_refused_naming_the_field():
    with pytest.raises(ConfigError, match=r"^randomise: .*mass: low 1.5 is above high 0.5"):
        load_config("smoke", overrides={"randomise": {"mass": [1.5, 0.5]}})


def test_the_largest_colour_jitter_keeps_every_two_colours_apart():
    """Two colours' jittered ranges (each channel +- colour_jitter) meet when every channel differs by at most
    twice the jitter: red stays red only below that, for objects and for navigation's floors (0.8 of the palette)."""
    import itertools

    from schemas.tasks import COLOUR_RGBA

    from schemas.config import COLOUR_JITTER_MAX as cap

    for scale in (1.0, 0.8):
        for a, b in itertools.combinations(COLOUR_RGBA, 2):
            gap = np.abs(np.subtract(COLOUR_RGBA[a][:3], COLOUR_RGBA[b][:3])).max() * scale
            assert gap > 2 * cap, (a, b, scale)
    with pytest.raises(ConfigError, match=r"randomise.colour_jitter: expected at most 0.13 .*got 0.15"):
        load_config("smoke", overrides={"randomise": {"colour_jitter": 0.15}})
    with pytest.raises(ConfigError, match=r"adapt.domain.colour_jitter: expected at most 0.13"):
        load_config("smoke", overrides={"adapt": {"domain": {"colour_jitter": 0.15}}})
    assert RandomiseConfig(colour_jitter=0.15).colour_jitter == 0.15  # a stored record of an older cap still reads


def test_robosuite_applies_every_aspect_and_undoes_it_exactly(lift_env):
    model = lift_env.env.sim.model._model
    cube = model.body("cube_main").id
    nominal = {name: getattr(model, name).copy() for name in ("body_mass", "geom_size", "geom_friction", "cam_pos")}
    plain = lift_env.reset(LIFT, seed=3).image
    draw = Randomisation(light=0.6, camera_shift=[0.02, 0, 0], camera_rotation_deg=[0, 2, 0], tint=[0.9, 1, 1.1],
                         colour_jitter=[0.05, 0, 0], size=1.1, mass=1.25, friction=0.8)
    randomised = lift_env.reset(LIFT, seed=3, randomisation=draw).image
    assert model.body_mass[cube] == pytest.approx(1.25 * nominal["body_mass"][cube])
    cube_geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] == cube]
    assert np.allclose(model.geom_size[cube_geoms], 1.1 * nominal["geom_size"][cube_geoms])
    assert np.allclose(model.geom_friction[cube_geoms, 0], 0.8 * nominal["geom_friction"][cube_geoms, 0])
    assert np.abs(randomised.astype(int) - plain).mean() > 3  # the camera sees it
    assert randomised.mean() < plain.mean()  # less light
    again = lift_env.reset(LIFT, seed=3).image
    assert np.array_equal(again, plain)  # nothing of the draw survives into the next episode
    for name, value in nominal.items():
        assert np.array_equal(getattr(model, name), value), name


def test_what_a_scene_cannot_change_is_recorded_as_null():
    """The record says what the episode saw: PickPlace's objects collide through meshes, which keep their size
    and friction (both scale primitive geoms), so its episodes record neither; the latched door has no free
    body, so no mass either."""
    env = RobosuiteEnv("PickPlaceMilk", RenderConfig())
    try:
        model = env.env.sim.model._model
        milk = model.body("Milk_main").id
        touching = [g for g in range(model.ngeom) if model.geom_bodyid[g] == milk
                    and (model.geom_contype[g] or model.geom_conaffinity[g])]
        assert touching and all(model.geom_type[g] == 7 for g in touching)  # mjGEOM_MESH
        nominal = model.geom_friction.copy()
        env.randomiser.apply(Randomisation(friction=0.7))
        assert np.array_equal(model.geom_friction, nominal)  # nothing it could scale
        draw = sample_randomisation(RandomiseConfig(), 3, env.RANDOMISES)
        assert draw.friction is None and draw.size is None and draw.mass is not None
    finally:
        env.close()
    from envs.robosuite_env import ROBOSUITE_SCENES

    door = sample_randomisation(RandomiseConfig(), 3, ROBOSUITE_SCENES["Door"].randomises)
    assert door.mass is None and door.friction is None and door.light is not None


def test_metaworld_records_mass_and_friction_only_where_its_scene_changes_them():
    """A button has no free body (no mass to scale); the basketball collides through meshes (no friction);
    the puck has both. The other aspects' draws are the same whatever a scene applies."""
    from envs.metaworld_env import MetaWorldEnv

    draws = {name: sample_randomisation(RandomiseConfig(), 3, MetaWorldEnv(name, None).RANDOMISES)
             for name in ("button-press-v3", "basketball-v3", "push-v3")}
    assert (draws["button-press-v3"].mass, draws["button-press-v3"].friction) == (None, None)
    assert draws["basketball-v3"].mass is not None and draws["basketball-v3"].friction is None
    assert draws["push-v3"].mass is not None and draws["push-v3"].friction is not None
    assert len({(d.light, tuple(d.tint)) for d in draws.values()}) == 1


def test_a_resized_block_collides_at_its_new_size(lift_env):
    env = lift_env.env
    cube_geom = env.sim.model._model.geom("cube_g0").id
    half_height = lift_env.randomiser.nominal["geom_size"][cube_geom][2]
    for size in (0.8, 1.0, 1.2):
        lift_env.reset(LIFT, seed=5, randomisation=Randomisation(size=size))
        for _ in range(15):  # robosuite drops objects from 1 cm; let it land
            lift_env.step(np.zeros(7))
        resting = env.sim.data.body_xpos[env.cube_body_id][2]
        assert resting == pytest.approx(env.table_offset[2] + size * half_height, abs=1e-3), size


def test_the_expert_still_lifts_under_randomisation(lift_env):
    config = RandomiseConfig()
    for seed in (1, 2):
        draw = sample_randomisation(config, seed, lift_env.RANDOMISES)
        expert = PickPlaceExpert(noise=0.1, rng=np.random.default_rng(seed))
        _, _, success = rollout(lift_env, LIFT, seed, expert.act, draw)
        assert success


def test_navigation_markers_change_size_but_keep_no_mass():
    [task] = generate_tasks(TasksConfig(specs=["nav-ball"], colours=["red"]), 0)
    env = NavigationEnv("FindBall", RenderConfig())
    try:
        draw = sample_randomisation(RandomiseConfig(), 4, env.RANDOMISES)
        assert draw.size is not None and draw.mass is None and draw.friction is None
        ball = env.model.geom("ball_0_geom").id
        nominal = env.model.geom_size[ball].copy()
        env.reset(task, 4, draw)
        assert env.model.geom_size[ball][0] == pytest.approx(draw.size * nominal[0])
        assert env.model.geom_rgba[ball][:3].tolist() != [0.85, 0.12, 0.10]  # jittered, still reddish
        red, green, blue = env.model.geom_rgba[env.model.geom("ball_0_geom").id][:3]
        assert red > 0.75 and green < 0.2 and blue < 0.2
        assert env.model.vis.headlight.diffuse[0] == pytest.approx(min(1.0, 0.5 * draw.light), rel=1e-5)
    finally:
        env.close()


def test_explored_episodes_record_their_draw_and_the_warehouse_can_select_by_it(tmp_path):
    config = CampaignConfig.model_validate(
        {"name": "dr", "tasks": {"specs": ["lift"], "colours": ["red"], "horizon": {"lift": 20}},
         "explore": {"episodes_per_task": 3, "episodes_per_shard": 3}}
    )
    workspace = Workspace.at(tmp_path).create()
    [unit] = plan_explore(config, 0, generate_tasks(config.tasks, config.seed), None, {}, workspace)
    episodes = {s.table: s for s in run_explore_unit(unit)}["episodes"].path
    rows = duckdb.sql(
        f"SELECT seed, randomisation.light AS light, randomisation.mass AS mass, randomisation.camera_shift AS shift "
        f"FROM '{episodes}' ORDER BY seed"
    ).fetchall()
    assert len(rows) == 3
    for seed, light, mass, shift in rows:
        expected = sample_randomisation(config.randomise, seed, ASPECTS)
        assert light == pytest.approx(expected.light, rel=1e-6) and mass == pytest.approx(expected.mass, rel=1e-6)
        assert shift == pytest.approx(expected.camera_shift, rel=1e-5)
    dim = duckdb.sql(f"SELECT count(*) FROM '{episodes}' WHERE randomisation.light < 1.0").fetchone()[0]
    assert dim == sum(light < 1.0 for _, light, _, _ in rows)
