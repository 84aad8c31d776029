"""Benchmarks: `sim2act bench envs | warehouse | rollout | train | rl | panels | soak`."""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from flows.cli.common import (Commands, add_campaign_options, add_workspace_option, output_file, positive_int,
                              print_or_write, scratch_folder)
from schemas.config import ConfigError
from schemas.tasks import FAMILIES
from schemas.workspace import Workspace, write_text_atomically


def cmd_bench_envs(args: argparse.Namespace) -> int:
    from bench.envs import bench_envs, markdown

    if args.steps < 1:
        raise ConfigError(f"bench envs: --steps must be at least 1, got {args.steps}")
    rows = bench_envs(args.family or list(FAMILIES), args.steps)
    table = markdown(rows, args.command_line)
    print(table)
    if args.out:
        write_text_atomically(args.out, table)
        print(f"written to {args.out}")
    return 0


def cmd_bench_warehouse(args: argparse.Namespace) -> int:
    from bench.warehouse import QUICK, BenchSizes, bench_warehouse, markdown

    sizes = QUICK if args.quick else BenchSizes()
    if args.sql_steps:
        if min(args.sql_steps) < 1:
            raise ConfigError(f"bench warehouse: --sql-steps must be positive, got {args.sql_steps}")
        sizes = sizes.model_copy(update={"sql_steps": args.sql_steps})
    measures = bench_warehouse(sizes, args.scratch)
    return print_or_write(args, json.dumps([m.model_dump() for m in measures], indent=1), markdown(measures, args.command_line))


def cmd_bench_rollout(args: argparse.Namespace) -> int:
    if args.mix:
        from bench.rollout_mix import QUICK as MIX_QUICK, MixSizes, bench_mix, markdown as mix_markdown

        mix = bench_mix(MIX_QUICK if args.quick else MixSizes(), args.scratch)
        return print_or_write(args, mix.model_dump_json(indent=1), mix_markdown(mix, args.command_line))
    from bench.rollout import QUICK, RolloutSizes, bench_rollout, markdown

    bench = bench_rollout(QUICK if args.quick else RolloutSizes(), args.scratch)
    return print_or_write(args, bench.model_dump_json(indent=1), markdown(bench, args.command_line))


def cmd_bench_train(args: argparse.Namespace) -> int:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")  # the fine-tuned encoder case loads MiniLM from disk
    os.environ.setdefault("TOKENIZERS_PARALLELISM", "false")
    from bench.train import QUICK, TrainSizes, bench_train, markdown

    sizes = QUICK if args.quick else TrainSizes()
    if args.cases:
        sizes = sizes.model_copy(update={"cases": args.cases.split(",")})
    bench = bench_train(sizes, args.scratch)
    return print_or_write(args, bench.model_dump_json(indent=1), markdown(bench, args.command_line))


def cmd_bench_rl(args: argparse.Namespace) -> int:
    from bench.rl import bench_rl, markdown, rl_cases
    from flows.cli.common import campaign_config
    from stages.generate_tasks import campaign_tasks

    if args.steps < 1:
        raise ConfigError(f"bench rl: --steps must be at least 1, got {args.steps}")
    config = campaign_config(args)
    if args.agent:
        config = config.model_copy(update={"baselines": config.baselines.model_copy(update={"agents": args.agent})})
    tasks, _ = campaign_tasks(Workspace.at(args.workspace), config)  # as the campaign's, where it ran in the workspace
    tasks = [t for t in tasks if not args.family or t.family in args.family]
    cases = rl_cases(config, tasks, args.steps, _explored_steps(args, config.name), args.sac_encoder)
    if not cases:
        among = "" if config.baselines.families is None else f" (baselines.families: {config.baselines.families})"
        raise ConfigError(f"bench rl: expected an RL agent (baselines.agents: ppo, sac) and a family with seen tasks "
                          f"it acts in, got agents {config.baselines.agents} over {sorted({t.family for t in tasks})}"
                          f"{among}")
    costs = bench_rl(cases)
    return print_or_write(args, json.dumps([c.model_dump() for c in costs], indent=1),
                          markdown(costs, config.name, args.command_line))


def _explored_steps(args: argparse.Namespace, campaign: str) -> dict[str, int]:
    """family -> environment steps the campaign explored in the workspace: the RL agents' budgets
    (none where the workspace holds no warehouse)."""
    from flows.cli.common import open_catalog
    from stages.baselines import exploration_steps

    if not Workspace.at(args.workspace).catalog.exists():
        return {}
    _, catalog = open_catalog(args)
    units = [key for (key,) in catalog.query(
        "SELECT unit_key FROM stage_runs WHERE stage = 'explore' AND campaign = ?", [campaign])]
    return exploration_steps(catalog, units) if units else {}


def cmd_bench_soak(args: argparse.Namespace) -> int:
    from bench.soak import KINDS, markdown, soak
    from envs.pool import log_stages_to_stderr
    from flows.cli.common import campaign_config, campaign_flags

    if args.kills < 1:
        raise ConfigError(f"bench soak: --kills must be at least 1, got {args.kills}")
    low, high = args.wait
    if not 0 < low <= high:
        raise ConfigError(f"bench soak: --wait expects 0 < MIN <= MAX seconds, got {low:g} {high:g}")
    kinds = args.kinds.split(",")
    if not kinds or set(kinds) - set(KINDS):
        raise ConfigError(f"bench soak: --kinds expects some of {','.join(KINDS)}, got {args.kinds!r}")
    # a bad campaign flag (or --iterations) costs one line here, not one per restart
    campaign_config(args, {} if args.iterations is None else {"iterations": args.iterations})
    run_args = campaign_flags(args) + (["--iterations", str(args.iterations)] if args.iterations is not None else [])
    out = args.out or Path(args.workspace) / "soak" / "soak.md"
    log_stages_to_stderr()  # each kill and check as it happens

    def write(result) -> None:  # after every check: a soak killed itself keeps what it saw
        write_text_atomically(out, markdown(result, args.command_line))
        write_text_atomically(out.with_suffix(".json"), result.model_dump_json(indent=1))

    result = soak(run_args, Path(args.workspace), args.kills, args.seed, (low, high), Path(args.workspace) / "soak", write,
                  kinds)
    print(markdown(result, args.command_line))
    print(f"written to {out}")
    return 0 if result.final_sha256_ok and result.ended in ("finished", "stopped") else 1  # not: too few kills


def cmd_bench_panels(args: argparse.Namespace) -> int:
    from dashboards.panel_times import bench_panels, markdown
    from dashboards.reads import campaigns as warehouse_campaigns
    from flows.cli.common import open_catalog

    if args.repeats < 1:
        raise ConfigError(f"bench panels: --repeats must be at least 1, got {args.repeats}")
    _, catalog = open_catalog(args)
    if not catalog.path.exists():
        raise ConfigError(f"bench panels: no warehouse at {args.workspace} (run a campaign there first)")
    campaigns = warehouse_campaigns(catalog)
    if not campaigns:
        raise ConfigError(f"bench panels: the warehouse at {args.workspace} holds no campaign (run one there first)")
    campaign = args.campaign or (campaigns[0] if len(campaigns) == 1 else None)
    if campaign not in campaigns:
        raise ConfigError(f"bench panels: expected --campaign, one of {', '.join(campaigns) or '(none)'}; "
                          f"got {args.campaign or 'none'}")
    [(steps, shards)] = catalog.query("SELECT coalesce(sum(num_rows) FILTER (WHERE table_name = 'steps'), 0), "
                                      "count(*) FROM shards")
    times = bench_panels(catalog, campaign, args.repeats)
    facts = f"campaign {campaign!r}, {steps:,} steps in {shards:,} shards"
    return print_or_write(args, json.dumps([t.model_dump() for t in times], indent=1), markdown(times, facts, args.command_line))


def register(commands: Commands) -> None:
    bench = commands.add_parser("bench", help="benchmarks: speed side by side, as ratios")
    bench_commands = bench.add_subparsers(dest="bench_command", required=True)
    bench_env = bench_commands.add_parser("envs", help="env steps/s per family: raw physics, env, adapter, render")
    bench_env.add_argument("--steps", type=int, default=500, help="timed control steps per layer")
    bench_env.add_argument("--family", choices=FAMILIES, action="append", help="default: every family")
    bench_env.add_argument("--out", type=output_file, help="also write the table as markdown here")
    bench_env.set_defaults(handler=cmd_bench_envs)

    def bench_parser(name: str, help: str, quick: str, handler) -> argparse.ArgumentParser:
        """A benchmark command with the options every side-by-side bench takes."""
        command = bench_commands.add_parser(name, help=help)
        command.add_argument("--json", action="store_true", help="print the figures as JSON")
        command.add_argument("--quick", action="store_true", help=quick)
        command.add_argument("--scratch", type=scratch_folder, help="folder for the throwaway workspaces (default: $TMPDIR)")
        command.add_argument("--out", type=output_file, help="also write the table as markdown here")
        command.set_defaults(handler=handler)
        return command

    bench_parser("warehouse", "ingest, SQL and training-read speed vs bare references",
                 "small sizes (seconds, for a smoke check)", cmd_bench_warehouse
                 ).add_argument("--sql-steps", type=int, nargs="+", help="warehouse sizes for the SQL measure")
    bench_parser("rollout", "explore stage vs plain robosuite loops, steps/s",
                 "a few short episodes (seconds, for a smoke check)", cmd_bench_rollout
                 ).add_argument("--mix", action="store_true",
                                help="instead: the stage over a sample of the generalist's tasks as it was (meshes 1.0, "
                                     "robosuite's controller), decimated, decimated with the fused substeps, and with "
                                     "the colliding meshes drawn decimated too; the same episodes, per family, each "
                                     "side cold (units build their environments) and warm (the same worker again, as "
                                     "a campaign explores)")
    bench_parser("train", "train stage samples/s vs in-memory batches; policy latency",
                 "a few steps, default case only (seconds, a smoke check)", cmd_bench_train
                 ).add_argument("--cases", metavar="A,B", help="run only these cases (stage always runs): "
                                "stage, memory, precision (fp32 vs bf16, CPU), workers0, resnet18, vit, minilm, cuda, act")
    rl = add_campaign_options(bench_commands.add_parser(
        "rl", help="an RL baseline's environment step (PPO, SAC), CPU ms per family; with a workspace that explored "
                   "the campaign, the hours its budget takes"))
    rl.add_argument("--steps", type=int, default=400, help="timed training steps per agent")
    rl.add_argument("--agent", choices=["ppo", "sac"], action="append", help="default: the campaign's baselines.agents")
    rl.add_argument("--family", choices=FAMILIES, action="append", help="default: every family with seen tasks")
    rl.add_argument("--sac-encoder", choices=["critic", "separate"], action="append",
                    help="SAC's encoder, each one given side by side (baselines.sac_encoder); default: the campaign's")
    rl.add_argument("--json", action="store_true", help="print the figures as JSON")
    rl.add_argument("--out", type=output_file, help="also write the table as markdown here")
    rl.set_defaults(handler=cmd_bench_rl)
    panels = add_workspace_option(bench_commands.add_parser(
        "panels", help="each dashboard panel's query timed on a warehouse (target: 1 s)"))
    panels.add_argument("--campaign", help="whose panels (default: the warehouse's one campaign)")
    panels.add_argument("--repeats", type=int, default=3, help="warm runs per panel, after the first")
    panels.add_argument("--json", action="store_true", help="print the figures as JSON")
    panels.add_argument("--out", type=output_file, help="also write the table as markdown here")
    panels.set_defaults(handler=cmd_bench_panels)
    soak = add_campaign_options(bench_commands.add_parser(
        "soak", help="run a campaign through random SIGKILLs (flow, worker, server), checking its finished parts"))
    soak.add_argument("--iterations", type=positive_int, help="as `sim2act run --iterations` (1 or more: a soak explores)")
    soak.add_argument("--kills", type=int, default=10, help="SIGKILLs before the campaign is let finish")
    soak.add_argument("--wait", type=float, nargs=2, default=(60.0, 600.0), metavar=("MIN", "MAX"),
                      help="seconds from a (re)start to its kill, drawn uniformly")
    soak.add_argument("--kinds", default="flow,worker,server", metavar="A,B",
                      help="the processes to kill, in turn: flow (the run itself), worker (a rollout worker; while "
                           "training, a DataLoader worker), "
                           "server (Prefect's temporary API server)")
    soak.add_argument("--seed", type=int, default=0, help="draws the waits and the order of the kinds killed")
    soak.add_argument("--out", type=output_file, help="the report (Markdown, and .json beside it); default: "
                      "<workspace>/soak/soak.md, rewritten after every check")
    soak.set_defaults(handler=cmd_bench_soak)
