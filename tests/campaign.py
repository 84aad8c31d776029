"""A real smoke campaign through the CLI, for tests that need a finished workspace: run it
(optionally SIGKILLed when a log line matches), and snapshot its rows and digests."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from pathlib import Path

from schemas.workspace import Workspace
from tests.conftest import SIM2ACT, sim2act_env
from warehouse.catalog import Catalog

# a task spec file of tasks no campaign explores, for `sim2act eval --tasks`
NEW_TASKS = """
defaults: {family: robosuite, expert: pick_place}
specs:
  - name: lift-elsewhere
    env: Lift
    objects:
      target: {colours: [red, yellow]}
    templates:
      - elevate the {target} block
      - hoist up the {target} cube
      - bring the {target} block upward
    horizon: 20
"""

ROW_COUNTS = """
SELECT (SELECT count(*) FROM tasks), (SELECT count(*) FROM episodes), (SELECT count(*) FROM steps),
       (SELECT count(*) FROM filter_decisions), (SELECT count(*) FROM evaluations), (SELECT count(*) FROM models),
       (SELECT count(*) FROM deployments), (SELECT count(*) FROM stage_runs), (SELECT count(*) FROM shards),
       (SELECT count(DISTINCT episode_id) FROM steps)
"""


def run_campaign(workspace: Path, prefect_api: str, kill_at: str | None = None, *extra: str) -> tuple[str, float]:
    """Run `sim2act run --preset smoke [extra]`; with kill_at, SIGKILL the whole process group as
    soon as a log line matches it. Returns (output, seconds)."""
    started = time.monotonic()
    process = subprocess.Popen(
        [SIM2ACT, "run", "--preset", "smoke", "--workspace", str(workspace), *extra],
        env=sim2act_env(prefect_api), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        start_new_session=True,
    )
    lines = []
    for line in process.stdout:
        lines.append(line)
        if kill_at and re.search(kill_at, line):
            os.killpg(process.pid, signal.SIGKILL)
            break
    process.wait(timeout=600)
    output = "".join(lines)
    if kill_at:
        assert process.returncode == -signal.SIGKILL, output[-3000:]
    else:
        assert process.returncode == 0, output[-5000:]
    return output, time.monotonic() - started


def snapshot(workspace: Path) -> dict:
    """The campaign's row counts, episodes, dataset digests and shard bytes (sha256)."""
    catalog = Catalog(Workspace.at(workspace).catalog)
    return {
        "counts": catalog.query(ROW_COUNTS)[0],
        "episodes": catalog.query("SELECT episode_id, explorer, num_steps, episode_return FROM episodes ORDER BY 1"),
        "digests": catalog.query("SELECT iteration, dataset_digest, triplets FROM iterations ORDER BY 1"),
        "shards": catalog.query("SELECT path, sha256 FROM shards WHERE table_name <> 'instructions' ORDER BY 1"),
    }


def iteration_zero_snapshot(workspace: Path) -> dict:
    """Iteration 0's episodes, steps, shard bytes, dataset digest and model: equal in a campaign
    stopped after iteration 0 (`--set iterations=1`) and in the reference that went on."""
    catalog = Catalog(Workspace.at(workspace).catalog)
    return {
        "episodes": catalog.query("SELECT episode_id, explorer, num_steps, episode_return FROM episodes "
                                  "WHERE iteration = 0 ORDER BY 1"),
        "steps": catalog.query("SELECT count(*) FROM steps WHERE iteration = 0"),
        "shards": catalog.query("SELECT path, sha256 FROM shards WHERE iteration = 0 AND table_name <> 'instructions' "
                                "ORDER BY 1"),
        "digest": catalog.query("SELECT dataset_digest, triplets FROM iterations WHERE iteration = 0"),
        "model": catalog.query("SELECT model_key FROM models WHERE iteration = 0"),
        # the weights themselves (a key is a hash of settings and data: a resume that trained otherwise keeps it)
        "weights": [weights_digest(Workspace.at(workspace).checkpoint(key))
                    for (key,) in catalog.query("SELECT model_key FROM models WHERE iteration = 0 ORDER BY 1")],
        "evaluations": catalog.query("SELECT task_id, split, instruction, episodes, successes, episode_successes, "
                                     "mean_return FROM evaluations WHERE iteration = 0 ORDER BY ALL"),
    }


def weights_digest(checkpoint: Path) -> str:
    """sha256 over every member's tensors, by name: equal only for bit-identical weights."""
    import hashlib

    import torch

    from policies.policy import checkpoint_members

    digest = hashlib.sha256()
    for member in checkpoint_members(torch.load(checkpoint, weights_only=False)):
        for name in sorted(member):
            digest.update(name.encode() + member[name].detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()
