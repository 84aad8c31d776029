"""The LLM proposer's client against a local HTTP server that speaks the OpenAI chat-completions
protocol (the remote model is the one thing that cannot run here)."""

from __future__ import annotations

import json

import pytest

from envs.suite import generate_tasks
from policies.llm_proposer import ProposerUnavailable, chat, propose
from schemas.config import ProposerConfig, TasksConfig
from schemas.task_spec import load_specs
from tests.chat_server import closed_port

ANSWER = {"tasks": [
    {"spec": "lift", "colours": {"target": "purple"},  # a new binding: a new task
     "instructions": ["lift the purple cube", "pick the purple block up", "raise the purple block"]},
    {"spec": "lift", "colours": {"target": "red"},  # an existing task: extra paraphrases
     "instructions": ["hoist the red cube", "pick up the red block", "get the red block off the table"]},
    {"spec": "lift", "colours": {"target": "teal"}, "instructions": ["a", "b", "c"]},  # teal: not in the schema
    {"spec": "juggle", "colours": {}, "instructions": ["x", "y", "z"]},  # no such spec
    {"spec": "lift", "colours": {"target": "blue"}, "instructions": ["lift it", "raise it", "take it"]},  # unsaid
    {"spec": "stack", "colours": {"pick": "red", "place": "red"},
     "instructions": ["stack red on red", "red on red", "put red on red"]},  # repeated colour
]}


def _config(url: str, **extra) -> TasksConfig:
    proposer = ProposerConfig(url=url, model="tiny-llm", retries=1, timeout_s=5, **extra)
    return TasksConfig(specs=["lift", "stack"], colours=["red", "green", "blue"], proposer=proposer)


def _specs(config: TasksConfig):
    return {name: entry.spec for name, entry in load_specs().items() if name in config.specs}


def test_valid_proposals_become_tasks_and_invalid_ones_are_counted(serve_chat, monkeypatch):
    server = serve_chat(json.dumps(ANSWER))
    monkeypatch.setenv("TINY_KEY", "secret")
    config = _config(f"http://127.0.0.1:{server.server_port}/v1", api_key_env="TINY_KEY")
    templates = generate_tasks(config, seed=0)
    outcome = propose(config, _specs(config), templates)
    assert (outcome.valid, outcome.new_tasks) == (2, 1)
    assert outcome.rejected == {"schema": 1, "unknown_spec": 1, "colour_not_said": 1, "repeated_colour": 1}
    tasks = {t.task_id: t for t in outcome.tasks}
    assert tasks["lift-purple"].instructions[0] == "lift the purple cube" and tasks["lift-purple"].horizon == 80
    assert tasks["lift-red"].instructions[0] == "pick up the red block"  # the canonical stays first
    assert "hoist the red cube" in tasks["lift-red"].instructions
    assert len(outcome.tasks) == len(templates) + 1
    [(path, headers, body)] = server.requests
    assert path == "/v1/chat/completions" and body["model"] == "tiny-llm"
    assert headers["Authorization"] == "Bearer secret"
    assert [m["role"] for m in body["messages"]] == ["system", "user"] and "stack" in body["messages"][1]["content"]


def test_an_answer_that_is_not_json_is_rejected_not_fatal(serve_chat):
    server = serve_chat("Sure! Here are some tasks: lift the red cube")
    config = _config(f"http://127.0.0.1:{server.server_port}/v1")
    outcome = propose(config, _specs(config), generate_tasks(config, 0))
    assert outcome.rejected == {"not_json": 1} and outcome.new_tasks == 0


def test_an_unreachable_endpoint_fails_with_a_clear_message():
    config = _config(f"http://127.0.0.1:{closed_port()}/v1")
    with pytest.raises(ProposerUnavailable, match=r"did not answer .* after 2 tries"):
        propose(config, _specs(config), generate_tasks(config, 0))


def test_fallback_to_templates_only_when_the_config_says_so():
    config = _config(f"http://127.0.0.1:{closed_port()}/v1", fallback_to_templates=True)
    templates = generate_tasks(config, 0)
    outcome = propose(config, _specs(config), templates)
    assert outcome.tasks == templates and outcome.rejected == {"unreachable": 1}


def test_server_errors_are_retried_then_reported(serve_chat):
    server = serve_chat(("{}", 503, 0.0))
    config = ProposerConfig(url=f"http://127.0.0.1:{server.server_port}/v1", model="m", retries=2, timeout_s=5)
    with pytest.raises(ProposerUnavailable, match="HTTP 503"):
        chat(config, [{"role": "user", "content": "hi"}])
    assert len(server.requests) == 3


def test_a_proposal_that_repeats_a_held_out_instruction_is_not_trained_on(serve_chat):
    """Evaluation says `hoist the red block into the air` (lift-red's held-out paraphrase); a model that proposed
    it for training would make that split a seen one. (The held-out wording says no training colour word, so
    `colour_not_said` refuses a proposal of it already.)"""
    said = ["hoist the red block into the air", "raise the red block high", "lift the red block up"]
    answer = {"tasks": [{"spec": "lift", "colours": {"target": "red"}, "instructions": said}]}
    server = serve_chat(json.dumps(answer))
    config = _config(f"http://127.0.0.1:{server.server_port}/v1")
    outcome = propose(config, _specs(config), generate_tasks(config, seed=0))
    lift_red = {t.task_id: t for t in outcome.tasks}["lift-red"]
    assert {"raise the red block high", "lift the red block up"} <= set(lift_red.instructions)
    assert "hoist the red block into the air" not in lift_red.instructions
    assert outcome.rejected == {"held_out_instruction": 1}
