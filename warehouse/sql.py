"""Read-only SQL over the catalog, formatted for a terminal or a pipe."""

from __future__ import annotations

import csv
import io
import json
import logging
from typing import Literal

import duckdb
import pyarrow as pa

from schemas.errors import Sim2ActError
from warehouse.catalog import Catalog

OutputFormat = Literal["table", "csv", "json"]
_READ_STATEMENTS = {duckdb.StatementType.SELECT, duckdb.StatementType.EXPLAIN}
log = logging.getLogger("sim2act.warehouse")


class ReadOnlyViolation(Sim2ActError, ValueError):
    pass


def check_read_only(sql: str) -> None:
    """Refuse anything but SELECT/EXPLAIN (COPY ... TO writes files even on a read-only connection)."""
    try:
        statements = duckdb.extract_statements(sql)
    except duckdb.ParserException as exc:
        raise ReadOnlyViolation(f"SQL does not parse: {str(exc).splitlines()[0]}") from None
    if not statements:
        raise ReadOnlyViolation("no SQL statement given")
    for statement in statements:
        if statement.type not in _READ_STATEMENTS:
            words = statement.query.split()  # (a leading comment is no keyword: then DuckDB's name for the type)
            said = words[0].upper() if words and words[0].isalpha() else statement.type.name
            raise ReadOnlyViolation(f"the warehouse is read-only here: {said} statements are refused (use SELECT)")
    if len(statements) > 1:  # DuckDB answers the last one only: the others' results would vanish unsaid
        raise ReadOnlyViolation(f"expected one SQL statement, got {len(statements)}: run each on its own")


def _cell(value: object) -> object:
    if isinstance(value, bytes):
        return f"<{len(value)} bytes>"
    return value


def format_rows(table: pa.Table, fmt: OutputFormat) -> str:
    columns = table.column_names
    rows = [[_cell(v) for v in row.values()] for row in table.to_pylist()]
    if fmt == "json":
        return json.dumps([dict(zip(columns, row)) for row in rows], default=str, indent=1)
    if fmt == "csv":
        out = io.StringIO()
        writer = csv.writer(out, lineterminator="\n")
        writer.writerow(columns)
        writer.writerows(rows)
        return out.getvalue().rstrip("\n")
    text = [[str(c) for c in columns]] + [["NULL" if v is None else str(v) for v in row] for row in rows]
    widths = [min(60, max(len(r[i]) for r in text)) for i in range(len(columns))]
    lines = [" | ".join(cell[:60].ljust(w) for cell, w in zip(r, widths)) for r in text]
    lines.insert(1, "-+-".join("-" * w for w in widths))
    lines.append(f"({len(rows)} row{'s' if len(rows) != 1 else ''})")
    return "\n".join(lines)


def query_with_quarantine(catalog: Catalog, sql: str, as_of_iteration: int | None = None) -> pa.Table:
    """Run a read-only query on a connection confined to the warehouse's files; when it fails on a registered shard that turns out corrupt, the
    shard is quarantined (reported in the log) and the query runs again without it. The check
    includes its sha256: bytes changed inside a data page leave a whole Parquet footer, and only
    the query reading that page trips over them."""
    check_read_only(sql)
    while True:
        try:
            return catalog.query_arrow(sql, as_of_iteration=as_of_iteration, confined=True)
        except duckdb.Error as exc:
            path = catalog.registered_shard_in(str(exc))
            if path is None or not any(p == path for p, _ in catalog.verify(full=True, paths=[path])):
                raise
            log.warning("quarantined %s (%s); the query ran without it", path, str(exc).splitlines()[0])


def run_sql(catalog: Catalog, sql: str, fmt: OutputFormat = "table", as_of_iteration: int | None = None) -> str:
    return format_rows(query_with_quarantine(catalog, sql, as_of_iteration), fmt)
