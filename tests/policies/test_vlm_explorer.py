"""The VLM explorer against a local HTTP server that speaks the OpenAI chat-completions protocol with
scripted answers (no model weights can run here): what it sends, how answers become actions, and
what it counts per episode."""

from __future__ import annotations

import base64
import io
import json

import numpy as np
import pytest
from PIL import Image

from envs.navigation_env import ACTIONS
from envs.observation import PROPRIO_DIM, Observation
from envs.registry import action_bounds, make_env
from envs.rollout import rollout
from envs.suite import generate_tasks
from policies.openai_chat import ChatUnavailable
from policies.vlm_explorer import TooManyInvalidAnswers, VlmExplorer
from schemas.config import RenderConfig, TasksConfig, VlmExplorerConfig
from tests.chat_server import closed_port

INSTRUCTION = "go to the red room"


def _explorer(server_url: str, family: str = "robosuite", **extra) -> VlmExplorer:
    config = VlmExplorerConfig(url=server_url, model="tiny-vlm", **{"timeout_s": 5, **extra})
    return VlmExplorer(config, family, INSTRUCTION)


def _obs(height: int = 40, width: int = 48) -> Observation:
    image = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    return Observation(image, np.zeros(PROPRIO_DIM, dtype=np.float32), {})


def _sent_image(body: dict) -> np.ndarray:
    [image_part] = [p for p in body["messages"][-1]["content"] if p["type"] == "image_url"]
    header, data = image_part["image_url"]["url"].split(",", 1)
    assert header == "data:image/png;base64"
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(data))))


def _say(**answer) -> str:
    return json.dumps(answer)


@pytest.mark.parametrize("family", ["robosuite", "metaworld"])
def test_a_valid_manipulation_answer_is_the_action_and_the_request_carries_frame_and_instruction(serve_chat, family):
    server = serve_chat(_say(delta=[0.5, -1, 0.25], gripper="close"), _say(delta=[0, 0, 0.1], gripper="open"))
    explorer, obs = _explorer(server.url, family), _obs()
    assert explorer.act(obs).tolist() == [0.5, -1.0, 0.25, 0.0, 0.0, 0.0, 1.0]
    action = explorer.act(obs)
    assert action.shape == (7,) and action.dtype == np.float32 and action[-1] == -1.0
    low, high = action_bounds(family)
    assert low <= action.min() and action.max() <= high
    path, _, body = server.requests[0]
    assert path == "/v1/chat/completions" and body["model"] == "tiny-vlm"
    assert body["response_format"] == {"type": "json_object"} and body["max_tokens"] == 64
    system, user = body["messages"]
    assert "delta" in system["content"] and "gripper" in system["content"]
    assert any(INSTRUCTION in p.get("text", "") for p in user["content"])
    assert np.array_equal(_sent_image(body), obs.image)  # PNG is lossless: the very frame, upright
    assert explorer.stats() == {"steps": 2, "calls": 2, "retries": 0, "timeouts": 0, "http_errors": 0,
                                "connection_errors": 0, "malformed_replies": 0, "invalid_answers": 0,
                                "fallback_actions": 0}


def test_invalid_answers_are_counted_and_replaced_by_a_no_op(serve_chat):
    server = serve_chat(
        _say(delta=[0.1, 0.2, 0.3], gripper="close"),
        "Sure! I will move left.",  # not JSON
        _say(delta=[2.0, 0, 0], gripper="open"),  # out of range
        _say(delta=[0, 0], gripper="open"),  # wrong schema
        _say(delta=["0", 0, 0], gripper="open"),  # a string is not a number
        _say(action="forward"),  # navigation's schema, not manipulation's
        None,  # not a chat completion at all
    )
    explorer, obs = _explorer(server.url, max_invalid_answers=6), _obs()
    explorer.act(obs)
    for _ in range(6):  # the no-op: no motion, the gripper kept closed as last commanded
        assert explorer.act(obs).tolist() == [0.0] * 6 + [1.0]
    stats = explorer.stats()
    assert (stats["invalid_answers"], stats["malformed_replies"], stats["fallback_actions"]) == (5, 1, 6)
    assert (stats["steps"], stats["calls"], stats["retries"]) == (7, 7, 0)


def test_navigation_answers_name_a_discrete_action_and_unknown_names_are_invalid(serve_chat):
    server = serve_chat(_say(action="turn_right"), _say(action="fly"), _say(action="backward", reason="a wall ahead"))
    explorer, obs = _explorer(server.url, "navigation"), _obs()
    assert explorer.act(obs).tolist() == [ACTIONS.index("turn_right")]
    assert explorer.act(obs).tolist() == [ACTIONS.index("turn_left")]  # no stop action: turn in place
    assert explorer.act(obs).tolist() == [ACTIONS.index("backward")]  # an extra key is no harm
    assert explorer.stats()["invalid_answers"] == 1
    assert all(name in server.requests[0][2]["messages"][0]["content"] for name in ACTIONS)


def test_past_the_budget_of_invalid_answers_the_episode_fails(serve_chat):
    server = serve_chat("{}", "{}")
    explorer = _explorer(server.url, max_invalid_answers=1)
    explorer.act(_obs())
    with pytest.raises(TooManyInvalidAnswers, match="2 unusable answers .*max_invalid_answers=1"):
        explorer.act(_obs())


def test_a_server_error_then_success_counts_a_retry(serve_chat):
    server = serve_chat(("{}", 500, 0.0), _say(delta=[0, 0, -1], gripper="open"))
    explorer = _explorer(server.url, retries=1)
    assert explorer.act(_obs()).tolist() == [0, 0, -1, 0, 0, 0, -1]
    stats = explorer.stats()
    assert (stats["calls"], stats["retries"], stats["http_errors"], stats["timeouts"]) == (2, 1, 1, 0)


def test_an_answer_slower_than_the_timeout_is_counted_and_retried(serve_chat):
    server = serve_chat((_say(action="forward"), 200, 1.0), _say(action="backward"))
    explorer = _explorer(server.url, "navigation", timeout_s=0.3, retries=1)
    assert explorer.act(_obs()).tolist() == [ACTIONS.index("backward")]  # the slow answer came too late
    stats = explorer.stats()
    assert (stats["calls"], stats["retries"], stats["timeouts"], stats["fallback_actions"]) == (2, 1, 1, 0)


def test_an_unreachable_endpoint_raises_a_clear_error():
    explorer = _explorer(f"http://127.0.0.1:{closed_port()}/v1", retries=1)
    with pytest.raises(ChatUnavailable, match=r"VLM explorer at .* did not answer .* after 2 tries"):
        explorer.act(_obs())
    stats = explorer.stats()
    assert (stats["calls"], stats["retries"], stats["connection_errors"]) == (2, 1, 2)


def test_an_episode_applies_the_actions_the_server_chose(serve_chat):
    chosen = ["turn_left", "forward", "forward", "turn_right", "backward"]
    server = serve_chat(*(_say(action=name) for name in chosen))
    [task] = generate_tasks(TasksConfig(specs=["nav-room"], include=["nav-room-red"], horizon={"nav-room": 5}), 0)
    env = make_env("navigation", task.env_name, RenderConfig(image_size=64))
    try:
        explorer = VlmExplorer(VlmExplorerConfig(url=server.url, model="tiny-vlm"), "navigation", task.instructions[0])
        rows, _, _ = rollout(env, task, 3, explorer.act)
    finally:
        env.close()
    assert [row["action"] for row in rows] == [[float(ACTIONS.index(name))] for name in chosen]
    for row, (_, _, body) in zip(rows, server.requests, strict=True):  # the frame the server saw, each step
        assert np.array_equal(_sent_image(body), row["image"]) and row["image"].shape == (64, 64, 3)
        assert task.instructions[0] in body["messages"][-1]["content"][0]["text"]
    moved = np.hypot(*np.subtract(rows[3]["proprio"][:2], rows[1]["proprio"][:2]))
    assert moved > 0.1  # two forwards drove the agent
    assert explorer.stats()["calls"] == 5 and explorer.stats()["fallback_actions"] == 0


def test_a_two_view_frame_is_explained_to_the_model():
    """render.wrist_camera frames (H, 2H): the system message says which view is which; one view: as before."""
    from policies.vlm_explorer import TWO_VIEWS

    explorer = _explorer("http://127.0.0.1:9")  # messages only: nothing is sent
    assert explorer.messages(_obs(40, 80).image)[0]["content"].endswith(TWO_VIEWS)
    assert explorer.messages(_obs(40, 40).image)[0]["content"] == explorer.system
