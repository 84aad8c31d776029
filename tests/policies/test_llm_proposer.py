"""The LLM proposer's client against a local HTTP server that speaks the OpenAI chat-completions
protocol (the remote model is the one thing that cannot run here)."""

from __future__ import annotations

import json

import pytest

from envs.suite import generate_tasks, suite_tasks
from policies.llm_proposer import ProposerUnavailable, chat, merge_proposals, propose
from schemas.config import ProposerConfig, TasksConfig
from schemas.experts import load_expert_table
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
    assert outcome.rejected == {"schema": 1, "unknown_spec": 1, "colour_not_said": 1, "repeated_colour": 1,
                                "repeated_instruction": 1}  # lift-red says `pick up the red block` already
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


@pytest.mark.parametrize("status", [503, 429, 408])  # a server error, its rate limit, its timeout
def test_server_errors_and_rate_limits_are_retried_then_reported(serve_chat, status):
    server = serve_chat(("{}", status, 0.0))
    config = ProposerConfig(url=f"http://127.0.0.1:{server.server_port}/v1", model="m", retries=2, timeout_s=5)
    with pytest.raises(ProposerUnavailable, match=f"HTTP {status}"):
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


def _merged(proposals: list[dict], config: TasksConfig | None = None):
    config = config or TasksConfig(specs=["lift", "stack"], colours=["red", "green", "blue"])
    tasks = generate_tasks(config, seed=0)
    outcome = merge_proposals(json.dumps({"tasks": proposals}), _specs(config), config, tasks)
    return outcome, {t.task_id: t for t in outcome.tasks}


def test_held_out_text_is_refused_in_any_case_or_punctuation_and_by_its_words():
    """An LLM capitalises and ends with a full stop; MiniLM is uncased. `Hoist the red block into the air.` is
    lift-red's held-out paraphrase all the same, and `shove`/`brick` are words only the held-out wording says."""
    said = ["Hoist the red block into the air.", "Raise the red BRICK", "lift the red block up high"]
    outcome, tasks = _merged([{"spec": "lift", "colours": {"target": "red"}, "instructions": said}])
    assert "lift the red block up high" in tasks["lift-red"].instructions
    assert not {"Hoist the red block into the air.", "Raise the red BRICK"} & set(tasks["lift-red"].instructions)
    assert outcome.rejected == {"held_out_instruction": 2}


def test_repeated_empty_and_other_tasks_instructions_are_not_added():
    said = ["raise the red block", "Raise the red block!", "stack the red block on the green block"]  # stack-red-green's
    outcome, tasks = _merged([{"spec": "lift", "colours": {"target": "red"}, "instructions": said}])
    assert tasks["lift-red"].instructions.count("raise the red block") == 1
    assert outcome.rejected == {"repeated_instruction": 1, "other_task_instruction": 1}
    config = TasksConfig(specs=["mw-push"])  # no colour to say: an empty instruction passes the colour check
    outcome, tasks = _merged([{"spec": "mw-push", "instructions": ["", " ", "nudge the puck to the goal"]}], config)
    assert tasks["mw-push"].instructions[-1] == "nudge the puck to the goal"
    assert outcome.rejected == {"empty_instruction": 2}


def test_the_colour_must_be_said_as_a_word():
    """`desired` holds `red`; `Red` is red."""
    unsaid = ["lift the desired block", "lift the stored cube", "raise the covered block"]
    said = ["Lift the Red block", "RED block up", "raise the red cube"]
    outcome, tasks = _merged([{"spec": "lift", "colours": {"target": "red"}, "instructions": unsaid},
                              {"spec": "lift", "colours": {"target": "red"}, "instructions": said}])
    assert outcome.rejected == {"colour_not_said": 1} and outcome.valid == 1


def test_a_new_task_needs_enough_instructions_left_and_a_binding_the_config_takes():
    """Two of three instructions left after the filter: no task (a TaskRecord says a task three ways; one
    registered with two would fail every later load). A binding outside tasks.include, or one whose scripted
    expert is below target, is not made a task by a proposal either."""
    short = ["lift the purple cube", "Lift the purple cube.", "raise the purple block"]
    outcome, tasks = _merged([{"spec": "lift", "colours": {"target": "purple"}, "instructions": short}])
    assert "lift-purple" not in tasks and outcome.rejected == {"repeated_instruction": 1, "too_few_instructions": 1}

    included = TasksConfig(specs=["lift"], colours=["red", "green"], include=["lift-red"])
    new = ["lift the blue cube", "raise the blue block", "pick the blue block up"]
    outcome, tasks = _merged([{"spec": "lift", "colours": {"target": "blue"}, "instructions": new}], included)
    assert "lift-blue" not in tasks and outcome.rejected == {"not_included": 1}

    weak = next(t for t in suite_tasks() if t.task_id in load_expert_table().flagged())
    spec = load_specs()[weak.spec].spec
    said = [f"{text} now" for text in weak.instructions]
    config = TasksConfig(specs=[spec.name])
    tasks = generate_tasks(config, 0)
    outcome = merge_proposals(json.dumps({"tasks": [{"spec": spec.name, "colours": weak.object_colours, "instructions": said}]}),
                              {spec.name: spec}, config, tasks)
    assert weak.task_id not in {t.task_id for t in outcome.tasks} and outcome.rejected == {"weak_expert": 1}

