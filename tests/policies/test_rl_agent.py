"""The RL baselines train for hours at a campaign's budget: a kill resumes from the last checkpoint,
SAC's replay buffer included, and a kill during a checkpoint's swap leaves the one before."""

import json
import tempfile

import numpy as np
import pytest

from envs.gym_env import InstructedTasksEnv
from envs.suite import generate_tasks
from policies.rl_agent import CHECKPOINT, PREVIOUS, WRITING, last_checkpoint, learn_with_checkpoints, save_checkpoint
from schemas.config import RandomiseConfig, RenderConfig, TasksConfig


class Killed(Exception):
    """Stands for a SIGKILL: the training stops where it is, nothing more is saved."""


def _env(spec: str) -> InstructedTasksEnv:
    tasks = generate_tasks(TasksConfig(specs=[spec], colours=["red", "green"]), seed=0)
    said = sorted({text for task in tasks for text in task.instructions})
    embeddings = {text: np.full(8, i, dtype=np.float32) for i, text in enumerate(said)}
    return InstructedTasksEnv(tasks, embeddings, RenderConfig(image_size=48), RandomiseConfig())


def _killed_after(env: InstructedTasksEnv, steps: int) -> InstructedTasksEnv:
    step, taken = env.step, []

    def counted(action):
        taken.append(1)
        if len(taken) > steps:
            raise Killed(steps)
        return step(action)
    env.step = counted
    return env


@pytest.mark.parametrize("algorithm, spec, budget, every, kill, saved_at", [
    ("ppo", "nav-room", 600, 200, 450, 300),  # rollouts of 300 steps: the checkpoint at the second's start
    ("sac", "lift", 240, 100, 180, 100),  # one-step rollouts: a checkpoint at 100, the next due at 200
])
def test_a_killed_training_resumes_from_its_last_checkpoint(tmp_path, monkeypatch, algorithm, spec, budget, every, kill,
                                                           saved_at):
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    env = _killed_after(_env(spec), kill)
    with pytest.raises(Killed):
        learn_with_checkpoints(algorithm, env, budget, 0, tmp_path, every)
    last = last_checkpoint(tmp_path)
    assert last == tmp_path / CHECKPOINT
    state = json.loads((last / "state.json").read_text())
    assert state["num_timesteps"] == saved_at
    assert state["episodes"] <= env.episodes_finished  # the counters as they were at the checkpoint

    again = _env(spec)  # a new process: a fresh environment
    progress = []
    agent, resumed_at = learn_with_checkpoints(
        algorithm, again, budget, 0, tmp_path, every,
        on_progress=lambda done, at: progress.append((done, at, again.episodes_finished, again.successes)))
    assert resumed_at == saved_at
    assert agent.num_timesteps >= budget
    # the first rollout starts where the checkpoint was, its episode counters the checkpoint's (a fresh
    # environment counting from 0 would pass a ">=" after a few episodes)
    assert progress[0] == (saved_at, saved_at, state["episodes"], state["successes"])
    if algorithm == "sac":  # the replay buffer came back: the transitions before the checkpoint and the ones after
        assert agent.replay_buffer.size() == budget
    assert not list(temp.glob("SB3-*"))  # no log folder per start in the machine's /tmp


def test_a_kill_during_the_swap_leaves_the_checkpoint_before(tmp_path):
    assert last_checkpoint(tmp_path) is None
    (tmp_path / PREVIOUS).mkdir()
    (tmp_path / PREVIOUS / "state.json").write_text("{}")
    (tmp_path / WRITING).mkdir()  # the new one half-written: never read
    assert last_checkpoint(tmp_path) == tmp_path / PREVIOUS
    (tmp_path / CHECKPOINT).mkdir()  # renamed in, its state not there: not whole
    assert last_checkpoint(tmp_path) == tmp_path / PREVIOUS
    (tmp_path / CHECKPOINT / "state.json").write_text("{}")
    assert last_checkpoint(tmp_path) == tmp_path / CHECKPOINT


def test_a_checkpoint_is_on_disk_before_it_is_swapped_in(tmp_path, monkeypatch):
    """Every file of the new checkpoint and its folder are fsynced before the renames, the folder after them."""
    import os

    class Saved:
        num_timesteps = 200

        def save(self, path):
            path.write_bytes(b"agent")

        def save_replay_buffer(self, path):
            path.write_bytes(b"replay")

    class Counted:
        episodes_finished, successes = 3, 1

    events: list[str] = []
    real_fsync, real_rename = os.fsync, type(tmp_path).rename

    def fsync(handle):
        events.append("fsync " + os.path.basename(os.readlink(f"/proc/self/fd/{handle}")))
        real_fsync(handle)

    def rename(self, target):
        events.append(f"rename {self.name}")
        return real_rename(self, target)
    monkeypatch.setattr(os, "fsync", fsync)  # the module the checkpoint's fsync_path (warehouse.store) calls
    monkeypatch.setattr(type(tmp_path), "rename", rename)
    save_checkpoint(Saved(), Counted(), tmp_path)
    events.clear()
    save_checkpoint(Saved(), Counted(), tmp_path)  # a second: the first is renamed aside, then removed
    second = events
    assert sorted(second[:4]) == sorted(f"fsync {n}" for n in ("agent.zip", "replay.pkl", "state.json", WRITING))
    assert second[4:] == [f"rename {CHECKPOINT}", f"rename {WRITING}", f"fsync {tmp_path.name}"]
    assert last_checkpoint(tmp_path) == tmp_path / CHECKPOINT and not (tmp_path / PREVIOUS).exists()


def test_a_save_after_a_kill_between_renames_keeps_the_only_whole_checkpoint_until_replaced(tmp_path, monkeypatch):
    class Saved:  # what save_checkpoint asks of an agent: save(path) and its step count
        num_timesteps = 200

        def save(self, path):
            path.write_bytes(b"agent")

    class Counted:
        episodes_finished, successes = 3, 1

    (tmp_path / PREVIOUS).mkdir()  # a kill after `checkpoint` became `checkpoint.old`, before the new one moved in
    (tmp_path / PREVIOUS / "state.json").write_text('{"num_timesteps": 100}')
    real_rename = type(tmp_path).rename

    def killed_at_the_rename(self, target):
        raise Killed("between the writing and the swap")
    monkeypatch.setattr(type(tmp_path), "rename", killed_at_the_rename)
    with pytest.raises(Killed):
        save_checkpoint(Saved(), Counted(), tmp_path)
    assert last_checkpoint(tmp_path) == tmp_path / PREVIOUS  # the earlier one was not removed first
    monkeypatch.setattr(type(tmp_path), "rename", real_rename)
    save_checkpoint(Saved(), Counted(), tmp_path)
    assert last_checkpoint(tmp_path) == tmp_path / CHECKPOINT and not (tmp_path / PREVIOUS).exists()
    assert json.loads((tmp_path / CHECKPOINT / "state.json").read_text()) == {
        "num_timesteps": 200, "episodes": 3, "successes": 1}
