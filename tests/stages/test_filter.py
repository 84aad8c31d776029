import math

import numpy as np
import pytest

from bench.synthetic import explore_unit
from schemas.config import FilterConfig
from schemas.frames import encode_depth, encode_frame
from schemas.workspace import Workspace
from stages.filter import STEP_COLUMNS, decide, episode_facts, run_filter
from tests.warehouse.filled import CONFIG, fill, register_explore
from warehouse.catalog import Catalog

BOUNDS = (-1.0, 1.0)


def _steps(seed: int = 0) -> list[dict]:
    return explore_unit("u", seed=seed, episodes=1, steps=6)["steps"].select(STEP_COLUMNS).to_pylist()


def _episode(**overrides) -> dict:
    return {"error": None, "success": True, "episode_return": 3.0, "episode_id": "e1", **overrides}


def test_a_clean_episode_is_kept_and_its_digest_dedupes_the_next_identical_one():
    facts = episode_facts(_steps(), BOUNDS, 84)
    assert decide(_episode(), facts, FilterConfig(), {}) == ("kept", None)
    reason, detail = decide(_episode(episode_id="e2"), facts, FilterConfig(), {facts.digest: "e1"})
    assert reason == "duplicate" and "e1" in detail
    assert episode_facts(_steps(seed=1), BOUNDS, 84).digest != facts.digest


@pytest.mark.parametrize(
    ("spoil", "reason", "detail"),
    [
        (lambda s: s[2].update(reward=math.nan), "invalid_values", "step 2: non-finite reward"),
        (lambda s: s[1]["proprio"].__setitem__(0, math.inf), "invalid_values", "step 1: non-finite proprio"),
        (lambda s: s[3]["action"].__setitem__(6, 1.5), "action_out_of_bounds", "step 3: action"),
        (lambda s: s[4].update(image=b"not a frame"), "bad_image", "step 4: image of 11 bytes"),
    ],
)
def test_validation_rejects_with_the_step_and_value_named(spoil, reason, detail):
    steps = _steps()
    spoil(steps)
    assert decide(_episode(), episode_facts(steps, BOUNDS, 84), FilterConfig(), {})[0] == reason
    assert detail in decide(_episode(), episode_facts(steps, BOUNDS, 84), FilterConfig(), {})[1]


def test_an_image_of_the_wrong_size_is_rejected():
    facts = episode_facts(_steps(), BOUNDS, 64)
    assert decide(_episode(), facts, FilterConfig(), {}) == ("bad_image", facts.bad_image)
    assert "is not a 64x64 RGB frame" in facts.bad_image


def test_a_depth_campaign_rejects_a_step_without_its_depth_map():
    steps = [{**row, "depth": encode_depth(np.ones((84, 84), np.float32))} for row in _steps()]
    assert episode_facts(steps, BOUNDS, 84, depth=True).bad_image is None
    steps[2]["depth"] = None
    assert episode_facts(steps, BOUNDS, 84, depth=True).bad_image == "step 2: no depth map, not a 84x84 one"
    steps[2]["depth"] = encode_depth(np.ones((64, 64), np.float32))
    assert "step 2: 8192 bytes of depth map" in episode_facts(steps, BOUNDS, 84, depth=True).bad_image
    assert episode_facts(steps, BOUNDS, 84).bad_image is None  # an RGB campaign reads no depth


def test_a_wrist_camera_campaign_wants_frames_of_two_views():
    steps = _steps()
    assert "is not a 84x168 RGB frame" in episode_facts(steps, BOUNDS, 84, views=2).bad_image
    two_views = [{**row, "image": encode_frame(np.zeros((84, 168, 3), np.uint8))} for row in steps]
    assert episode_facts(two_views, BOUNDS, 84, views=2).bad_image is None
    assert "is not a 84x84 RGB frame" in episode_facts(two_views, BOUNDS, 84).bad_image


def test_rejection_sampling_on_success_and_return():
    facts = episode_facts(_steps(), BOUNDS, 84)
    assert decide(_episode(error="MujocoException: unstable"), facts, FilterConfig(), {})[0] == "env_error"
    assert decide(_episode(success=False), facts, FilterConfig(require_success=True), {}) == ("not_successful", None)
    assert decide(_episode(episode_return=0.5), facts, FilterConfig(min_return=1.0), {})[0] == "low_return"
    # and the kept side: a success where one is asked for, a return at the bar (it is `return < min_return` that fails)
    assert decide(_episode(success=True), facts, FilterConfig(require_success=True), {}) == ("kept", None)
    assert decide(_episode(episode_return=1.0), facts, FilterConfig(min_return=1.0), {}) == ("kept", None)


def test_a_changed_filter_setting_decides_the_same_episodes_again_and_dedupes_within_its_lineage(tmp_path):
    """Another filter.* gives new filter units over the same explore units: the episodes the first setting kept
    are not duplicates of themselves. A duplicate is one kept earlier in this dataset's lineage."""
    workspace = Workspace.at(tmp_path / "ws")
    workspace.create()
    explored = fill(workspace, iterations=1, units=2)[0]
    catalog = Catalog(workspace.catalog)
    first = run_filter(workspace, CONFIG, 0, explored)
    assert first.skipped_units == 2 and first.reasons == {}  # fill() decided them already
    looser = CONFIG.model_copy(update={"filter": FilterConfig(min_return=-1e9)})
    second = run_filter(workspace, looser, 0, explored)
    assert "duplicate" not in second.reasons and second.reasons["kept"] == sum(second.reasons.values()) > 0
    kept_first = catalog.query("SELECT count(*) FROM filter_decisions WHERE kept AND list_contains(?, filter_key)",
                               [first.unit_keys])[0][0]
    assert 0 < kept_first <= second.reasons["kept"]

    # iteration 1 explores the same episodes again (the same seed): duplicates of its lineage's, and only of those
    register_explore(workspace, "explore-again", 1, seed=0)
    again = run_filter(workspace, looser, 1, ["explore-again"], earlier_filter_keys=second.unit_keys)
    assert set(again.reasons) == {"duplicate"}
    alone = run_filter(workspace, looser.model_copy(update={"filter": FilterConfig(min_return=-1e8)}), 1,
                       ["explore-again"])
    assert "duplicate" not in alone.reasons
