"""`sim2act warehouse compact`: an iteration's small shards become a few large files, and nothing a
reader sees changes: queries, snapshots, the training stream batch for batch, verify and quarantine."""

from __future__ import annotations

import numpy as np
import pyarrow.parquet as pq
import pytest

from schemas.workspace import Workspace
from tests.warehouse.filled import fill
from warehouse.catalog import Catalog
from warehouse.compaction import compact, plan_compaction
from warehouse.training_reader import StepBatches, select_rows

QUERIES = [
    "SELECT task_id, iteration, episodes, successes FROM task_success ORDER BY ALL",
    "SELECT episode_id, step, reward, action FROM steps ORDER BY episode_id, step",
    "SELECT episode_id, kept, reason FROM filter_decisions ORDER BY ALL",
    "SELECT count(*), count(DISTINCT episode_id), sum(step) FROM triplets",
]


@pytest.fixture
def filled(tmp_path) -> Workspace:
    workspace = Workspace.at(tmp_path).create()
    fill(workspace, iterations=2, units=3, episodes=3, steps=10)
    return workspace


def _seen(catalog: Catalog) -> list:
    return [catalog.query(sql) for sql in QUERIES] + [catalog.query(QUERIES[1], as_of_iteration=0)]


def _batches(catalog: Catalog) -> list[tuple]:
    ranges = select_rows(catalog, "step % 3 <> 1")
    stream = StepBatches(ranges, batch_size=7, shuffle_buffer=9, seed=3, epochs=2, piece_rows=5, chunk=3)
    return [(b["batch"], np.asarray(b["image"]).tobytes(), str(b["action"]), str(b["action_chunk"])) for b in stream]


def _shard_files(workspace: Workspace) -> list[str]:
    return sorted(p.relative_to(workspace.warehouse).as_posix() for p in workspace.shards.rglob("*.parquet"))


def test_compaction_changes_where_rows_live_and_nothing_a_reader_sees(filled):
    catalog = Catalog(filled.catalog)
    before, batches, files = _seen(catalog), _batches(catalog), _shard_files(filled)
    some = ["explore-i0u0", "explore-i0u2"]  # the middle unit's rows lie between theirs once compacted
    chosen = [(r.path, r.start, r.stop) for r in select_rows(catalog, "TRUE", units=some)]
    shards = catalog.query("SELECT path, unit_key, sha256, num_rows FROM shards ORDER BY path")
    assert len(files) == 2 * 3 * 3  # iterations x units x (episodes, steps, filter_decisions)

    summary = compact(catalog)

    # one file per table and iteration, each source recorded where its rows went, in path order
    assert (summary.files, summary.sources, summary.quarantined) == (6, 18, [])
    assert len(_shard_files(filled)) == 6 and all("/compacted-" in f for f in _shard_files(filled))
    assert catalog.query("SELECT path, unit_key, sha256, num_rows FROM shards ORDER BY path") == shards  # lineage holds
    placed = catalog.query("SELECT table_name, iteration, path, stored_in, row_offset, num_rows FROM shards "
                           "ORDER BY table_name, iteration, path")
    for (table, iteration, *_), group in _grouped(placed):
        offsets = [offset for *_, offset, _ in group]
        assert offsets == [sum(n for *_, n in group[:k]) for k in range(len(group))]
        assert len({stored for *_, stored, _, _ in group}) == 1
    steps_file = catalog.query("SELECT path FROM compacted WHERE table_name = 'steps' AND iteration = 0")[0][0]
    assert pq.ParquetFile(filled.warehouse / steps_file).num_row_groups == 3  # one per source: the reader's unit

    assert _seen(catalog) == before  # queries and snapshots
    assert _batches(catalog) == batches  # the training stream, batch for batch
    assert catalog.verify(full=True) == [] and catalog.clean_orphans() == []
    # a dataset of some units reads only theirs, though their compacted file holds the others' rows too
    assert [(r.path, r.start, r.stop) for r in select_rows(catalog, "TRUE", units=some)] == chosen
    unit = shards[0][1]
    assert catalog.read_unit_shard("steps", unit).num_rows == dict(
        catalog.query("SELECT unit_key, num_rows FROM shards WHERE table_name = 'steps'"))[unit]
    assert plan_compaction(catalog) == [] and compact(catalog).files == 0  # done once

    # a unit quarantined after the compaction leaves its compacted files, which then read without it
    [(episodes,)] = catalog.query("SELECT count(*) FROM episodes")
    path = catalog.query("SELECT path FROM shards WHERE table_name = 'steps' AND unit_key = ?", [unit])[0][0]
    catalog.quarantine(path, "test")
    assert catalog.query("SELECT count(*) FROM shards WHERE unit_key = ?", [unit]) == [(0,)]
    assert catalog.query("SELECT count(*) FROM episodes")[0][0] == episodes - 3
    assert catalog.query("SELECT count(*) FROM steps WHERE episode_id LIKE ?", [f"{unit}%"]) == [(0,)]
    assert len(_shard_files(filled)) == 6  # the compacted files stay: they hold other units' rows
    assert sum(r.stop - r.start for r in select_rows(catalog, "TRUE")) == catalog.query("SELECT count(*) FROM steps")[0][0]


def _grouped(rows):
    import itertools

    return [(key, list(group)) for key, group in itertools.groupby(rows, key=lambda r: r[:2])]


def test_a_corrupt_compacted_file_quarantines_every_unit_it_holds(filled):
    catalog = Catalog(filled.catalog)
    compact(catalog, iterations=[0])
    assert catalog.query("SELECT count(*) FROM shards WHERE stored_in IS NULL") == [(9,)]  # iteration 1 untouched
    [(bad,)] = catalog.query("SELECT path FROM compacted WHERE table_name = 'episodes'")
    (filled.warehouse / bad).write_bytes(b"not parquet")
    found = catalog.verify()
    assert [path for path, _ in found] == [bad]
    # its three units are gone whole (their steps and decisions too), iteration 1 untouched; a resume redoes them
    assert catalog.query("SELECT count(DISTINCT unit_key) FROM quarantine") == [(3,)]
    assert catalog.query("SELECT DISTINCT iteration FROM episodes") == [(1,)]
    assert catalog.query("SELECT count(*) FROM steps WHERE iteration = 0") == [(0,)]
    # their episodes and steps files, left empty, went; the filter units' decisions are units of their own
    assert catalog.query("SELECT table_name FROM compacted WHERE iteration = 0") == [("filter_decisions",)]
    assert not (filled.warehouse / bad).exists() and (filled.warehouse / "quarantine" / bad).exists()


def test_a_kill_between_writing_and_registering_leaves_a_file_the_sweep_removes(filled, monkeypatch):
    catalog = Catalog(filled.catalog)
    before = _seen(catalog)

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(Catalog, "register_compacted", killed)
    with pytest.raises(KeyboardInterrupt):
        compact(catalog)
    monkeypatch.undo()
    assert [p for p in _shard_files(filled) if "compacted-" in p]  # written, not registered
    assert _seen(catalog) == before  # nothing a reader sees
    assert [p.name for p in catalog.clean_orphans()] and not [p for p in _shard_files(filled) if "compacted-" in p]
    assert compact(catalog).files == 6 and _seen(catalog) == before


def test_the_cli_compacts_once_and_says_what_it_did(filled, capsys):
    from flows.cli import main

    assert main(["warehouse", "compact", "--workspace", str(filled.root), "--iteration", "1"]) == 0
    out = capsys.readouterr().out
    assert "[3/3] steps iteration 1: 3 shards, 90 rows" in out and "9 shards" in out and "into 3 files" in out
    assert main(["warehouse", "compact", "--workspace", str(filled.root), "--iteration", "1"]) == 0
    assert "nothing to compact" in capsys.readouterr().out
    assert main(["warehouse", "compact", "--workspace", str(filled.root), "--iteration", "-1"]) == 2
    assert "--iteration must be 0 or more, got -1" in capsys.readouterr().err
    assert main(["warehouse", "compact", "--workspace", str(filled.root), "--iteration", "1", "--iteration", "42"]) == 2
    assert "--iteration 42: the warehouse holds iteration(s) 0, 1" in capsys.readouterr().err  # not 'nothing to compact'
    assert main(["sql", "--workspace", str(filled.root), "--as-of-iteration", "9", "SELECT 1"]) == 2
    assert "--as-of-iteration 9: the warehouse's latest iteration is 1" in capsys.readouterr().err


def _source(catalog: Catalog, table: str, index: int):
    return [p for p in plan_compaction(catalog, [0]) if p.table == table][0].sources[index]


def _flip_bytes(path, count: int = 64) -> None:
    data = bytearray(path.read_bytes())
    for k in range(len(data) // 4, len(data) // 4 + count):
        data[k] ^= 0xFF
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("damage", ["bytes in a frame", "a valid rewrite", "another schema", "undecodable"])
def test_a_source_not_as_registered_is_quarantined_with_its_own_unit_and_the_rest_compacted(filled, damage):
    """A source is checked against its registered sha256 before its rows go into a compacted file: a flipped bit
    in a frame decodes fine, and a compacted file (a new sha256) would keep it for good. Whatever the damage, the
    unit quarantined is the damaged source's (the second of its plan, not the first), and the iteration's other
    units are compacted in the same run (planned again: the unit's other tables' shards went with it)."""
    import pyarrow as pa

    catalog = Catalog(filled.catalog)
    table = "episodes" if damage == "another schema" else "steps"
    victim = _source(catalog, table, 1)
    path = filled.warehouse / victim.path
    if damage == "bytes in a frame":
        _flip_bytes(path)
    elif damage == "a valid rewrite":
        rows = pq.read_table(path)
        pq.write_table(rows.set_column(rows.schema.get_field_index("reward"), "reward",
                                       pa.compute.add(rows["reward"], 1000.0)), path)
    elif damage == "another schema":
        rows = pq.read_table(path)
        at = rows.schema.get_field_index("episode_return")
        pq.write_table(rows.set_column(at, "episode_return", rows["episode_return"].cast(pa.float16())), path)
    else:
        path.write_bytes(b"PAR1" + b"\0" * 64 + b"PAR1")

    summary = compact(catalog, iterations=[0])

    [(path_quarantined, reason)] = summary.quarantined
    assert path_quarantined == victim.path and "expected the registered" in reason  # any change moves the hash
    assert catalog.query("SELECT DISTINCT unit_key FROM quarantine") == [(victim.unit_key,)]
    assert catalog.query("SELECT count(*) FROM shards WHERE unit_key = ?", [victim.unit_key]) == [(0,)]
    # the other two units of iteration 0, every table, compacted in this run; nothing left to do there
    assert summary.files == 3 and plan_compaction(catalog, [0]) == []
    assert catalog.verify(full=True) == []


def test_a_verify_that_a_compaction_overtakes_quarantines_nothing(filled, monkeypatch):
    """`sim2act warehouse verify` lists the files, then checks them one by one: a compaction committed in between
    deletes the sources it listed. A source compacted away is not a bad file of its unit (its rows are in the
    compacted file): once that quarantined every unit of the iteration and the compacted files with them."""
    import warehouse.catalog as catalog_module

    catalog = Catalog(filled.catalog)
    before = _seen(catalog)
    inspect = catalog_module.inspect_shard
    overtaken = []

    def compaction_overtakes(*args, **kwargs):
        if not overtaken:  # verify's first check (the compaction's own registration inspects its file too)
            overtaken.append(None)
            overtaken[0] = compact(catalog, iterations=[0])
        return inspect(*args, **kwargs)

    monkeypatch.setattr(catalog_module, "inspect_shard", compaction_overtakes)
    assert catalog.verify() == []
    assert overtaken[0].files == 3 and catalog.query("SELECT count(*) FROM quarantine") == [(0,)]
    assert _seen(catalog) == before


def test_a_compaction_and_a_reader_of_the_shard_files_refuse_each_other(filled, capsys, tmp_path):
    """`sim2act train`, `export lerobot` and `warehouse verify` read the shard files at length; `warehouse compact`
    deletes the ones it rewrote. Whichever comes second is refused in one line, before any work; readers go
    beside each other."""
    from flows.cli import main
    from flows.run_lock import reading_shard_files, rewriting_shard_files

    catalog = Catalog(filled.catalog)
    before = _shard_files(filled)
    with reading_shard_files(filled, "train"), reading_shard_files(filled, "export lerobot"):
        assert main(["warehouse", "compact", "--workspace", str(filled.root)]) == 2
        [line] = capsys.readouterr().err.strip().splitlines()
        assert "warehouse compact: a training, export or verify is reading the shard files" in line
        assert _shard_files(filled) == before and catalog.query("SELECT count(*) FROM compacted") == [(0,)]
        assert main(["warehouse", "verify", "--workspace", str(filled.root)]) == 0  # readers beside each other
    capsys.readouterr()
    with rewriting_shard_files(filled):
        assert main(["warehouse", "verify", "--workspace", str(filled.root)]) == 2
        assert "warehouse verify: a `sim2act warehouse compact` is rewriting" in capsys.readouterr().err
        assert main(["export", "lerobot", "--workspace", str(filled.root), str(tmp_path / "out")]) == 2
        assert "export lerobot: a `sim2act warehouse compact` is rewriting" in capsys.readouterr().err
        assert not (tmp_path / "out").exists()
    assert main(["warehouse", "compact", "--workspace", str(filled.root)]) == 0  # released


def test_a_full_disk_during_compaction_is_one_line_and_keeps_the_sources(filled, monkeypatch):
    import errno

    from warehouse.shard_writer import DiskFull

    catalog = Catalog(filled.catalog)
    before, files = _seen(catalog), _shard_files(filled)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(type(catalog.store), "put_new", full)
    with pytest.raises(DiskFull, match="no space left on device writing the compacted .* file of iteration 0 .*"
                                       "nothing of it is registered and its sources are kept"):
        compact(catalog)
    monkeypatch.undo()
    assert _shard_files(filled) == files and _seen(catalog) == before
