"""`sim2act bench warehouse`: the warehouse's speed, side by side in one run.

- ingest: triplets/s and MB/s through the shard writer (schema check, zstd, fsync, sha256,
  atomic no-clobber move) vs a bare `pyarrow.parquet.write_table` of the same tables, same codec;
  and through the registrar as well;
- SQL: per-task success over N steps through the catalog's `steps` view, with the shards as
  explore writes them, and (reference) the same rows in 1M-row files; the same after
  `sim2act warehouse compact`, and the `task_success` view (the episodes) before and after it;
- training reads: decoded samples/s through the DataLoader (SQL selection, 2 workers, shuffle
  buffer, frames decoded) vs iterating an in-memory NumPy array of the same frames;
- bytes per triplet on disk;
- registration: one more explore unit registered into a catalog already holding N units (the
  10,000th by default) vs into an empty catalog — the registrar's cost must stay flat in N.
"""

from __future__ import annotations

import datetime
import json
import resource
import statistics
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from pydantic import BaseModel

from bench.synthetic import TASKS, explore_unit, register_explore_unit
from bench.tables import cores, table as markdown_table
from schemas.tables import EPISODES, STEPS
from schemas.version import SCHEMA_VERSION
from schemas.workspace import Workspace
from warehouse.catalog import Catalog
from warehouse.compaction import compact as compact_warehouse
from warehouse.shard_writer import ZSTD_LEVEL, write_shard

SUCCESS_BY_TASK = "SELECT task_id, avg(success::INTEGER) AS success_rate, count(*) AS steps FROM steps GROUP BY task_id"


class BenchSizes(BaseModel):
    ingest_triplets: int = 20_000
    sql_steps: list[int] = [1_000_000, 10_000_000]
    sql_shard_steps: int = 2_000  # rows per shard as explore writes them (K episodes of one task)
    read_samples: int = 20_000
    read_workers: int = 2
    batch_size: int = 64
    shuffle_buffer: int = 2_048
    steps_per_episode: int = 100
    registered_units: int = 10_000  # the registration measure times the units after this many


# seconds, for tests and a smoke check; the figures mean little at these sizes
QUICK = BenchSizes(ingest_triplets=800, sql_steps=[20_000], sql_shard_steps=1_000, read_samples=800,
                   shuffle_buffer=256, registered_units=200)
REGISTRATION_TIMED = 10  # units registered and timed one by one, at each end


class Measure(BaseModel):
    name: str
    value: float
    unit: str
    reference: float | None = None  # the side-by-side figure it is compared with
    ratio: float | None = None
    target: str | None = None
    note: str = ""


def _best(run, repeats: int = 2) -> float:
    """Fastest of `repeats` runs: the machine's noise only ever adds time."""
    return min(run() for _ in range(repeats))


def bench_ingest(root: Path, sizes: BenchSizes) -> list[Measure]:
    units = max(1, sizes.ingest_triplets // (4 * sizes.steps_per_episode))
    tables = [explore_unit(f"u{u}", seed=u, steps=sizes.steps_per_episode, unique_frames=sizes.steps_per_episode)
              for u in range(units)]
    triplets = sum(t["steps"].num_rows for t in tables)
    megabytes = sum(t["steps"].nbytes + t["episodes"].nbytes for t in tables) / 1e6
    workspace = Workspace.at(root / "ingest").create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    attempt = iter(range(100))

    def bare() -> float:
        folder = root / f"bare{next(attempt)}"
        folder.mkdir()
        started = time.perf_counter()
        for u, t in enumerate(tables):
            for name, table in t.items():
                pq.write_table(table, folder / f"{name}-{u}.parquet", compression="zstd", compression_level=ZSTD_LEVEL)
        return time.perf_counter() - started

    def ours(register: bool) -> float:
        run = next(attempt)
        started = time.perf_counter()
        for u, t in enumerate(tables):
            key = f"explore-{run}-{u}"
            shards = [write_shard(name, table, workspace.shard_path(name, run, key)) for name, table in t.items()]
            if register:
                catalog.register_unit(unit_key=key, stage="explore", campaign="bench", iteration=run, summary={},
                                      shards=shards)
        return time.perf_counter() - started

    bare_s, writer_s, registered_s = _best(bare), _best(lambda: ours(False)), _best(lambda: ours(True))
    [(disk_bytes, rows)] = catalog.query(
        "SELECT sum(num_bytes), sum(num_rows) FILTER (WHERE table_name = 'steps') FROM shards"
    )
    return [
        Measure(name="ingest: shard writer", value=triplets / writer_s, unit="triplets/s",
                reference=triplets / bare_s, ratio=bare_s / writer_s, target="ratio >= 0.8",
                note=f"{megabytes / writer_s:,.0f} MB/s vs bare pq.write_table {megabytes / bare_s:,.0f} MB/s; "
                     f"{units} shards of {triplets // units} triplets"),
        Measure(name="ingest: shard writer + registrar", value=triplets / registered_s, unit="triplets/s",
                reference=triplets / bare_s, ratio=bare_s / registered_s,
                note="each unit checked (footer, schema, sha256) and committed to the catalog"),
        Measure(name="bytes per triplet on disk", value=disk_bytes / rows, unit="bytes",
                note="84x84 frames, zstd; episodes shards included (rendered robosuite frames: see docs/warehouse.md)"),
    ]


def bench_registration(root: Path, sizes: BenchSizes) -> list[Measure]:
    """register_unit's wall time for small explore units (steps + episodes shards) into an empty catalog
    (the reference) and into one already holding `registered_units` - 1 units. The units in between are
    registered in bulk for the setup's speed: the rows and shard files register_unit would have written
    (one transaction; the bench, not the product, reaches into the catalog for it)."""
    from warehouse.catalog import _insert, check_rows

    workspace = Workspace.at(root / "registration").create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()

    def shards_of(key: str, seed: int) -> list:
        tables = explore_unit(key, seed=seed, episodes=1, steps=4, unique_frames=1)
        return [write_shard(name, table, workspace.shard_path(name, 0, key), catalog.store) for name, table in tables.items()]

    def timed(keys: list[str], iteration: int = 0) -> float:
        seconds = []
        for key in keys:
            shards = shards_of(key, len(seconds))
            started = time.perf_counter()
            catalog.register_unit(unit_key=key, stage="explore", campaign="bench", iteration=iteration, summary={},
                                  shards=shards)
            seconds.append(time.perf_counter() - started)
        return statistics.median(seconds)

    empty_s = timed([f"explore-first-{u:02d}" for u in range(REGISTRATION_TIMED)])
    bulk = [(f"explore-bulk-{u:06d}", shards_of(f"explore-bulk-{u:06d}", u))
            for u in range(sizes.registered_units - 1 - REGISTRATION_TIMED)]
    now = datetime.datetime.now(datetime.timezone.utc).replace(tzinfo=None)
    with catalog._transaction() as con:
        _insert(con, "stage_runs", check_rows("stage_runs", [
            {"unit_key": key, "stage": "explore", "campaign": "bench", "iteration": 0, "finished_at": now,
             "wall_s": 0.0, "summary": json.dumps({})} for key, _ in bulk]))
        _insert(con, "shards", check_rows("shards", [
            {"path": shard.path.relative_to(catalog.warehouse).as_posix(), "table_name": shard.table, "unit_key": key,
             "campaign": "bench", "iteration": 0, "num_rows": shard.num_rows, "num_bytes": shard.num_bytes,
             "sha256": shard.sha256, "schema_version": SCHEMA_VERSION, "view_part": None,
             "stored_in": None, "row_offset": None}
            for key, shards in bulk for shard in shards]))
        catalog._refresh_views(con, {"steps", "episodes"}, everything=True)
    nth = sizes.registered_units
    full_s = timed([f"explore-last-{u:02d}" for u in range(REGISTRATION_TIMED)])
    [(shards,)] = catalog.query("SELECT count(*) FROM shards")
    # the views name every shard file, and DuckDB reads and writes the catalog's view text at every
    # connect and close: after iteration 0 is compacted they name its few files, so a registration into
    # iteration 1 should cost near what the 10,000th does, not more (the catalog's tables still hold every row)
    compact_warehouse(catalog, [0])
    compacted_s = timed([f"explore-next-{u:02d}" for u in range(REGISTRATION_TIMED)], iteration=1)
    return [Measure(
        name=f"registration: unit {nth:,} (after {nth - 1:,})", value=full_s * 1000, unit="ms",
        reference=empty_s * 1000, ratio=empty_s / full_s, target="ratio >= 0.5 (flat in the units registered)",
        note=f"median of {REGISTRATION_TIMED} explore units (steps + episodes shards) each side; {shards:,} shards "
             f"registered at the end; reference: the first {REGISTRATION_TIMED} units of an empty catalog"),
        Measure(
        name=f"registration: unit {nth + REGISTRATION_TIMED + 1:,}, its iteration 0 compacted", value=compacted_s * 1000,
        unit="ms", reference=empty_s * 1000, ratio=empty_s / compacted_s, target="ratio >= 0.5 (flat in the units registered)",
        note=f"the same catalog after `sim2act warehouse compact --iteration 0`; median of {REGISTRATION_TIMED} units "
             "registered into iteration 1; reference: the first units of an empty catalog")]


def _sql_steps(n: int, seed: int) -> pa.Table:
    """`n` steps of the real schema with the columns the query reads drawn, the rest null (a
    columnar scan never reads them)."""
    rng = np.random.default_rng(seed)
    episode = np.arange(n) // 100
    columns = {field.name: pa.nulls(n, field.type) for field in STEPS}
    columns.update(
        campaign=pa.array(np.full(n, "bench")), iteration=pa.array(np.zeros(n, np.int32)),
        episode_id=pa.array(np.char.add("e", episode.astype(str))),
        task_id=pa.array(np.asarray(TASKS)[episode % len(TASKS)]), step=pa.array((np.arange(n) % 100).astype(np.int32)),
        success=pa.array(rng.random(n) < 0.05),
    )
    return pa.table(columns, schema=STEPS)


def _sql_episodes(steps: pa.Table) -> pa.Table:
    """The episodes of `_sql_steps`' steps (100 steps each), the columns `task_success` reads drawn."""
    n = steps.num_rows // 100
    firsts = steps.take(np.arange(n) * 100)
    columns = {field.name: pa.nulls(n, field.type) for field in EPISODES}
    columns.update(
        campaign=firsts["campaign"], iteration=firsts["iteration"], episode_id=firsts["episode_id"],
        task_id=firsts["task_id"], explorer=pa.array(np.full(n, "expert")),
        num_steps=pa.array(np.full(n, 100, np.int32)), episode_return=pa.array(np.arange(n) % 7 * 1.0),
        success=pa.array(np.arange(n) % 3 == 0),
    )
    return pa.table(columns, schema=EPISODES)


def bench_sql(root: Path, sizes: BenchSizes) -> list[Measure]:
    measures = []
    for n in sizes.sql_steps:
        workspace = Workspace.at(root / f"sql-{n}").create()
        catalog = Catalog(workspace.catalog)
        catalog.initialise()
        rows = _sql_steps(n, seed=n)
        episodes = _sql_episodes(rows)
        shards = [
            shard for start in range(0, n, sizes.sql_shard_steps) for shard in (
                write_shard("steps", rows.slice(start, sizes.sql_shard_steps),
                            workspace.shard_path("steps", 0, f"explore-{start:010d}")),
                write_shard("episodes", episodes.slice(start // 100, sizes.sql_shard_steps // 100),
                            workspace.shard_path("episodes", 0, f"explore-{start:010d}")))
        ]
        for first in range(0, len(shards), 200):  # registered 200 shards per unit, to keep setup short
            catalog.register_unit(unit_key=f"explore-{first}", stage="explore", campaign="bench", iteration=0,
                                  summary={}, shards=shards[first : first + 200])
        big = root / f"sql-{n}-compact"
        big.mkdir()
        for start in range(0, n, 1_000_000):
            pq.write_table(rows.slice(start, 1_000_000), big / f"{start}.parquet", compression="zstd",
                           row_group_size=100_000)

        def timed(sql: str) -> float:
            with catalog.connect(read_only=True) as con:
                def query() -> float:
                    con.execute(sql).fetchall()  # warm: file metadata cached, as for a user's second query
                    started = time.perf_counter()
                    con.execute(sql).fetchall()
                    return time.perf_counter() - started

                return _best(query, 3)

        task_success = "SELECT * FROM task_success"
        sharded, sharded_tasks = timed(SUCCESS_BY_TASK), timed(task_success)
        big_files = timed(SUCCESS_BY_TASK.replace("FROM steps", f"FROM read_parquet('{big.as_posix()}/*.parquet')"))
        summary = compact_warehouse(catalog)
        compacted, compacted_tasks = timed(SUCCESS_BY_TASK), timed(task_success)
        target = {1_000_000: "<= 100 ms", 10_000_000: "<= 1000 ms"}.get(n)
        steps_shards = len(shards) // 2
        measures += [
            Measure(name=f"SQL: success per task over {n:,} steps", value=sharded * 1000, unit="ms",
                    reference=big_files * 1000, ratio=big_files / sharded, target=target,
                    note=f"{steps_shards:,} shards of {sizes.sql_shard_steps:,} steps as explore writes them; "
                         "reference: the same rows in 1M-row files (100K-row groups)"),
            Measure(name=f"SQL: success per task over {n:,} steps, compacted", value=compacted * 1000, unit="ms",
                    reference=big_files * 1000, ratio=big_files / compacted,
                    note=f"after `sim2act warehouse compact` ({summary.sources:,} shards into {summary.files} files "
                         f"in {summary.wall_s:.1f} s): the steps keep one row group per source shard, which the "
                         "training reader reads whole; reference: the same rows in 1M-row files (100K-row groups)"),
            Measure(name=f"SQL: task_success over {n:,} steps, compacted", value=compacted_tasks * 1000, unit="ms",
                    reference=sharded_tasks * 1000, ratio=sharded_tasks / compacted_tasks,
                    target="<= 100 ms" if n >= 10_000_000 else None,
                    note=f"the view over {n // 100:,} episodes in 100K-row groups; reference: the same view before "
                         f"the compaction ({steps_shards:,} episodes shards as explore writes them)"),
        ]
        shutil.rmtree(workspace.root)
        shutil.rmtree(big)
    return measures


def bench_reads(root: Path, sizes: BenchSizes) -> list[Measure]:
    from schemas.frames import decode_frame
    from warehouse.training_reader import StepBatches, select_rows, training_loader

    workspace = Workspace.at(root / "reads").create()
    catalog = Catalog(workspace.catalog)
    catalog.initialise()
    for u in range(max(1, sizes.read_samples // (4 * sizes.steps_per_episode))):
        register_explore_unit(workspace, f"explore-r{u}", seed=u, steps=sizes.steps_per_episode,
                              unique_frames=sizes.steps_per_episode)
    [(warehouse_bytes,)] = catalog.query("SELECT sum(num_bytes) FROM shards")
    ranges = select_rows(catalog, "NOT done")
    samples = sum(r.stop - r.start for r in ranges)
    batches = StepBatches(ranges, sizes.batch_size, sizes.shuffle_buffer, seed=0, epochs=1, workers=sizes.read_workers)
    # the training's own loader (spawned workers), kept across passes: a pass is one epoch, the first
    # also starts the workers, which a training does once
    loader = training_loader(batches, sizes.read_workers, persistent=True)

    def streamed() -> float:
        started = time.perf_counter()
        count = sum(len(batch["action"]) for batch in loader)
        assert count == batches.rows_per_epoch, (count, batches.rows_per_epoch)
        return time.perf_counter() - started

    def in_memory() -> float:
        started = time.perf_counter()
        order = np.random.default_rng(0).permutation(len(frames))
        for first in range(0, len(frames), sizes.batch_size):
            chosen = order[first : first + sizes.batch_size]
            np.ascontiguousarray(frames[chosen]), actions[chosen]
        return time.perf_counter() - started

    first_s = streamed()
    stream_s = _best(streamed)
    loader = None  # the last reference: its workers exit and are waited for, so their peak counts below
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    frames = np.stack([decode_frame(image) for (image,) in catalog.query("SELECT image FROM steps WHERE NOT done")])
    actions = np.zeros((len(frames), 7), np.float32)
    memory_s = _best(in_memory)
    return [
        Measure(name="training reads: DataLoader over the warehouse", value=samples / stream_s, unit="samples/s",
                reference=samples / memory_s, ratio=memory_s / stream_s, target=">= 5,000 samples/s",
                note=f"{samples:,} decoded 84x84 frames, SQL selection, {sizes.read_workers} spawned workers (the "
                     f"first epoch took {max(0.0, first_s - stream_s):.1f} s longer: their start and first reads, not "
                     f"counted), shuffle buffer {sizes.shuffle_buffer:,}, batch {sizes.batch_size}; reference: batches "
                     f"gathered from an in-memory uint8 array; peak worker RSS {peak_mb:,.0f} MiB for a "
                     f"{warehouse_bytes / 1e6:,.0f} MB warehouse"),
    ]


def bench_warehouse(sizes: BenchSizes, scratch: Path | None = None) -> list[Measure]:
    if scratch is not None:  # --scratch names a folder to use: made if missing, like a workspace
        Path(scratch).mkdir(parents=True, exist_ok=True)
    root = Path(tempfile.mkdtemp(prefix="sim2act-bench-", dir=scratch))
    try:  # reads first: the peak RSS of this process's children it reads is then its own workers' alone
        reads = bench_reads(root, sizes)
        return bench_ingest(root, sizes) + bench_registration(root, sizes) + bench_sql(root, sizes) + reads
    finally:
        shutil.rmtree(root, ignore_errors=True)


def _figure(value: float | None, unit: str = "") -> str:
    if value is None:
        return ""
    return f"{value:,.0f}" if value >= 100 else f"{value:,.2f}" if unit != "ms" else f"{value:,.1f}"


def markdown(measures: list[Measure], command: str) -> str:
    lines = [
        "# Warehouse benchmark",
        "",
        f"Made by `{command}` on {datetime.date.today().isoformat()}, {cores()} cores, no GPU used. Each figure is the best "
        "of its repeats; the reference is measured in the same run. Ratio = ours / reference in speed terms "
        "(above 1: faster than the reference).",
        "",
        *markdown_table(["measure", "ours", "reference", "ratio", "target", "notes"], [
            [m.name, f"{_figure(m.value, m.unit)} {m.unit}", _figure(m.reference, m.unit),
             None if m.ratio is None else f"{m.ratio:.2f}", m.target or "", m.note] for m in measures]),
    ]
    return "\n".join(lines) + "\n"
