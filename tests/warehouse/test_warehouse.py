"""The warehouse on real files: registration checks, snapshots, ready views, quarantine,
streaming training reads, and two registrars in two processes."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter

import numpy as np
import pyarrow as pa
import pytest
import torch

from schemas.workspace import Workspace
from tests.warehouse.filled import fill
from warehouse.catalog import Catalog
from warehouse.shard_writer import SchemaMismatch, write_shard
from warehouse.sql import run_sql
from warehouse.training_reader import RowRange, SelectionError, StepBatches, partition, select_rows, training_loader


@pytest.fixture
def filled(tmp_path) -> Workspace:
    workspace = Workspace.at(tmp_path).create()
    fill(workspace, iterations=2, units=2, episodes=3, steps=10)
    return workspace


def test_every_catalog_table_has_its_declared_columns(filled):
    Catalog(filled.catalog).check_layout()


def test_a_row_with_a_wrong_column_is_refused_naming_it(filled):
    catalog = Catalog(filled.catalog)
    bad = {"model_key": "m", "campaign": "c", "iteration": 0, "checkpoint_path": "x", "dataset_digest": "d",
           "dataset_shards": [], "train_samples": "many", "final_loss": 1.0, "unit_key": "m"}
    with pytest.raises(SchemaMismatch, match="models: a value does not fit"):
        catalog.register_unit(unit_key="m", stage="train", campaign="c", iteration=0, summary={}, rows={"models": [bad]})
    with pytest.raises(SchemaMismatch, match="'final_los' is not in the schema"):
        catalog.register_unit(unit_key="m", stage="train", campaign="c", iteration=0, summary={},
                              rows={"models": [{**bad, "train_samples": 1, "final_los": 1.0}]})
    assert not catalog.is_registered("m")


def test_a_shard_with_a_mismatched_column_is_refused_naming_column_and_reason(filled, tmp_path):
    steps = register_steps_table(seed=3)
    mistyped = steps.set_column(steps.schema.get_field_index("reward"), "reward", steps["reward"].cast(pa.float64()))
    with pytest.raises(SchemaMismatch, match=r"steps: column 'reward' is double, expected float"):
        write_shard("steps", mistyped, filled.shard_path("steps", 0, "explore-x"))
    # the same file written by something else and handed to the registrar
    import pyarrow.parquet as pq

    path = filled.shard_path("steps", 0, "explore-y")
    pq.write_table(steps.drop_columns(["mocap"]), path)
    from warehouse.shard_writer import ShardFile, sha256_of

    shard = ShardFile("steps", path, steps.num_rows, path.stat().st_size, sha256_of(path))
    with pytest.raises(SchemaMismatch, match="column 'mocap' is missing"):
        Catalog(filled.catalog).register_unit(unit_key="explore-y", stage="explore", campaign="bench", iteration=0,
                                              summary={}, shards=[shard])
    assert not Catalog(filled.catalog).is_registered("explore-y")
    # a whole file whose rows or bytes are not what its writer said (a torn write, another file at the path)
    from dataclasses import replace

    from warehouse.catalog import ShardUnreadable

    path = filled.shard_path("steps", 0, "explore-z")
    pq.write_table(steps, path)
    true = ShardFile("steps", path, steps.num_rows, path.stat().st_size, sha256_of(path))
    for wrong in (replace(true, sha256="0" * 64), replace(true, num_rows=steps.num_rows + 1)):
        with pytest.raises(ShardUnreadable, match="differs from what its writer reported"):
            Catalog(filled.catalog).register_unit(unit_key="explore-z", stage="explore", campaign="bench", iteration=0,
                                                  summary={}, shards=[wrong])
        assert not Catalog(filled.catalog).is_registered("explore-z")
    assert not Catalog(filled.catalog).query("SELECT count(*) FROM shards WHERE unit_key = 'explore-z'")[0][0]


def register_steps_table(seed: int) -> pa.Table:
    from bench.synthetic import explore_unit

    return explore_unit("u", seed=seed, episodes=1, steps=3)["steps"]


def test_as_of_iteration_sees_the_warehouse_after_that_iteration(filled):
    catalog = Catalog(filled.catalog)
    now = catalog.query("SELECT max(iteration), count(*) FROM steps")[0]
    assert now == (1, 2 * 2 * 3 * 10)
    for table in ("steps", "episodes", "filter_decisions", "stage_runs", "shards", "dataset_composition"):
        assert catalog.query(f"SELECT max(iteration) FROM {table}", as_of_iteration=0) == [(0,)], table
    assert catalog.query("SELECT count(*) FROM steps", as_of_iteration=0) == [(2 * 3 * 10,)]
    assert catalog.query("SELECT count(*) FROM steps") == [(now[1],)]  # the snapshot changed nothing
    assert '"n": 60' in run_sql(catalog, "SELECT count(*) AS n FROM triplets", "json", as_of_iteration=0)


def test_ready_views_agree_with_the_raw_tables(filled):
    catalog = Catalog(filled.catalog)
    episodes = catalog.query("SELECT task_id, iteration, success, episode_id FROM episodes")
    expected = Counter((t, i) for t, i, _, _ in episodes)
    successes = Counter((t, i) for t, i, s, _ in episodes if s)
    rows = catalog.query("SELECT task_id, iteration, family, episodes, successes, success_rate FROM task_success")
    assert {(t, i): n for t, i, _, n, _, _ in rows} == dict(expected)
    for t, i, family, n, k, rate in rows:
        assert k == successes[(t, i)] and rate == pytest.approx(k / n)
        assert family == ("metaworld" if t.startswith("mw") else "robosuite")
    passes = catalog.query("SELECT iteration, reason, episodes, fraction FROM filter_pass_rates ORDER BY 1, 2")
    assert {r for _, r, _, _ in passes} <= {"kept", "low_return"} and any(r == "low_return" for _, r, _, _ in passes)
    for iteration in (0, 1):
        assert sum(f for i, _, _, f in passes if i == iteration) == pytest.approx(1.0)
    [(kept_triplets,)] = catalog.query("SELECT sum(kept_triplets) FROM dataset_composition")
    assert kept_triplets == catalog.query("SELECT count(*) FROM kept_steps")[0][0]


def test_a_campaign_filtered_again_or_its_tasks_made_again_counts_each_episode_once(filled):
    """A re-run with another filter.* decides the same episodes again, and a changed tasks.* registers the same
    ids again (here in another split): the views read the latest decision and the latest tasks unit."""
    import time

    from stages.filter import run_filter
    from tests.warehouse.filled import CONFIG

    catalog = Catalog(filled.catalog)
    before = {view: catalog.query(f"SELECT count(*), sum(episodes) FROM {view}")
              for view in ("task_success", "dataset_composition", "filter_pass_rates")}
    steps = catalog.query("SELECT count(*) FROM kept_steps")[0][0]
    time.sleep(0.01)  # after the first filter's units
    lenient = CONFIG.model_copy(update={"filter": CONFIG.filter.model_copy(update={"min_return": -1e9})})
    explore = [k for (k,) in catalog.query("SELECT unit_key FROM stage_runs WHERE stage = 'explore' ORDER BY 1")]
    run_filter(filled, lenient, 0, [k for k in explore if "-i0" in k])
    run_filter(filled, lenient, 1, [k for k in explore if "-i1" in k])
    [(episodes,)] = catalog.query("SELECT count(*) FROM episodes")
    assert catalog.query("SELECT sum(episodes) FROM filter_pass_rates")[0][0] == episodes
    assert catalog.query("SELECT sum(episodes), sum(kept_episodes) FROM dataset_composition")[0] == (episodes, episodes)
    assert catalog.query("SELECT count(*) FROM kept_steps")[0][0] == catalog.query("SELECT count(*) FROM steps")[0][0] > steps
    rows = catalog.query("SELECT * FROM tasks WHERE unit_key = 'tasks-test'")
    columns = [c for (c,) in catalog.query("SELECT column_name FROM duckdb_columns() WHERE table_name = 'tasks' "
                                            "ORDER BY column_index")]
    again = [{**dict(zip(columns, row)), "split": "unseen", "unit_key": "tasks-again"} for row in rows]
    catalog.register_unit(unit_key="tasks-again", stage="generate_tasks", campaign=CONFIG.name, iteration=0, summary={},
                          rows={"tasks": again})
    assert catalog.query("SELECT count(*), count(DISTINCT task_id), min(split) FROM task_families") == \
        [(len(rows), len(rows), "unseen")]
    assert catalog.query("SELECT count(*), sum(episodes) FROM task_success") == before["task_success"]


def test_an_iteration_indexed_under_two_filter_settings_gives_each_config_its_own_dataset(filled):
    """`sim2act train` took the first row the catalog gave (no tie-break, no check of its filter): the dataset of
    another filter.* than the config's. Now the config's, and of several the latest registered."""
    import time

    from stages.filter import run_filter
    from stages.index import latest_index, run_index
    from tests.warehouse.filled import CONFIG

    catalog = Catalog(filled.catalog)
    explore = [k for (k,) in catalog.query("SELECT unit_key FROM stage_runs WHERE stage = 'explore' AND iteration = 0 "
                                           "ORDER BY 1")]
    strict = run_index(filled, CONFIG, 0, explore, run_filter(filled, CONFIG, 0, explore).unit_keys, None)
    time.sleep(0.01)
    lenient_config = CONFIG.model_copy(update={"filter": CONFIG.filter.model_copy(update={"min_return": -1e9})})
    lenient = run_index(filled, lenient_config, 0, explore, run_filter(filled, lenient_config, 0, explore).unit_keys,
                        None)
    assert lenient.kept_episodes > strict.kept_episodes
    assert latest_index(filled, CONFIG.name, 0, CONFIG).unit_key == strict.unit_key
    assert latest_index(filled, CONFIG.name, 0, lenient_config).unit_key == lenient.unit_key
    assert latest_index(filled, CONFIG.name, 0).unit_key == lenient.unit_key  # the latest registered
    other = CONFIG.model_copy(update={"filter": CONFIG.filter.model_copy(update={"min_return": 3.0})})
    assert latest_index(filled, CONFIG.name, 0, other) is None


def test_a_corrupt_shard_is_quarantined_and_queries_keep_working(filled):
    catalog = Catalog(filled.catalog)
    [(victim, unit)] = catalog.query(
        "SELECT path, unit_key FROM shards WHERE table_name = 'steps' AND unit_key = 'explore-i1u0'"
    )
    path = filled.warehouse / victim
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])  # truncated, as by a full disk
    total = run_sql(catalog, "SELECT count(*) AS n FROM steps", "json")
    assert json.loads(total) == [{"n": 90}]  # three of the four units' steps
    assert not path.exists() and (catalog.quarantine_folder / victim).exists()
    assert not catalog.is_registered(unit)  # the next run redoes the unit
    quarantined = catalog.query("SELECT path, reason FROM quarantine ORDER BY path")
    assert len(quarantined) == 2 and any(victim == p and "Parquet" in r for p, r in quarantined)
    assert catalog.verify(full=True) == []


def test_verify_finds_a_file_whose_bytes_changed(filled):
    catalog = Catalog(filled.catalog)
    [(victim,)] = catalog.query("SELECT path FROM shards WHERE table_name = 'episodes' ORDER BY path LIMIT 1")
    import pyarrow.parquet as pq

    from bench.synthetic import explore_unit

    pq.write_table(explore_unit("other", seed=9, episodes=3, steps=10)["episodes"], filled.warehouse / victim)
    bad = catalog.verify(full=True)
    assert [p for p, _ in bad] == [victim] and "sha256" in bad[0][1]


def _actions(batches) -> list[tuple]:
    return [tuple(np.float32(a).tolist()) for b in batches for a in b["action"]]


def test_select_rows_and_stream_every_selected_step_once_per_epoch_across_workers(filled):
    catalog = Catalog(filled.catalog)
    where = "task_id LIKE 'lift%' AND step < 7"
    ranges = select_rows(catalog, where)
    expected = catalog.query(f"SELECT count(*) FROM steps WHERE {where}")[0][0]
    assert expected > 0 and sum(r.stop - r.start for r in ranges) == expected
    assert len(ranges) <= catalog.query(f"SELECT count(DISTINCT episode_id) FROM steps WHERE {where}")[0][0]
    batches = StepBatches(ranges, batch_size=5, shuffle_buffer=8, seed=1, epochs=2, workers=2, piece_rows=7)
    loader = training_loader(batches, workers=2)  # the training's own: spawned (test_training_loader.py)
    read = list(loader)
    assert [int(b["batch"]) for b in read] == list(range(len(batches))) and len(batches) == 2 * batches.batches_per_epoch
    assert all(b["image"].shape[1:] == (84, 84, 3) and b["image"].dtype == torch.uint8 for b in read)
    per_epoch = batches.batches_per_epoch
    stored = Counter(tuple(np.float32(a).tolist()) for (a,) in catalog.query(f"SELECT action FROM steps WHERE {where}"))
    for epoch in range(2):
        seen = Counter(_actions(read[epoch * per_epoch:(epoch + 1) * per_epoch]))
        # every step at most once; workers get equal shares, so up to workers - 1 steps sit an epoch out
        assert not seen - stored and sum((stored - seen).values()) == expected % 2
    assert _actions(read[:per_epoch]) != _actions(read[per_epoch:])  # each epoch reshuffled


def test_a_resumed_stream_reads_exactly_the_rest_of_the_sequence(filled):
    ranges = select_rows(Catalog(filled.catalog), "TRUE")
    sizes = dict(batch_size=4, shuffle_buffer=16, seed=3, epochs=3, piece_rows=9)
    for workers in (0, 2):
        full = list(training_loader(StepBatches(ranges, workers=workers, **sizes), workers))
        for start in (1, 7, len(full) // 2 + 1):
            rest = list(training_loader(StepBatches(ranges, workers=workers, start_batch=start, **sizes), workers))
            assert [int(b["batch"]) for b in rest] == list(range(start, len(full)))
            assert _actions(rest) == _actions(full[start:])
    shuffled = _actions(full[: len(full) // 3])
    in_order = [tuple(np.float32(a).tolist()) for (a,) in Catalog(filled.catalog).query(
        "SELECT action FROM steps ORDER BY episode_id, step")]
    assert shuffled != in_order[: len(shuffled)]


def test_partition_gives_every_worker_the_same_rows():
    ranges = [RowRange("a", 0, 10), RowRange("a", 20, 23), RowRange("b", 5, 30)]
    parts = partition(ranges, workers=3, piece_rows=4)
    rows = [[(p, r) for piece in part for p, a, b in piece for r in range(a, b)] for part in parts]
    assert [len(r) for r in rows] == [12, 12, 12]
    everything = [(r.path, n) for r in ranges for n in range(r.start, r.stop)]
    assert sorted(sum(rows, [])) == everything[:36]  # the last 38 % 3 rows of the selection sit out


def test_a_bad_selection_is_one_clear_error(filled):
    with pytest.raises(SelectionError, match="no_such_column"):
        select_rows(Catalog(filled.catalog), "no_such_column > 1")


def test_a_selection_reads_the_warehouse_and_no_other_file(filled):
    """train.where arrives from configs and the Prefect form: SQL that could read any file otherwise."""
    from warehouse.training_reader import check_where

    outside = "task_id IN (SELECT column0 FROM read_csv('/etc/passwd'))"
    for refuse in (lambda: check_where(outside), lambda: select_rows(Catalog(filled.catalog), outside)):
        with pytest.raises(SelectionError, match="file system operations are disabled"):
            refuse()
    assert select_rows(Catalog(filled.catalog), "task_id IN (SELECT task_id FROM tasks)")  # the catalog's own: fine


WRITER = """
import sys
from schemas.workspace import Workspace
from tests.warehouse.filled import register_explore
workspace = Workspace.at(sys.argv[1])
first, last = int(sys.argv[2]), int(sys.argv[3])
new = sum(register_explore(workspace, f"explore-c{u:03d}", 2, seed=u, episodes=2, steps=5) for u in range(first, last))
print(new)
"""


def test_two_processes_writing_and_registering_at_once_lose_and_duplicate_nothing(filled):
    # units 0..29 and 20..49: the overlap is computed, written and registered by both
    procs = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(filled.root), str(a), str(b)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=str(__import__("pathlib").Path(__file__).parents[2]))
        for a, b in ((0, 30), (20, 50))
    ]
    outputs = [p.communicate(timeout=300) for p in procs]
    assert all(p.returncode == 0 for p in procs), outputs
    assert sum(int(out) for out, _ in outputs) == 50  # each unit registered by exactly one of them
    catalog = Catalog(filled.catalog)
    assert catalog.query(
        "SELECT count(*), count(DISTINCT unit_key) FROM stage_runs WHERE unit_key LIKE 'explore-c%'") == [(50, 50)]
    assert catalog.query("SELECT count(*), count(DISTINCT episode_id) FROM episodes WHERE iteration = 2") == [(100, 100)]
    assert catalog.query("SELECT count(*) FROM steps WHERE iteration = 2") == [(500,)]
    assert catalog.verify(full=True) == []
    assert catalog.clean_orphans() == []  # nothing written that the catalog does not name


def test_the_cli_queries_snapshots_verifies_and_exports(filled, tmp_path, capsys):
    from flows.cli import main

    root = str(filled.root)
    assert main(["sql", "--workspace", root, "--as-of-iteration", "0", "--format", "csv",
                 "SELECT count(*) AS n FROM episodes"]) == 0
    assert capsys.readouterr().out.strip() == "n\n6"
    assert main(["sql", "--workspace", root, "SELECT nope FROM episodes"]) == 2
    assert 'SQL error: Binder Error: Referenced column "nope" not found' in capsys.readouterr().err
    assert main(["warehouse", "verify", "--full", "--workspace", root]) == 0
    assert "0 quarantined" in capsys.readouterr().out
    out = tmp_path / "lerobot"
    assert main(["export", "lerobot", str(out), "--workspace", root, "--where", "task_id LIKE 'lift%'"]) == 0
    info = json.loads((out / "meta" / "info.json").read_text())
    [(kept_lift,)] = Catalog(filled.catalog).query(
        "SELECT count(*) FROM filter_decisions WHERE kept AND task_id LIKE 'lift%'")
    assert info["codebase_version"] == "v3.0" and info["total_episodes"] == kept_lift > 0
    assert main(["export", "lerobot", str(out), "--workspace", root]) == 2  # not empty: refused
    assert "is a folder with files in it: export into a new one" in capsys.readouterr().err


def test_a_chunked_stream_carries_each_steps_next_actions_of_its_episode(filled):
    """Look-ahead past the selection (steps >= 7 are not selected but are read as a chunk's later
    steps), never across episodes, shorter at an episode's end."""
    catalog = Catalog(filled.catalog)
    ranges = select_rows(catalog, "step < 7 OR step = 9")
    stored = {(e, s): (a, x) for e, s, a, x in catalog.query("SELECT episode_id, step, action, expert_action FROM steps")}
    by_action = {tuple(np.float32(a).tolist()): key for key, (a, _) in stored.items()}
    read = list(StepBatches(ranges, batch_size=6, shuffle_buffer=8, seed=0, epochs=1, piece_rows=5, chunk=4))
    rows = 0
    for batch in read:
        for action, chunk, expert in zip(batch["action"], batch["action_chunk"], batch["expert_chunk"]):
            episode, step = by_action[tuple(np.float32(action).tolist())]
            later = [s for s in range(step, step + 4) if (episode, s) in stored]
            assert [tuple(np.float32(a).tolist()) for a in chunk] == [tuple(np.float32(stored[episode, s][0]).tolist())
                                                                    for s in later]
            assert expert == [stored[episode, s][1] for s in later]
            rows += 1
    assert rows == sum(r.stop - r.start for r in ranges) and min(len(c) for b in read for c in b["action_chunk"]) == 1
