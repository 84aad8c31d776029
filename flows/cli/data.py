"""The warehouse: `sim2act sql`, `export lerobot`, `replay`, `labels`, `warehouse verify`, `warehouse compact`."""

from __future__ import annotations

import argparse
import logging
import sys
import time
from contextlib import nullcontext
from pathlib import Path

from envs.pool import log_stages_to_stderr
from flows.cli.common import Commands, add_workspace_option, open_catalog, output_file
from flows.run_lock import exclusive_run, reading_shard_files, rewriting_shard_files
from schemas.config import ConfigError
from schemas.workspace import Workspace, write_text_atomically


def cmd_sql(args: argparse.Namespace) -> int:
    import duckdb

    from warehouse.catalog import Catalog
    from warehouse.sql import run_sql

    if args.as_of_iteration is not None and args.as_of_iteration < 0:
        raise ConfigError(f"sql: --as-of-iteration must be 0 or more, got {args.as_of_iteration}")
    catalog = Catalog(Workspace.at(args.workspace).catalog)
    if args.as_of_iteration is not None and catalog.path.exists():
        held = _iterations(catalog)
        if not held or args.as_of_iteration > held[-1]:  # the warehouse as it is now: a typo, most likely
            raise ConfigError(f"sql: --as-of-iteration {args.as_of_iteration}: the warehouse's latest iteration is "
                              f"{held[-1]}" if held else f"sql: --as-of-iteration {args.as_of_iteration}: the warehouse "
                              "holds no iteration yet")
    try:
        print(run_sql(catalog, args.query, args.format, args.as_of_iteration))
    except duckdb.Error as exc:
        print(f"sim2act: SQL error: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


def cmd_export_lerobot(args: argparse.Namespace) -> int:
    from envs.pool import Progress
    from warehouse.export_lerobot import FETCH_MB, export_lerobot

    if args.fps is not None and args.fps < 1:
        raise ConfigError(f"export lerobot: --fps must be at least 1, got {args.fps}")
    if args.fetch_mb is not None and not 0 < args.fetch_mb < float("inf"):  # NaN too
        raise ConfigError(f"export lerobot: --fetch-mb must be positive, got {args.fetch_mb:g}")
    workspace, catalog = open_catalog(args)
    log_stages_to_stderr()
    bar: list[Progress] = []  # made at the first episode, when the selection's size is known

    def report(done: int, total: int) -> None:  # the bar on a terminal; a log line per 1% (rate, ETA)
        if not bar:
            bar.append(Progress(logging.getLogger("sim2act.export"), "export lerobot", total, "episodes", "episodes"))
        bar[0].advance(1, 1, log=done == total or done % max(total // 100, 1) == 0)

    with reading_shard_files(workspace, "export lerobot") if catalog.path.exists() else nullcontext():
        summary = export_lerobot(catalog, args.out_dir, args.where, fps=args.fps, include_rejected=args.include_rejected,
                                 repo_id=args.repo_id, progress=report,
                                 fetch_mb=FETCH_MB if args.fetch_mb is None else args.fetch_mb)
    if bar:
        bar[0].close()
    print(f"{summary.episodes} episodes, {summary.frames} frames, {summary.tasks} tasks, "
          f"{summary.bytes / 1e6:.1f} MB: LeRobotDataset v3.0 at {summary.out_dir}")
    return 0


def cmd_replay(args: argparse.Namespace) -> int:
    from envs.replay import replay

    result = replay(Workspace.at(args.workspace), args.episode_id, args.camera, args.size, args.out, args.fps)
    print(f"{result.frames} frames of {args.episode_id} ({result.render.camera}, {result.render.image_size} px, "
          f"one per step) written to {result.path}")
    return 0


def cmd_labels(args: argparse.Namespace) -> int:
    from envs.label_audit import audit_labels, markdown
    from envs.pool import Progress

    if args.iteration < 0:
        raise ConfigError(f"labels: --iteration must be 0 or more, got {args.iteration}")
    _, catalog = open_catalog(args)
    log_stages_to_stderr()
    bar: list[Progress] = []

    def report(done: int, total: int) -> None:  # the bar on a terminal; a log line per episode (rate, ETA)
        if done == 0:  # before the first episode: the bar starts its clock
            bar.append(Progress(logging.getLogger("sim2act.labels"), "labels", total, "episodes", "episodes"))
        else:
            bar[0].advance(1, 1)

    table = markdown(audit_labels(catalog, args.iteration, args.explorer, args.campaign, progress=report))
    if bar:
        bar[0].close()
    if args.out:
        write_text_atomically(args.out, table + "\n")
    print(table)
    return 0


def cmd_warehouse_verify(args: argparse.Namespace) -> int:
    workspace, catalog = open_catalog(args)
    with reading_shard_files(workspace, "warehouse verify") if catalog.path.exists() else nullcontext():
        bad = catalog.verify(full=args.full)
    for path, reason in bad:
        print(f"quarantined {path}: {reason}")
    [(files,)] = catalog.query("SELECT (SELECT count(*) FROM shards WHERE stored_in IS NULL) + (SELECT count(*) FROM compacted)")
    print(f"{files} registered file(s) verified{' (sha256 too)' if args.full else ''}, {len(bad)} quarantined "
          f"to {catalog.quarantine_location}; the next `sim2act run` redoes their units")
    return 1 if bad else 0


def cmd_warehouse_compact(args: argparse.Namespace) -> int:
    from warehouse.compaction import compact

    if args.iteration is not None and any(k < 0 for k in args.iteration):
        raise ConfigError(f"warehouse compact: --iteration must be 0 or more, got {_listed(args.iteration)}")
    workspace, catalog = open_catalog(args)
    if not catalog.path.exists():
        raise ConfigError(f"warehouse compact: no warehouse at {workspace.warehouse} (run `sim2act run` first)")
    held = _iterations(catalog)
    missing = [k for k in args.iteration or [] if k not in held]
    if missing:
        raise ConfigError(f"warehouse compact: --iteration {_listed(missing)}: the warehouse holds iteration(s) "
                          f"{_listed(held) or 'none'}")
    started = time.monotonic()

    def report(done: int, total: int, plan) -> None:
        rate = done / max(time.monotonic() - started, 1e-9)
        print(f"[{done}/{total}] {plan.table} iteration {plan.iteration}: {len(plan.sources)} shards, "
              f"{plan.num_rows:,} rows; {rate:.2f} files/s, ETA {(total - done) / rate:.0f}s", flush=True)

    # no campaign writes the warehouse meanwhile, and nothing trains from, exports or verifies its files
    with exclusive_run(workspace, "warehouse compact"), rewriting_shard_files(workspace):
        catalog.clean_orphans()  # a killed compaction's unregistered file, or its sources left behind
        summary = compact(catalog, args.iteration, progress=report)
    for path, reason in summary.quarantined:
        print(f"quarantined {path}: {reason}")
    if not summary.files:
        print("nothing to compact: every iteration's shards are compacted already (or one per table)")
        return 1 if summary.quarantined else 0
    print(f"{summary.sources:,} shards ({summary.bytes_before / 1e6:.1f} MB) compacted into {summary.files} files "
          f"({summary.bytes_after / 1e6:.1f} MB, {summary.rows:,} rows) in {summary.wall_s:.1f} s; queries, "
          "snapshots and trainings read them as before")
    return 1 if summary.quarantined else 0


def _iterations(catalog) -> list[int]:
    """The iterations the warehouse holds shards of (every campaign's), in order."""
    return [k for (k,) in catalog.query("SELECT DISTINCT iteration FROM shards ORDER BY 1")]


def _listed(numbers: list[int]) -> str:
    return ", ".join(str(n) for n in numbers)


def register(commands: Commands) -> None:
    sql = commands.add_parser("sql", help="read-only SQL over the warehouse (tasks, episodes, steps, triplets, ...)")
    sql.add_argument("query")
    sql.add_argument("--format", choices=("table", "csv", "json"), default="table")
    sql.add_argument("--as-of-iteration", type=int, metavar="K", help="see the warehouse as it was after iteration K (of every campaign in it: name "
                     "yours in the query)")
    add_workspace_option(sql).set_defaults(handler=cmd_sql)

    export = commands.add_parser("export", help="write a warehouse selection in another project's format")
    export_commands = export.add_subparsers(dest="export_command", required=True)
    lerobot = export_commands.add_parser("lerobot", help="a LeRobotDataset v3.0 (Parquet + MP4), kept episodes")
    lerobot.add_argument("out_dir", type=Path, help="a new or empty folder")
    lerobot.add_argument("--where", help="SQL over the steps columns; whole episodes with a matching step go out")
    lerobot.add_argument("--include-rejected", action="store_true", help="also episodes the filter rejected")
    lerobot.add_argument("--fetch-mb", type=float,
                         help="MB of encoded frames read per query (default 64): bounds the export's memory, "
                              "whatever its size")
    lerobot.add_argument("--fps", type=int, default=None,
                         help="frames per second; default: the family's control rate (robosuite 20, MetaWorld 80, "
                              "navigation 10)")
    lerobot.add_argument("--repo-id", default="sim2act/export")
    add_workspace_option(lerobot).set_defaults(handler=cmd_export_lerobot)

    replay = commands.add_parser("replay", help="re-render a stored episode from its MuJoCo states into an MP4")
    replay.add_argument("episode_id")
    replay.add_argument("--camera", help="default: the episode's own (agentview, frontview, birdview, sideview)")
    replay.add_argument("--size", type=int, help="image side in pixels; default: the episode's own")
    replay.add_argument("--out", type=output_file, help="default: ./<episode_id>_<camera>_<size>px.mp4")
    replay.add_argument("--fps", type=int, default=None,
                        help="frames per second (one frame per step; default: the family's control rate)")
    add_workspace_option(replay).set_defaults(handler=cmd_replay)

    labels = commands.add_parser(
        "labels", help="replay an iteration's expert-labelled episodes: what the labels say, in which phase, and why")
    labels.add_argument("--iteration", type=int, required=True, metavar="K")
    labels.add_argument("--explorer", default="policy%",
                        help="SQL LIKE pattern on episodes.explorer (default 'policy%%': the champion's; 'expert')")
    labels.add_argument("--campaign", help="whose episodes (default: the one campaign of the workspace that has them)")
    labels.add_argument("--out", type=output_file, help="also write the table to this Markdown file")
    add_workspace_option(labels).set_defaults(handler=cmd_labels)

    warehouse = commands.add_parser("warehouse", help="warehouse upkeep")
    warehouse_commands = warehouse.add_subparsers(dest="warehouse_command", required=True)
    verify = warehouse_commands.add_parser("verify", help="check every registered shard, quarantine bad ones")
    verify.add_argument("--full", action="store_true", help="also compare each file's sha256 with the catalog's")
    add_workspace_option(verify).set_defaults(handler=cmd_warehouse_verify)
    compact = warehouse_commands.add_parser(
        "compact", help="concatenate each iteration's small shards into large files (faster queries at scale)")
    compact.add_argument("--iteration", type=int, nargs="+", metavar="K", help="only these iterations (default: all)")
    add_workspace_option(compact).set_defaults(handler=cmd_warehouse_compact)
