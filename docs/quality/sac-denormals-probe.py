"""How much of a trained SAC's Adam state is denormal, and what an update costs with and without
`policies.precision.denormals_flushed` (docs/bench-rl.md). Loads an RL baseline's checkpoint (agent and replay, as
the baselines stage saves them every `baselines.checkpoint_every` steps), counts the denormals in its optimisers'
moments, then times `train` (10 warm-up updates, then blocks of 50) in one mode: run it once per mode, in separate
processes (a flushed update rounds the moments it writes, so one process cannot time both). One thread; from the
repository root, e.g. both modes at once, a core each:

    .venv/bin/python docs/quality/sac-denormals-probe.py <workspace>/models/baselines-<key>/checkpoint flushed &
    .venv/bin/python docs/quality/sac-denormals-probe.py <workspace>/models/baselines-<key>/checkpoint kept; wait
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import policies.rl_sac as rl_sac  # noqa: E402
from policies.rl_agent import agent_class, without_log_folder  # noqa: E402
from policies.rl_encoder import encoder_precision, skip_critic_encoder_in_actor_loss  # noqa: E402


def denormal_moments(optimizer: torch.optim.Optimizer) -> tuple[int, int]:
    """(denormal entries, all entries) of the optimiser's Adam moments."""
    tiny, found, total = torch.finfo(torch.float32).tiny, 0, 0
    for state in optimizer.state.values():
        for moment in (state["exp_avg"], state["exp_avg_sq"]):
            found += int(((moment != 0) & (moment.abs() < tiny)).sum())
            total += moment.numel()
    return found, total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path, help="a SAC checkpoint folder: agent.zip and replay.pkl")
    parser.add_argument("mode", choices=["flushed", "kept"], help="the update with denormals flushed, or kept")
    parser.add_argument("--blocks", type=int, default=4, help="timed blocks of 50 updates")
    parser.add_argument("--sac-encoder", choices=["separate", "critic"], default="separate",
                        help="the checkpoint's baselines.sac_encoder: its update is that class's")
    args = parser.parse_args()
    if not (args.checkpoint / "agent.zip").is_file() or not (args.checkpoint / "replay.pkl").is_file():
        sys.exit(f"expected a SAC checkpoint folder with agent.zip and replay.pkl, got {args.checkpoint}")
    torch.set_num_threads(1)
    if args.mode == "kept":
        rl_sac.denormals_flushed = contextlib.nullcontext
    agent = without_log_folder(agent_class("sac", args.sac_encoder).load(args.checkpoint / "agent.zip", device="cpu"))
    agent.load_replay_buffer(args.checkpoint / "replay.pkl")
    skip_critic_encoder_in_actor_loss(agent)
    for name in ("actor", "critic"):
        found, total = denormal_moments(getattr(agent, name).optimizer)
        print(f"{name}'s Adam moments: {found:,} of {total:,} denormal ({100 * found / total:.0f}%)")
    with tempfile.TemporaryDirectory() as cache:  # the precision probe's cache, not the workspace's
        print(encoder_precision(agent, Path(cache))[1])
    agent._current_progress_remaining = 0.9  # a learning rate schedule reads it; SB3's default is constant
    agent.train(gradient_steps=10, batch_size=agent.batch_size)
    timed = []
    for _ in range(args.blocks):
        started = time.perf_counter()
        agent.train(gradient_steps=50, batch_size=agent.batch_size)
        timed.append(1000 * (time.perf_counter() - started) / 50)
    print(f"{args.mode}: ms an update, blocks of 50: {', '.join(f'{ms:.1f}' for ms in timed)}")


if __name__ == "__main__":
    main()
