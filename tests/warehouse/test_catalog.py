import duckdb
import pyarrow as pa
import pytest

from schemas.tables import FILTER_DECISIONS
from schemas.workspace import Workspace
from schemas.version import SCHEMA_VERSION
from warehouse.catalog import Catalog, CatalogMissing, CatalogVersionError
from warehouse.shard_writer import SchemaMismatch, write_shard
from warehouse.sql import ReadOnlyViolation, run_sql


def _decisions(n: int, key: str) -> pa.Table:
    return pa.Table.from_pylist(
        [
            {"campaign": "t", "iteration": 0, "episode_id": f"{key}-e{i}", "task_id": "lift-red", "kept": i % 2 == 0,
             "reason": "kept" if i % 2 == 0 else "low_return", "episode_return": float(i), "filter_key": key}
            for i in range(n)
        ],
        schema=FILTER_DECISIONS,
    )


@pytest.fixture
def workspace(tmp_path) -> Workspace:
    ws = Workspace.at(tmp_path).create()
    Catalog(ws.catalog).initialise()
    return ws


def _register(ws: Workspace, key: str, rows: int) -> bool:
    shard = write_shard("filter_decisions", _decisions(rows, key), ws.shard_path("filter_decisions", 0, key))
    return Catalog(ws.catalog).register_unit(
        unit_key=key, stage="filter", campaign="t", iteration=0, summary={}, shards=[shard]
    )


def test_threads_registering_one_unit_at_once_register_it_once(workspace):
    """No key catches a duplicate (layout 10): the process's write transactions take turns instead."""
    from concurrent.futures import ThreadPoolExecutor

    shard = write_shard("filter_decisions", _decisions(2, "filter-t"), workspace.shard_path("filter_decisions", 0, "filter-t"))
    catalogs = [Catalog(workspace.catalog) for _ in range(4)]  # as separate task runs would hold them
    catalogs[0].query("SELECT 1")  # DuckDB's instance cache: a first connect raced by threads fails to attach
    with ThreadPoolExecutor(4) as pool:
        registered = list(pool.map(lambda c: c.register_unit(unit_key="filter-t", stage="filter", campaign="t",
                                                             iteration=0, summary={}, shards=[shard]), catalogs))
    assert sorted(registered) == [False, False, False, True]
    assert catalogs[0].query("SELECT count(*) FROM stage_runs") == [(1,)]
    assert catalogs[0].query("SELECT count(*) FROM shards") == [(1,)]


def test_a_thread_reading_waits_for_another_threads_registration_and_the_other_way_round(workspace):
    """DuckDB opens a file in one process read-only or read-write at a time: a query beside another thread's
    open transaction (the baselines' evaluation beside a training's registration) waits for it, not fails."""
    import threading
    import time

    catalog = Catalog(workspace.catalog)
    catalog.query("SELECT 1")  # the instance cache, as above
    for holding, other in ((False, lambda: catalog.query("SELECT count(*) FROM stage_runs")),
                           (True, lambda: _register(workspace, "filter-w", 2))):
        held = catalog._open(read_only=holding)  # a transaction or a query in flight, in another thread
        done: list = []
        waiting = threading.Thread(target=lambda: done.append(other()))
        waiting.start()
        time.sleep(0.3)
        assert not done  # waits while the other mode holds the file
        held.close()
        waiting.join(30)
        assert done and done[0] in ([(0,)], True)
    assert catalog.query("SELECT count(*) FROM stage_runs") == [(1,)]


def test_a_reader_counts_by_this_codes_views_in_a_catalog_an_older_sim2act_wrote(workspace):
    """The views' definitions live in the catalog: one last written by older code kept them (counting a
    re-filtered campaign twice) until a writer opened it; the dashboard's panels and `sim2act sql` read them."""
    import duckdb

    from warehouse.sql import run_sql

    _register(workspace, "filter-a", 4)
    with duckdb.connect(str(workspace.catalog)) as con:  # as an older sim2act left it
        con.execute("CREATE OR REPLACE VIEW filter_pass_rates AS SELECT 'old' AS campaign, 0 AS iteration")
    catalog = Catalog(workspace.catalog)
    assert catalog.query("SELECT campaign FROM filter_pass_rates") == [("old",)]  # a plain (writer's) read: as stored
    assert "old" not in run_sql(catalog, "SELECT DISTINCT campaign FROM filter_pass_rates", "csv")
    assert "old" not in run_sql(catalog, "SELECT DISTINCT campaign FROM filter_pass_rates", "csv", as_of_iteration=0)


def test_views_show_registered_shards_only_and_registering_twice_is_a_no_op(workspace):
    catalog = Catalog(workspace.catalog)
    assert catalog.query("SELECT count(*) FROM filter_decisions") == [(0,)]
    assert _register(workspace, "filter-a", 4) is True
    assert _register(workspace, "filter-a", 4) is False
    # a file written but never registered (a run killed in between) stays invisible
    write_shard("filter_decisions", _decisions(3, "filter-b"), workspace.shard_path("filter_decisions", 0, "filter-b"))
    assert catalog.query("SELECT count(*), count(DISTINCT filter_key) FROM filter_decisions") == [(4, 1)]
    assert catalog.query("SELECT count(*) FROM shards") == [(1,)]
    removed = catalog.clean_orphans()
    assert [p.name for p in removed] == ["filter-b.parquet"]
    assert workspace.shard_path("filter_decisions", 0, "filter-a").exists()


def test_shards_are_zstd_parquet_in_hive_folders(workspace):
    _register(workspace, "filter-a", 2)
    path = workspace.shard_path("filter_decisions", 0, "filter-a")
    assert path.parent.name == "iteration=0"
    import pyarrow.parquet as pq

    meta = pq.ParquetFile(path).metadata
    assert meta.row_group(0).column(0).compression == "ZSTD"
    assert pq.read_schema(path).metadata[b"sim2act.schema_version"] == str(SCHEMA_VERSION).encode()


def test_a_warehouse_of_another_layout_version_is_refused_untouched(workspace):
    catalog = Catalog(workspace.catalog)
    with duckdb.connect(str(workspace.catalog)) as con:
        con.execute("UPDATE catalog_meta SET value = '1' WHERE key = 'schema_version'")
    before = workspace.catalog.read_bytes()
    for check in (catalog.check_version, catalog.initialise):
        with pytest.raises(CatalogVersionError, match=r"has layout version 1, this sim2act writes \d+: use a new"):
            check()
    assert workspace.catalog.read_bytes() == before


def test_a_wrong_schema_is_refused_and_nothing_is_written(workspace):
    rows = _decisions(2, "filter-x").drop_columns(["reason"])
    path = workspace.shard_path("filter_decisions", 0, "filter-x")
    with pytest.raises(SchemaMismatch, match="reason"):
        write_shard("filter_decisions", rows, path)
    assert not path.parent.exists() or not any(path.parent.iterdir())


@pytest.mark.parametrize(
    "statement",
    ["DELETE FROM tasks", "DROP VIEW steps", "COPY (SELECT 1) TO '/tmp/sim2act-x.csv'", "CREATE TABLE x (a INT)"],
)
def test_sql_is_read_only(workspace, statement):
    with pytest.raises(ReadOnlyViolation, match="read-only"):
        run_sql(Catalog(workspace.catalog), statement)


def test_sql_runs_one_statement_and_names_a_refused_one_by_its_keyword(workspace):
    """DuckDB answers only the last of several statements (the others' results vanished, exit 0), and an
    INSTALL was refused as a LOAD statement."""
    catalog = Catalog(workspace.catalog)
    with pytest.raises(ReadOnlyViolation, match="expected one SQL statement, got 2: run each on its own"):
        run_sql(catalog, "SELECT 1; SELECT 2")
    with pytest.raises(ReadOnlyViolation, match="INSTALL statements are refused"):
        run_sql(catalog, "INSTALL httpfs")


def test_sql_reads_the_warehouses_files_and_nothing_outside_it(workspace, tmp_path_factory):
    """A query is someone's text: it may read the warehouse's shards, by view or by path, but not a
    file elsewhere on the machine, not through `..`, not by attaching a database, at any snapshot."""
    _register(workspace, "filter-a", 4)
    catalog = Catalog(workspace.catalog)
    outside = tmp_path_factory.mktemp("outside") / "secret.csv"
    outside.write_text("token\nhunter2\n")
    assert duckdb.sql(f"SELECT * FROM read_csv('{outside}')").fetchall() == [("hunter2",)]  # readable by a plain client
    shard = workspace.shard_path("filter_decisions", 0, "filter-a")
    assert run_sql(catalog, f"SELECT count(*) AS n FROM read_parquet('{shard}')", "csv") == "n\n4"
    for as_of in (None, 0):
        assert run_sql(catalog, "SELECT count(*) AS n FROM filter_decisions", "csv", as_of_iteration=as_of) == "n\n4"
        for sql in (f"SELECT * FROM read_csv('{outside}')", "SELECT * FROM read_csv('/etc/passwd')",
                    f"SELECT * FROM read_csv('{workspace.catalog.parent}/../{outside.parent.name}/secret.csv')",
                    "SELECT * FROM glob('/*')"):
            with pytest.raises(duckdb.Error, match="file system operations are disabled"):
                run_sql(catalog, sql, as_of_iteration=as_of)
    with catalog.connect(read_only=True, confined=True) as con:
        with pytest.raises(duckdb.Error, match="configuration has been locked"):
            con.execute("SET enable_external_access = true")
        with pytest.raises(duckdb.Error, match="file system operations are disabled"):
            con.execute(f"ATTACH '{outside.parent / 'other.duckdb'}'")
    with pytest.raises(ValueError, match="read-only"):
        with catalog.connect(confined=True):
            pass
    # concurrent connections of one process share DuckDB's instance and its locked settings (the dashboard
    # answers requests concurrently): the second one is confined too, and answers
    with catalog.connect(read_only=True, confined=True) as first, catalog.connect(read_only=True, confined=True) as second:
        assert first.execute("SELECT count(*) FROM filter_decisions").fetchall() == [(4,)]
        assert second.execute("SELECT count(*) FROM filter_decisions").fetchall() == [(4,)]
        with pytest.raises(duckdb.Error, match="file system operations are disabled"):
            second.execute("SELECT * FROM read_csv('/etc/passwd')")
        # a plain read that joins the confined instance (the dashboard's episode frames beside a panel's
        # query) reads the views by location: relative names are refused there (a CI failure)
        assert catalog.query("SELECT count(*) FROM filter_decisions") == [(4,)]
        assert catalog.query("SELECT count(*) FROM filter_decisions", as_of_iteration=0) == [(4,)]
    from concurrent.futures import ThreadPoolExecutor

    from dashboards.reads import read_rows
    with ThreadPoolExecutor(8) as pool:  # the dashboard's concurrent requests (two once both set the lock: refused)
        counts = list(pool.map(lambda _: read_rows(catalog, "SELECT count(*) AS n FROM filter_decisions").rows,
                               range(200)))
    assert counts == [[{"n": 4}]] * 200
    with pytest.raises(duckdb.Error, match="file system operations are disabled"):
        read_rows(catalog, "SELECT * FROM read_csv('/etc/passwd')")


def test_sql_formats(workspace):
    _register(workspace, "filter-a", 4)
    catalog = Catalog(workspace.catalog)
    table = run_sql(catalog, "SELECT reason, count(*) AS n FROM filter_decisions GROUP BY 1 ORDER BY 1")
    assert "kept" in table and "(2 rows)" in table
    assert run_sql(catalog, "SELECT count(*) AS n FROM filter_decisions", "csv") == "n\n4"
    assert '"n": 4' in run_sql(catalog, "SELECT count(*) AS n FROM filter_decisions", "json")


def test_catalog_opens_in_a_plain_duckdb_client(workspace, monkeypatch):
    """The views name shards relative to the warehouse folder: a client opened there reads them, or
    one told where they are (docs/warehouse.md)."""
    _register(workspace, "filter-a", 4)
    with duckdb.connect(str(workspace.catalog), read_only=True) as con:
        con.execute("SET file_search_path = ?", [str(workspace.warehouse)])
        assert con.execute("SELECT count(*) FROM filter_decisions WHERE kept").fetchone() == (2,)
    monkeypatch.chdir(workspace.warehouse)
    with duckdb.connect("catalog.duckdb", read_only=True) as con:
        assert con.execute("SELECT count(*) FROM filter_decisions WHERE kept").fetchone() == (2,)


def test_missing_catalog_is_a_clear_error(tmp_path):
    with pytest.raises(CatalogMissing, match="sim2act run"):
        Catalog(tmp_path / "nope.duckdb").query("SELECT 1")


def test_a_moved_warehouse_reads_its_own_files(workspace, tmp_path_factory, monkeypatch):
    """A copied or moved workspace reads its own files, in sim2act and in a plain DuckDB client."""
    import shutil

    _register(workspace, "filter-a", 4)
    moved = Workspace.at(tmp_path_factory.mktemp("elsewhere") / "workspace")
    shutil.move(workspace.root, moved.root)  # nothing is left at the old path
    with duckdb.connect(str(moved.catalog), read_only=True) as con:  # before sim2act opened it there
        con.execute("SET file_search_path = ?", [str(moved.warehouse)])
        assert con.execute("SELECT count(*) FROM filter_decisions").fetchall() == [(4,)]
    catalog = Catalog(moved.catalog)
    assert catalog.query("SELECT count(*) FROM filter_decisions") == [(4,)]  # read-only: this connection's views
    assert catalog.query("SELECT count(*) FROM filter_decisions", as_of_iteration=0) == [(4,)]
    assert _register(moved, "filter-b", 2)  # a writer re-points the views for good
    assert catalog.query("SELECT value FROM catalog_meta WHERE key = 'root'") == [(moved.warehouse.resolve().as_posix(),)]
    monkeypatch.chdir(moved.warehouse)
    with duckdb.connect("catalog.duckdb", read_only=True) as con:  # a plain client sees the new one too
        assert con.execute("SELECT count(*) FROM filter_decisions").fetchall() == [(6,)]


def test_a_layout_6_catalog_is_brought_to_this_layout_in_place_keeping_its_rows(workspace, tmp_path):
    """Layout 7 added evaluations.episode_achieved, 8 shards.view_part, 9 shards.stored_in/row_offset and
    the compacted table, 10 dropped the keys of stage_runs and shards: a layout-6 catalog gains them all
    where any command opens it (no new workspace), its rows kept, the new columns null until used."""
    from schemas.version import MIGRATIONS

    assert SCHEMA_VERSION == 10 and MIGRATIONS[6] == [("evaluations", "episode_achieved")]
    _register_filter(workspace, "explore-before", 3)
    with duckdb.connect(str(workspace.catalog)) as con:  # what a layout-6 sim2act left
        con.execute("ALTER TABLE evaluations DROP COLUMN episode_achieved")
        con.execute("ALTER TABLE shards DROP COLUMN row_offset")
        con.execute("ALTER TABLE shards DROP COLUMN stored_in")
        con.execute("ALTER TABLE shards DROP COLUMN view_part")
        con.execute("DROP TABLE compacted")
        con.execute("UPDATE catalog_meta SET value = '6' WHERE key = 'schema_version'")
        con.execute("INSERT INTO evaluations (unit_key, task_id, successes) VALUES ('evaluate-old', 'lift-red', 3)")
    import shutil

    moved = Workspace.at(tmp_path / "copied")  # a copy elsewhere: its views are followed before it is migrated
    shutil.copytree(workspace.root, moved.root)
    workspace = moved
    catalog = Catalog(workspace.catalog)
    catalog.check_version()
    catalog.check_layout()  # every declared column, in order
    assert catalog.query("SELECT value FROM catalog_meta WHERE key = 'schema_version'") == [("10",)]
    assert catalog.query("SELECT count(*) FROM compacted") == [(0,)]
    assert catalog.query("SELECT table_name FROM duckdb_constraints() WHERE constraint_type = 'PRIMARY KEY' "
                         "AND table_name IN ('stage_runs', 'shards', 'evaluations') ORDER BY 1") == [("evaluations",)]
    assert catalog.query("SELECT unit_key FROM stage_runs") == [("explore-before",)]
    assert catalog.query("SELECT unit_key, successes, episode_achieved FROM evaluations") == [("evaluate-old", 3, None)]
    assert catalog.query("SELECT count(*), count(view_part) FROM shards") == [(1, 0)]
    assert catalog.query("SELECT count(*) FROM filter_decisions") == [(3,)]  # the old view still reads
    catalog.initialise()  # the next writer gives the old shards their part
    assert catalog.query("SELECT count(*), count(view_part) FROM shards") == [(1, 1)]
    assert catalog.query("SELECT count(*) FROM filter_decisions") == [(3,)]


def _register_filter(workspace, key: str, rows: int) -> None:
    path = workspace.shard_path("filter_decisions", 0, key)
    Catalog(workspace.catalog).register_unit(unit_key=key, stage="filter", campaign="t", iteration=0, summary={},
                                             shards=[write_shard("filter_decisions", _decisions(rows, key), path)])


def test_views_come_in_parts_and_a_registration_rewrites_only_the_last(workspace, monkeypatch):
    """Parts of at most VIEW_PART_SHARDS shards, filled in registration order: registering rewrites
    the part its shard joined (and the table's view when a part is added); every row stays visible,
    and a quarantine rewrites the part that lost its shard."""
    import warehouse.catalog as catalog_module

    monkeypatch.setattr(catalog_module, "VIEW_PART_SHARDS", 2)
    catalog = Catalog(workspace.catalog)
    for n in range(5):
        _register_filter(workspace, f"filter-{n}", n + 1)
    parts = catalog.query("SELECT path, view_part FROM shards ORDER BY view_part, path")
    assert [part for _, part in parts] == [0, 0, 1, 1, 2]
    assert catalog.query("SELECT count(*) FROM filter_decisions") == [(15,)]
    views = dict(catalog.query("SELECT view_name, sql FROM duckdb_views() WHERE view_name LIKE '_filter_decisions_part_%'"))
    assert sorted(views) == ["_filter_decisions_part_00000", "_filter_decisions_part_00001",
                             "_filter_decisions_part_00002"]
    assert all(views[f"_filter_decisions_part_{p:05d}"].count(".parquet") == n for p, n in ((0, 2), (1, 2), (2, 1)))
    catalog.quarantine(parts[0][0], "test")  # filter-0 (one row) leaves part 0
    assert catalog.query("SELECT count(*) FROM filter_decisions") == [(14,)]
    _register_filter(workspace, "filter-5", 6)  # part 2 had room for one more
    assert catalog.query("SELECT view_part FROM shards WHERE unit_key = 'filter-5'") == [(2,)]
    assert catalog.query("SELECT count(*) FROM filter_decisions") == [(20,)]
    with duckdb.connect(str(workspace.catalog), read_only=True) as con:  # a plain client reads them too
        con.execute("SET file_search_path = ?", [str(workspace.warehouse.resolve())])
        assert con.execute("SELECT count(*) FROM filter_decisions").fetchone() == (20,)


def test_a_first_initialise_killed_midway_leaves_nothing_half_recorded(tmp_path, monkeypatch):
    """A first `initialise` is one transaction: killed after catalog_meta was made but before its shard_store
    record, the record's absence read as 'the folder' and an S3 workspace was refused by every later command."""
    from warehouse.catalog import Catalog

    catalog = Catalog(tmp_path / "warehouse" / "catalog.duckdb")

    def killed(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(Catalog, "_refresh_views", killed)
    with pytest.raises(KeyboardInterrupt):
        catalog.initialise()
    monkeypatch.undo()
    assert Catalog(catalog.path)._meta() is None  # as if never begun
    catalog = Catalog(catalog.path)
    catalog.initialise()
    assert Catalog(catalog.path)._meta()["shard_store"] == catalog.store.url
