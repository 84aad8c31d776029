"""The DuckDB catalog: the single point of truth for what the warehouse holds.

One registrar commits at a time (DuckDB lets one process write; others wait for the lock);
readers open it read-only. A unit of work is done exactly when its key is in `stage_runs`;
its shards are visible exactly when they are in `shards`. Files the catalog does not know
are ignored and cleaned up; registered files found corrupt are moved to quarantine.
"""

from __future__ import annotations

import itertools
import json
import logging
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import duckdb
import pyarrow as pa

from schemas.errors import Sim2ActError
from schemas.retry import retrying
from schemas.tables import CATALOG_TABLES, ITERATION_TABLES, SHARD_TABLES, VIEWS, catalog_ddl, sql_type
from schemas.version import MIGRATIONS, REBUILT, SCHEMA_VERSION
from warehouse.shard_writer import SchemaMismatch, ShardFile, ShardUnreadable, inspect_shard, read_shard, read_shard_rows
from warehouse.store import FOLDER, ShardStore, open_store

log = logging.getLogger("sim2act.warehouse.catalog")

LOCK_WAIT_S = 120.0
VIEW_PART_SHARDS = 500  # shard files per part view: what a registration's view rewrite names at most
COMPACTED_PART = -1  # shards.view_part of a compacted shard: its table's `_<table>_compacted` view reads it
_CONFINING = threading.Lock()  # Catalog._confine: DuckDB's settings belong to the instance threads share
_RECORDED_STORES: dict[tuple[Path, int], str] = {}  # catalog file -> its recorded store: fixed once it exists
# catalog files this process has opened confined: DuckDB shares one instance per file, so a plain reader of
# one may find the instance confined, or see it confined under it mid-query (Catalog.connect)
_CONFINED_FILES: set[str] = set()
# one write transaction at a time in this process (other processes wait on DuckDB's file lock): two
# threads' transactions that both rewrite a view conflict ("Catalog write-write conflict"), and
# register_unit's "is this unit registered?" and its inserts must be one step, with no key left to catch a
# second thread registering the same unit meanwhile (layout 10 dropped the keys)
_WRITING = threading.RLock()


class CatalogMissing(Sim2ActError, FileNotFoundError):
    pass


class CatalogUnreadable(Sim2ActError, OSError):
    """The catalog file is there but DuckDB cannot open it (not a DuckDB file, another DuckDB's format)."""


class CatalogVersionError(Sim2ActError, RuntimeError):
    """The warehouse was written by another layout version; nothing is touched."""


def _is_lock_error(exc: BaseException) -> bool:
    """Another process's write lock on the file, or, in this one, a thread's connection in the other mode: DuckDB
    opens a file in one process read-only or read-write at a time (its instance cache refuses the other with "a
    different configuration"); both are held for one query or transaction, so a wait gets through."""
    if isinstance(exc, duckdb.ConnectionException):
        return "different configuration" in str(exc)
    return isinstance(exc, duckdb.IOException) and "lock" in str(exc).lower()


def check_rows(table: str, rows: Sequence[Mapping[str, Any]]) -> pa.Table:
    """Catalog rows as an Arrow table of the declared schema: a missing, extra or mistyped
    column is refused, naming it."""
    schema = CATALOG_TABLES[table].schema
    for row in rows:
        for name in schema.names:
            if name not in row:
                raise SchemaMismatch(f"{table}: column {name!r} is missing from a row")
        for name in row:
            if name not in schema.names:
                raise SchemaMismatch(f"{table}: column {name!r} is not in the schema (schemas/tables.py)")
    try:
        return pa.Table.from_pylist(list(rows), schema=schema)
    except (pa.ArrowException, TypeError, ValueError) as exc:
        raise SchemaMismatch(f"{table}: a value does not fit the schema: {exc}") from None


def _insert(con: duckdb.DuckDBPyConnection, table: str, rows: pa.Table) -> None:
    con.register("new_rows", rows)
    con.execute(f"INSERT INTO {table} SELECT * FROM new_rows")
    con.unregister("new_rows")


class Catalog:
    def __init__(self, path: Path):
        self.path = path
        self.warehouse = path.parent
        self._in_place = False  # the shard views were seen pointing at this folder: no need to look again
        self._store: ShardStore | None = None

    @property
    def store(self) -> ShardStore:
        """Where this warehouse's shards live (warehouse/store.py): the store its catalog recorded when
        it was created; a new catalog takes SIM2ACT_SHARD_STORE's, else the folder."""
        if self._store is None:
            self._store = open_store(self.warehouse, self._recorded_store())
        return self._store

    def _recorded_store(self) -> str | None:
        """The catalog's record (a catalog older than the record keeps its shards in the folder); None
        before the catalog exists. Read on a connection of its own, before connect() opens another."""
        if not self.path.exists():
            return None
        key = (self.path.resolve(), self.path.stat().st_ino)  # a catalog made anew at the same path is another
        if key in _RECORDED_STORES:
            return _RECORDED_STORES[key]
        meta = self._meta()
        if meta is None:
            return None  # created, not initialised yet
        _RECORDED_STORES[key] = meta.get("shard_store", FOLDER)
        return _RECORDED_STORES[key]

    def _meta(self) -> dict[str, str] | None:
        """catalog_meta, on a connection of its own (None: no catalog, or not initialised yet)."""
        if not self.path.exists():
            return None
        con = self._open(read_only=True)
        try:
            if not con.execute("SELECT 1 FROM duckdb_tables() WHERE table_name = 'catalog_meta'").fetchone():
                return None
            return dict(con.execute("SELECT key, value FROM catalog_meta").fetchall())
        finally:
            con.close()

    def _open(self, read_only: bool) -> duckdb.DuckDBPyConnection:
        """The catalog file, opened; another process holding DuckDB's write lock is waited for a while.

        Raises:
            CatalogUnreadable: the file is not one DuckDB opens (one line, not DuckDB's traceback)."""
        try:
            return retrying(_is_lock_error, within_s=LOCK_WAIT_S, wait_s=0.05)(
                duckdb.connect, str(self.path), read_only=read_only)
        except duckdb.IOException as exc:
            if _is_lock_error(exc):
                raise
            raise CatalogUnreadable(f"the warehouse catalog {self.path} cannot be opened: {str(exc).splitlines()[0]}; "
                                    "restore it from a copy (the shards beside it are untouched)") from None

    @property
    def quarantine_folder(self) -> Path:
        return self.warehouse / "quarantine"

    @property
    def quarantine_location(self) -> str:
        """Where quarantined shards go: the folder, or the store's quarantine/ prefix."""
        return self.store.location("quarantine")

    @contextmanager
    def connect(self, read_only: bool = False, as_of_iteration: int | None = None,
                confined: bool = False, follow_move: bool = True) -> Iterator[duckdb.DuckDBPyConnection]:
        """Open briefly and close: DuckDB lets one process write, so nobody holds it for long.

        With `as_of_iteration=K` the connection sees the warehouse as it was after iteration K:
        temporary views shadow every table and shard view, cut at iteration <= K.
        `confined` (read-only connections that run someone's SQL: `sim2act sql`, the dashboard): the
        connection reads files in the warehouse folder and nowhere else, no ATTACH, no extension, and
        its configuration is locked, so a query cannot read `/etc/passwd` or undo the confinement.
        `follow_move=False`: the layout migration's connection, which must not rewrite a moved
        warehouse's views before the columns they read exist.
        """
        if confined and not read_only:
            raise ValueError("a confined connection is a read-only one")
        if read_only and not self.path.exists():
            raise CatalogMissing(f"no warehouse catalog at {self.path} (run `sim2act run` first)")
        store = self.store  # before the connection: it may read the catalog's record on one of its own
        key = str(self.path.resolve())
        if confined:
            _CONFINED_FILES.add(key)  # before it locks anything
        # another process holds DuckDB's write lock for a moment: wait for it, a while at most
        con = self._open(read_only)
        try:
            # a read beside a confined one (the dashboard answers requests concurrently; settings are per
            # instance) cannot count on reading the views' relative names: the instance is confined, or may
            # be confined under it mid-query. It reads as a confined one does, by location.
            self._search_warehouse(con)
            joined_confined = read_only and key in _CONFINED_FILES  # only this process's confined ones lock it
            store.prepare(con)  # S3: httpfs and the store's key, before any view is read
            if as_of_iteration is not None:
                self._snapshot_views(con, as_of_iteration)
            elif confined or joined_confined or (follow_move and not self._in_place and self._moved(con)):
                self._follow_move(con, read_only)
            if confined:
                self._confine(con)
            yield con
        finally:
            con.close()

    # -- writer side -----------------------------------------------------------------------

    def initialise(self) -> None:
        self.check_version()  # an older layout is brought to this one here
        # an S3 prefix another catalog keeps its shards under is refused before anything is written here
        warehouse_id = self.store.claim((self._meta() or {}).get("warehouse_id"), self.path.resolve())
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # one transaction: a first initialise killed midway leaves no catalog_meta without its shard_store
        # record (which `_recorded_store` would read as the folder: an S3 workspace, refused for good)
        with self._transaction() as con:
            for name in CATALOG_TABLES:
                con.execute(catalog_ddl(name))
            con.execute(
                "INSERT INTO catalog_meta VALUES ('schema_version', ?) ON CONFLICT DO NOTHING", [str(SCHEMA_VERSION)]
            )
            con.execute("INSERT INTO catalog_meta VALUES ('shard_store', ?) ON CONFLICT DO NOTHING", [self.store.url])
            con.execute("INSERT INTO catalog_meta VALUES ('warehouse_id', ?) ON CONFLICT DO NOTHING", [warehouse_id])
            for name, schema in SHARD_TABLES.items():
                con.register("empty_shard", pa.Table.from_batches([], schema=schema))
                con.execute(f"CREATE TABLE IF NOT EXISTS _empty_{name} AS SELECT * FROM empty_shard")
                con.unregister("empty_shard")
            self._refresh_views(con, SHARD_TABLES, everything=True)
            for name, query in VIEWS.items():
                con.execute(f"CREATE OR REPLACE VIEW {name} AS {query}")
        self.check_layout()

    def _stamped_version(self) -> int | None:
        """The layout version the catalog was written with; None where there is no catalog yet."""
        if not self.path.exists():
            return None
        with self.connect(read_only=True) as con:
            if not con.execute("SELECT 1 FROM duckdb_tables() WHERE table_name = 'catalog_meta'").fetchone():
                return None  # a first initialise that did not finish
            stamped = con.execute("SELECT value FROM catalog_meta WHERE key = 'schema_version'").fetchone()
        return None if stamped is None else int(stamped[0])

    def check_version(self) -> None:
        """Refuse a warehouse of another layout version, before any work (no-op if none exists); an
        older layout that MIGRATIONS brings to this one in place is brought (`_migrate`)."""
        stamped = self._stamped_version()
        if stamped is None or stamped == SCHEMA_VERSION:
            return
        if stamped < SCHEMA_VERSION and all(version in MIGRATIONS for version in range(stamped, SCHEMA_VERSION)):
            self._migrate(stamped)
            return
        raise CatalogVersionError(
            f"the warehouse at {self.warehouse} has layout version {stamped}, this sim2act writes "
            f"{SCHEMA_VERSION}: use a new --workspace (the old one stays readable with `sim2act sql`)"
        )

    def _migrate(self, stamped: int) -> None:
        """Bring a catalog of layout `stamped` to this one in place, one version at a time, each
        version's columns, rebuilt tables and new stamp in one transaction (a kill leaves the old layout
        or the new one)."""
        with self.connect(follow_move=False) as con:
            for version in range(stamped, SCHEMA_VERSION):
                con.execute("BEGIN TRANSACTION")
                for table, column in MIGRATIONS[version]:
                    field = CATALOG_TABLES[table].schema.field(column)
                    con.execute(f"ALTER TABLE {table} ADD COLUMN IF NOT EXISTS {column} {sql_type(field)}")
                for name in REBUILT.get(version, ()):  # its key changed (10: none on stage_runs, shards)
                    con.execute(f"ALTER TABLE {name} RENAME TO _{name}_layout_{version}")
                    con.execute(catalog_ddl(name))
                    con.execute(f"INSERT INTO {name} SELECT * FROM _{name}_layout_{version}")
                    con.execute(f"DROP TABLE _{name}_layout_{version}")
                for name in CATALOG_TABLES:  # a table the layout adds (9: compacted), whole
                    con.execute(catalog_ddl(name))
                con.execute("UPDATE catalog_meta SET value = ? WHERE key = 'schema_version'", [str(version + 1)])
                con.execute("COMMIT")
            for name, query in VIEWS.items():  # the ready-made views of this layout (initialise makes them too)
                con.execute(f"CREATE OR REPLACE VIEW {name} AS {query}")
        log.info("catalog %s: layout %d brought to %d in place", self.path, stamped, SCHEMA_VERSION)

    def check_layout(self) -> None:
        """Every catalog table has exactly the declared columns and types."""
        with self.connect(read_only=True) as con:
            for name, table in CATALOG_TABLES.items():
                found = con.execute(
                    "SELECT column_name, data_type FROM duckdb_columns() WHERE table_name = ? AND schema_name = 'main' "
                    "ORDER BY column_index", [name]
                ).fetchall()
                want = [(f.name, sql_type(f)) for f in table.schema]
                for declared, present in itertools.zip_longest(want, found):
                    if declared != present:
                        raise CatalogVersionError(
                            f"catalog table {name}: column {present} where schemas/tables.py declares {declared}"
                        )

    def is_registered(self, unit_key: str) -> bool:
        return bool(self.registered_keys([unit_key]))

    def registered_keys(self, keys: Sequence[str]) -> set[str]:
        if not keys or not self.path.exists():
            return set()
        with self.connect(read_only=True) as con:
            rows = con.execute("SELECT unit_key FROM stage_runs WHERE list_contains(?, unit_key)", [list(keys)])
            return {row[0] for row in rows.fetchall()}

    def register_unit(
        self,
        *,
        unit_key: str,
        stage: str,
        campaign: str,
        iteration: int,
        summary: Mapping[str, Any],
        wall_s: float = 0.0,
        shards: Sequence[ShardFile] = (),
        rows: Mapping[str, Sequence[Mapping[str, Any]]] | None = None,
    ) -> bool:
        """Commit one finished unit: its stage_runs row, its shards and its catalog rows, atomically.

        Every shard is checked first (a whole Parquet file of its declared schema, the rows
        and bytes its writer reported) and every row against its table's schema: a bad shard
        or row is refused before anything is committed. Registering a key twice is a no-op
        and returns False.
        """
        for shard in shards:  # in the store: an object on S3 is read back as the registrar sees it
            if (inspect_shard(shard.table, shard.path, self.store) != shard.num_rows
                    or self.store.sha256(self.store.rel(shard.path)) != shard.sha256):
                raise ShardUnreadable(f"{self.store.location(self.store.rel(shard.path))}: differs from what its "
                                      "writer reported; not registered")
        tables = {table: check_rows(table, table_rows) for table, table_rows in (rows or {}).items()}
        now = datetime.now(timezone.utc).replace(tzinfo=None)
        tables["stage_runs"] = check_rows("stage_runs", [{
            "unit_key": unit_key, "stage": stage, "campaign": campaign, "iteration": iteration,
            "finished_at": now, "wall_s": wall_s, "summary": json.dumps(summary),
        }])
        tables["shards"] = check_rows("shards", [{
            "path": shard.path.relative_to(self.warehouse).as_posix(), "table_name": shard.table,
            "unit_key": unit_key, "campaign": campaign, "iteration": iteration, "num_rows": shard.num_rows,
            "num_bytes": shard.num_bytes, "sha256": shard.sha256, "schema_version": SCHEMA_VERSION,
            "view_part": None,  # given by _refresh_views, in the same transaction
            "stored_in": None, "row_offset": None,  # its own file until a compaction
        } for shard in shards])
        with self._transaction() as con:
            if con.execute("SELECT 1 FROM stage_runs WHERE unit_key = ?", [unit_key]).fetchone():
                return False  # nothing written: the empty transaction commits
            for table, arrow in tables.items():
                _insert(con, table, arrow)
            self._refresh_views(con, {shard.table for shard in shards})
        return True

    def register_compacted(self, *, path: str, table: str, campaign: str, iteration: int, num_rows: int,
                           num_bytes: int, sha256: str, offsets: Sequence[tuple[str, int]]) -> None:
        """Commit a compacted file (warehouse/compaction.py): its `compacted` row, and each source
        shard (path, its first row in the file) re-pointed at it, with the table's views, atomically.
        The sources' files are the caller's to delete after.

        Raises:
            ShardUnreadable: the file is not the rows and bytes the compaction reported.
            ValueError: a source is not a registered shard of `table` that is still its own file."""
        if (inspect_shard(table, self.warehouse / path, self.store) != num_rows
                or self.store.sha256(path) != sha256):
            raise ShardUnreadable(f"{self.store.location(path)}: differs from what the compaction wrote; not registered")
        now = datetime.now(timezone.utc).replace(tzinfo=None)
        with self._transaction() as con:
            sources = [p for p, _ in offsets]
            [(found,)] = con.execute("SELECT count(*) FROM shards WHERE list_contains(?, path) AND table_name = ? "
                                     "AND stored_in IS NULL", [sources, table]).fetchall()
            if found != len(sources):
                raise ValueError(f"expected {len(sources)} registered {table} shards still their own files, got {found}")
            _insert(con, "compacted", check_rows("compacted", [{
                "path": path, "table_name": table, "campaign": campaign, "iteration": iteration, "num_rows": num_rows,
                "num_bytes": num_bytes, "sha256": sha256, "sources": len(sources), "compacted_at": now}]))
            con.register("compacted_offsets", pa.table({"path": sources, "row_offset": [o for _, o in offsets]}))
            con.execute("UPDATE shards SET stored_in = ?, row_offset = o.row_offset, view_part = ? FROM compacted_offsets o "
                        "WHERE shards.path = o.path", [path, COMPACTED_PART])
            con.unregister("compacted_offsets")
            self._refresh_views(con, {table}, everything=True)

    @contextmanager
    def _transaction(self) -> Iterator[duckdb.DuckDBPyConnection]:
        """A write connection in one transaction: committed whole, or rolled back on any error; one
        at a time in this process."""
        with _WRITING, self.connect() as con:
            con.execute("BEGIN TRANSACTION")
            try:
                yield con
            except BaseException:
                con.execute("ROLLBACK")
                raise
            con.execute("COMMIT")

    @staticmethod
    def _persistent(con: duckdb.DuckDBPyConnection) -> str:
        """Qualifier of the catalog file's own objects: temporary views shadow bare names, and a
        bare `main.` resolves to the temporary catalog's schema too."""
        return f'"{con.execute("SELECT current_database()").fetchone()[0]}".main'

    def _shard_source(self, con: duckdb.DuckDBPyConnection, table: str, as_of_iteration: int | None,
                      temporary: bool) -> str:
        """What a view of `table` reads: its registered shards (of iterations <= `as_of_iteration`)."""
        return self._source(con, table, "? IS NULL OR s.iteration <= ?", [as_of_iteration, as_of_iteration], temporary)

    def _source(self, con: duckdb.DuckDBPyConnection, table: str, where: str, params: Sequence[Any],
                temporary: bool) -> str:
        """A FROM item over the registered shards of `table` that `where` (SQL over `shards s`) picks:
        the files of those still their own, and the compacted files that hold the others, read whole,
        or cut to the rows still registered where a quarantine after the compaction took a unit out.

        The catalog file's views name a folder's files relative to it (they hold when the workspace
        moves); a connection's temporary views name them by location, which confinement
        (allowed_directories: absolute folders) can check."""
        persistent = self._persistent(con)
        locate = self.store.location if temporary else self.store.view_location
        # a catalog of a layout before 9 (read as it is: `sim2act sql`, or before its migration) has no compaction
        compacted = con.execute("SELECT count(*) > 0 FROM duckdb_tables() WHERE table_name = 'compacted' "
                                "AND NOT temporary").fetchone()[0]
        held = ("coalesce(s.stored_in, s.path), s.row_offset, s.num_rows, c.num_rows FROM {p}.shards s "
                "LEFT JOIN {p}.compacted c ON c.path = s.stored_in" if compacted else
                "s.path, NULL, s.num_rows, NULL FROM {p}.shards s").format(p=persistent)
        rows = con.execute(f"SELECT {held} WHERE s.table_name = ? AND ({where}) ORDER BY 1, 2",
                           [table, *params]).fetchall()
        whole, cut = [], []
        for file, group in itertools.groupby(rows, key=lambda row: row[0]):
            group = list(group)
            held, total = sum(row[2] for row in group), group[0][3]
            if total is None or held == total:  # its own file, or a compacted one all of whose rows count
                whole.append(locate(file))
            else:
                cut.append((locate(file), [(offset, offset + n) for _, offset, n, _ in group]))
        sources = [f"SELECT * FROM read_parquet({whole!r})"] if whole else []
        for file, ranges in cut:
            keep = " OR ".join(f"file_row_number BETWEEN {a} AND {b - 1}" for a, b in ranges)
            sources.append(f"SELECT * EXCLUDE (file_row_number) FROM read_parquet({file!r}, file_row_number = true) "
                           f"WHERE {keep}")
        if not sources:
            return f"{persistent}._empty_{table}" if temporary else f"_empty_{table}"
        if not cut:
            return f"read_parquet({whole!r})"
        return "(" + " UNION ALL ".join(sources) + ")"

    def _moved(self, con: duckdb.DuckDBPyConnection) -> bool:
        """Whether the views may name files under another folder than this warehouse: it was copied
        or moved, and they were made before views named shards relative to it (or live on S3)."""
        if not con.execute("SELECT 1 FROM duckdb_tables() WHERE table_name = 'catalog_meta'").fetchone():
            return False  # not initialised yet
        root = con.execute(f"SELECT value FROM {self._persistent(con)}.catalog_meta WHERE key = 'root'").fetchone()
        self._in_place = root is not None and root[0] == self.warehouse.resolve().as_posix()
        return not self._in_place

    def _follow_move(self, con: duckdb.DuckDBPyConnection, read_only: bool) -> None:
        """Point the shard views at this folder's files: for good when writing, for this
        connection (temporary views) when reading (a confined connection's always)."""
        if read_only:
            for name in SHARD_TABLES:
                con.execute(f"CREATE TEMP VIEW {name} AS SELECT * FROM {self._shard_source(con, name, None, True)}")
            self._current_views(con)
            return
        self._refresh_views(con, SHARD_TABLES, everything=True)
        con.execute("INSERT OR REPLACE INTO catalog_meta VALUES ('root', ?)", [self.warehouse.resolve().as_posix()])
        self._in_place = True

    def _search_warehouse(self, con: duckdb.DuckDBPyConnection) -> None:
        """Relative file names (the views' shards) resolve in the warehouse folder. Set on the DuckDB
        instance (GLOBAL), which a confined connection then locks: later connections find it set."""
        folder = self.warehouse.resolve().as_posix()
        with _CONFINING:
            [(locked, searched)] = con.execute(
                "SELECT current_setting('lock_configuration'), current_setting('file_search_path')").fetchall()
            if searched == folder:
                return
            if locked:
                raise RuntimeError(f"expected this process's DuckDB instance to search {folder}, got a locked "
                                   f"configuration searching {searched!r}")
            con.execute("SET GLOBAL file_search_path = ?", [folder])

    def _confine(self, con: duckdb.DuckDBPyConnection) -> None:
        """After the views exist (they name the shard files): the warehouse folder only, then lock.

        DuckDB keeps these settings on the database instance, which every connection a process holds
        open to the same file shares (the dashboard answers requests concurrently): a connection that
        finds the instance already locked checks that the lock confines it to this warehouse instead
        of setting it again (which a locked configuration refuses)."""
        folders = self.store.allowed()  # the warehouse folder; an S3 store's prefix too
        with _CONFINING:  # two threads that both found it unlocked would both set it: the second is refused
            [(locked, external, allowed)] = con.execute(
                "SELECT current_setting('lock_configuration'), current_setting('enable_external_access'), "
                "current_setting('allowed_directories')").fetchall()
            if locked:
                if external or not set(folders) <= set(allowed):
                    raise RuntimeError(f"expected this process's DuckDB instance confined to {folders}, "
                                       f"got a locked configuration allowing {allowed} (external access {external})")
                return
            con.execute("SET allowed_directories = ?", [folders])
            con.execute("SET enable_external_access = false")
            con.execute("SET lock_configuration = true")

    def _refresh_views(self, con: duckdb.DuckDBPyConnection, tables: Sequence[str] | set[str],
                       emptied: Mapping[str, set[int]] | None = None, everything: bool = False) -> None:
        """Views over exactly the registered shards of `tables`: unregistered files are invisible.

        A table's view is the UNION ALL of its part views (`_<table>_part_<n>`), each naming at most
        VIEW_PART_SHARDS files; shards join the last part in registration order. Rewriting one view
        that named every shard cost a registration time in proportion to the shards registered (1 s
        at the 10,000th unit); now a registration rewrites the parts its shards joined, and the
        table's view only when a part is added. `emptied`: parts that lost shards (quarantine), also
        rewritten; `everything` rewrites every part and the view (initialise, a moved warehouse).
        (The ready-made views name these views, so they need no refresh.)"""
        for name in tables:
            before = self._last_part(con, name)
            parts = self._assign_parts(con, name, before)
            last = max(parts, default=before)  # parts are given from the last one on
            rewrite_view = everything or last != before
            compacted = rewrite_view and con.execute(  # asked only where the table's view is rewritten
                f"SELECT count(*) > 0 FROM {self._persistent(con)}.shards WHERE table_name = ? AND view_part = ?",
                [name, COMPACTED_PART]).fetchone()[0]
            if everything:
                parts = set(range(last + 1)) | ({COMPACTED_PART} if compacted else set())
            for part in sorted(parts | set((emptied or {}).get(name, ()))):
                con.execute(f"CREATE OR REPLACE VIEW {self._part_view(name, part)} AS SELECT * FROM "
                            f"{self._part_source(con, name, part)}")
            if rewrite_view:
                union = " UNION ALL ".join(f"SELECT * FROM {self._part_view(name, part)}" for part in
                                           [*([COMPACTED_PART] if compacted else []), *range(last + 1)])
                con.execute(f"CREATE OR REPLACE VIEW {name} AS {union or f'SELECT * FROM _empty_{name}'}")

    @staticmethod
    def _last_part(con: duckdb.DuckDBPyConnection, table: str) -> int:
        """The table's highest view part; -1 before any."""
        return con.execute(f"SELECT coalesce(max(view_part), -1) FROM {Catalog._persistent(con)}.shards "
                           "WHERE table_name = ?", [table]).fetchone()[0]

    def _assign_parts(self, con: duckdb.DuckDBPyConnection, table: str, last: int) -> set[int]:
        """Give the table's shards without a part (just registered; or all, after the layout-8
        migration) the last part while it has room, then new ones, in path order. -> the parts given."""
        waiting = [path for (path,) in con.execute(
            "SELECT path FROM shards WHERE table_name = ? AND view_part IS NULL ORDER BY path", [table]).fetchall()]
        if not waiting:
            return set()
        held = con.execute("SELECT count(*) FROM shards WHERE table_name = ? AND view_part = ?", [table, last]).fetchone()[0]
        part, room, given = (last, VIEW_PART_SHARDS - held, []) if last >= 0 else (0, VIEW_PART_SHARDS, [])
        for path in waiting:
            if room == 0:
                part, room = part + 1, VIEW_PART_SHARDS
            given.append((part, path))
            room -= 1
        con.executemany("UPDATE shards SET view_part = ? WHERE path = ?", given)
        return {part for part, _ in given}

    def _part_source(self, con: duckdb.DuckDBPyConnection, table: str, part: int) -> str:
        """What a part view reads: its shards, named relative to the warehouse (the views hold when the
        workspace moves); COMPACTED_PART's are the compacted files."""
        return self._source(con, table, "s.view_part = ?", [part], temporary=False)

    @staticmethod
    def _part_view(table: str, part: int) -> str:
        return f"_{table}_compacted" if part == COMPACTED_PART else f"_{table}_part_{part:05d}"

    def _snapshot_views(self, con: duckdb.DuckDBPyConnection, iteration: int) -> None:
        """Temporary views shadow the persistent ones (DuckDB resolves temp first)."""
        for name in SHARD_TABLES:
            con.execute(
                f"CREATE TEMP VIEW {name} AS SELECT * FROM {self._shard_source(con, name, iteration, True)}"
            )
        persistent = self._persistent(con)
        for name in ITERATION_TABLES:
            con.execute(f"CREATE TEMP VIEW {name} AS SELECT * FROM {persistent}.{name} WHERE iteration <= {int(iteration)}")
        self._current_views(con)

    @staticmethod
    def _current_views(con: duckdb.DuckDBPyConnection) -> None:
        """This code's ready-made views (schemas/tables.VIEWS) for this connection: a catalog last written by an
        older sim2act keeps their older definitions until a writer opens it (a layout bump would stop runs of
        that older code; a stamp would not see an older writer replace them again), and a reader — the
        dashboard's panels, `sim2act sql` — would count by them. ~20 ms a connection on 100 units' shards."""
        for name, query in VIEWS.items():
            con.execute(f"CREATE TEMP VIEW {name} AS {query}")

    def clean_orphans(self) -> list[Path]:
        """Delete shard files (and temporaries) that no catalog row names, and abort unfinished uploads
        (a store's: `ShardStore.abort_uploads`): leftovers of a killed run. Call it only where no other writer is at work on this warehouse. -> their paths
        under the warehouse folder (where the store keeps them)."""
        known: set[str] = set()
        if self.path.exists():
            with self.connect(read_only=True) as con:
                known = {row[0] for row in con.execute(  # a compacted shard's own file is gone, or soon
                    "SELECT path FROM shards WHERE stored_in IS NULL UNION ALL SELECT path FROM compacted").fetchall()}
        removed = []
        for rel in self.store.files("shards"):
            if rel not in known:
                self.store.delete(rel)
                removed.append(self.warehouse / rel)
        return removed + [self.warehouse / rel for rel in self.store.abort_uploads("shards")]

    # -- corruption ------------------------------------------------------------------------

    def verify(self, full: bool = False, paths: Sequence[str] | None = None) -> list[tuple[str, str]]:
        """Check the registered files (all, or those at `paths`): the shards still their own and the
        compacted files: present, a whole Parquet file of the declared schema and row count, with
        `full` its sha256 too. The bad ones are quarantined (a compacted file: every unit it holds).
        -> [(path, reason)]."""
        if not self.path.exists():
            return []
        with self.connect(read_only=True) as con:
            files = con.execute(
                "SELECT path, table_name, num_rows, sha256 FROM (SELECT path, table_name, num_rows, sha256 FROM shards "
                "WHERE stored_in IS NULL UNION ALL SELECT path, table_name, num_rows, sha256 FROM compacted) "
                "WHERE ? IS NULL OR list_contains(?, path) ORDER BY path", [paths, paths],
            ).fetchall()
        bad = []
        for path, table, num_rows, sha in files:
            where = self.store.location(path)
            try:
                if inspect_shard(table, self.warehouse / path, self.store) != num_rows:
                    raise ShardUnreadable(f"{where}: {num_rows} rows registered, the file has others")
                if full and self.store.sha256(path) != sha:
                    raise ShardUnreadable(f"{where}: sha256 differs from the registered one")
            except (ShardUnreadable, SchemaMismatch) as exc:
                bad.append((path, str(exc)))
        # a file listed above may have been compacted away since (a `warehouse compact` beside this): its
        # rows are in the compacted file now, and its unit is not the one to quarantine
        return [(path, reason) for path, reason in bad if self.quarantine(path, reason, checked_file=True)]

    def quarantine(self, path: str, reason: str, checked_file: bool = False) -> bool:
        """Unregister the unit whose file `path` is bad, with all its shards (a compacted file: every
        unit it holds), and move the files to warehouse/quarantine/: queries keep working without them,
        and the next run redoes the units (same seeds, same data). A compacted file that still holds
        other units' rows stays, its views cut to those rows; one that holds none goes too.
        `checked_file`: `path` is a file found bad (verify's), quarantined only while the catalog still
        reads it, as a shard's own file or a compacted one (a source compacted since is not). -> whether
        any unit was quarantined."""
        with self._transaction() as con:
            own_file = "stored_in IS NULL" if checked_file else "TRUE"
            units = [unit for (unit,) in con.execute(
                f"SELECT DISTINCT unit_key FROM shards WHERE (path = ? AND {own_file}) OR stored_in = ? ORDER BY 1",
                [path, path]).fetchall()]
            if not units:
                return False
            siblings = con.execute("SELECT path, table_name, iteration, view_part, unit_key, stored_in FROM shards "
                                   "WHERE list_contains(?, unit_key)", [units]).fetchall()
            now = datetime.now(timezone.utc).replace(tzinfo=None)
            _insert(con, "quarantine", check_rows("quarantine", [{
                "path": p, "table_name": t, "unit_key": unit, "iteration": i,
                "reason": reason if path in (p, stored) else f"sibling of {path}", "quarantined_at": now,
            } for p, t, i, _, unit, stored in siblings]))
            parts: dict[str, set[int]] = {}
            for _, table, _, part, _, _ in siblings:
                if part is not None:
                    parts.setdefault(table, set()).add(part)
            con.execute("DELETE FROM shards WHERE list_contains(?, unit_key)", [units])
            con.execute("DELETE FROM stage_runs WHERE list_contains(?, unit_key)", [units])
            emptied = [file for (file,) in con.execute(
                "DELETE FROM compacted WHERE path NOT IN (SELECT stored_in FROM shards WHERE stored_in IS NOT NULL) "
                "RETURNING path").fetchall()]
            self._refresh_views(con, {t for _, t, _, _, _, _ in siblings}, emptied=parts)
        for p in [p for p, _, _, _, _, stored in siblings if stored is None] + emptied:
            if self.store.exists(p):
                self.store.move(p, f"quarantine/{p}")
        return True

    def registered_shard_in(self, message: str) -> str | None:
        """The registered file (a shard's own, or a compacted one) a DuckDB error message names, if any. Read on
        a bare connection: one that makes the shard views (a confined reader's) would read the torn file again."""
        con = self._open(True)
        try:
            paths = con.execute("SELECT path FROM shards WHERE stored_in IS NULL UNION ALL SELECT path FROM compacted")
            return next((path for (path,) in paths.fetchall() if path in message), None)
        finally:
            con.close()

    # -- reader side -----------------------------------------------------------------------

    def query(self, sql: str, params: Sequence[Any] = (), as_of_iteration: int | None = None,
              confined: bool = False) -> list[tuple]:
        """`confined`: the SQL holds a user's text (a --where): the warehouse's files only (connect)."""
        with self.connect(read_only=True, as_of_iteration=as_of_iteration, confined=confined) as con:
            return con.execute(sql, list(params)).fetchall()

    def query_arrow(self, sql: str, params: Sequence[Any] = (), as_of_iteration: int | None = None,
                    confined: bool = False) -> pa.Table:
        with self.connect(read_only=True, as_of_iteration=as_of_iteration, confined=confined) as con:
            return con.execute(sql, list(params)).to_arrow_table()

    def read_unit_shard(self, table: str, unit_key: str, columns: list[str] | None = None) -> pa.Table:
        """The rows unit `unit_key` wrote into `table`, from its own file or the compacted one holding them.

        Raises:
            KeyError: the unit has no registered shard of that table."""
        found = self.query("SELECT path, stored_in, row_offset, num_rows FROM shards WHERE table_name = ? AND unit_key = ?",
                           [table, unit_key])
        if not found:
            raise KeyError(f"expected a registered {table} shard of unit {unit_key}, got none")
        [(path, stored_in, offset, rows)] = found
        if stored_in is None:
            return read_shard(table, self.warehouse / path, columns, self.store)
        return read_shard_rows(table, self.warehouse / stored_in, offset, offset + rows, columns, self.store)
