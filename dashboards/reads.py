"""Everything the dashboard reads from the warehouse: read-only SQL on a brief connection.

A campaign may be registering units while the page is open: Catalog.connect opens read-only,
waits out a writer's lock, and closes at once, so the dashboard never holds the writer up
for longer than one query. Shards found corrupt are left to `sim2act sql` and
`sim2act warehouse verify` to quarantine: the dashboard writes nothing.
"""

from __future__ import annotations

import datetime
import decimal
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import duckdb

from schemas.tables import CURRENT_FILTER_DECISIONS, CURRENT_TASK_FAMILIES
from warehouse.catalog import Catalog
from warehouse.sql import check_read_only


@dataclass(frozen=True)
class Rows:
    columns: list[str]
    rows: list[dict[str, Any]]


def _json_value(value: Any) -> Any:
    if isinstance(value, decimal.Decimal):
        return float(value)
    if isinstance(value, (datetime.date, datetime.datetime, datetime.timedelta)):
        return str(value)
    if isinstance(value, bytes):
        return f"<{len(value)} bytes>"
    return value


def read_rows(catalog: Catalog, sql: str, params: Mapping[str, Any] | Sequence[Any] = ()) -> Rows:
    """A read-only query's rows as JSON-ready dicts (anything but SELECT/EXPLAIN is refused), on a
    connection confined to the warehouse's files like `sim2act sql`'s (Catalog.connect)."""
    with catalog.connect(read_only=True, confined=True) as con:
        return _rows(con, sql, params)


def _rows(con: duckdb.DuckDBPyConnection, sql: str, params: Mapping[str, Any] | Sequence[Any] = ()) -> Rows:
    """`read_rows` on a connection already open (several queries of one request share it)."""
    check_read_only(sql)
    cursor = con.execute(sql, params if isinstance(params, Mapping) else list(params))
    columns = [d[0] for d in cursor.description]
    return Rows(columns, [dict(zip(columns, map(_json_value, row))) for row in cursor.fetchall()])


def campaigns(catalog: Catalog) -> list[str]:
    """The catalog's campaigns, the one most recently at work first."""
    sql = "SELECT campaign FROM stage_runs GROUP BY campaign ORDER BY max(finished_at) DESC, campaign"
    return [row["campaign"] for row in read_rows(catalog, sql).rows]


# The episode browser: explored episodes with the filter's decision, narrowed by the page's choices.
_EPISODES = f"""
    SELECT e.episode_id, e.iteration, e.task_id, t.family, t.split, e.instruction, e.explorer,
           e.episode_return, e.success, e.num_steps, e.error, f.kept, f.reason, f.detail
    FROM episodes e
    LEFT JOIN {CURRENT_TASK_FAMILIES} t ON t.campaign = e.campaign AND t.task_id = e.task_id
    LEFT JOIN {CURRENT_FILTER_DECISIONS} f ON f.episode_id = e.episode_id
    WHERE e.campaign = $campaign
      AND ($iteration IS NULL OR e.iteration = $iteration)
      AND ($task IS NULL OR e.task_id = $task)
      AND ($explorer IS NULL OR e.explorer = $explorer)
      AND ($reason IS NULL OR coalesce(f.reason, 'not filtered yet') = $reason)
"""


@dataclass(frozen=True)
class EpisodeQuery:
    campaign: str
    iteration: int | None = None
    task: str | None = None
    explorer: str | None = None
    reason: str | None = None

    def params(self) -> dict[str, Any]:
        return {"campaign": self.campaign, "iteration": self.iteration, "task": self.task,
                "explorer": self.explorer, "reason": self.reason}


_CHOICES = f"""
    SELECT list_sort(list_distinct(list(iteration))) AS iterations, list_sort(list_distinct(list(task_id))) AS tasks,
           list_sort(list_distinct(list(explorer))) AS explorers,
           list_sort(list_distinct(list(coalesce(reason, 'not filtered yet')))) AS reasons
    FROM ({_EPISODES})"""


def episodes(catalog: Catalog, query: EpisodeQuery, offset: int, limit: int) -> tuple[int, Rows, dict[str, list]]:
    """(how many episodes match, one page of them in exploration order, what the browser's filters offer: the
    values present in the campaign's episodes). One connection, one read of the shards' footers for all three
    (six connections made a page of an 800-shard warehouse take 2.7 s), and a count that agrees with the page."""
    with catalog.connect(read_only=True, confined=True) as con:
        total = _rows(con, f"SELECT count(*) AS n FROM ({_EPISODES})", query.params()).rows[0]["n"]
        page = _rows(con, f"{_EPISODES} ORDER BY e.iteration, e.task_id, e.episode_id "
                          f"LIMIT {int(limit)} OFFSET {int(offset)}", query.params())
        [choices] = _rows(con, _CHOICES, EpisodeQuery(query.campaign).params()).rows
    return total, page, {name: values or [] for name, values in choices.items()}


def task_evaluations(catalog: Catalog, campaign: str, task_id: str) -> Rows:
    """The campaign's evaluation cases of a task, each with its MP4s (paths as the evaluate stage
    wrote them): every iteration's model (agent `policy`) and the baselines (`expert`, `ppo`, `sac`), on the
    campaign's cases first, then on another suite (`sim2act eval --tasks`, or other render settings: named)."""
    return read_rows(catalog, """
        SELECT e.iteration, e.model_key,
               CASE WHEN m.model_key IS NOT NULL THEN 'policy' ELSE coalesce(b.summary->>'algorithm', e.model_key) END
                   AS agent,
               e.suite, e.split, e.instruction, e.successes, e.episodes, e.success_video, e.failure_video
        FROM current_evaluations e
        LEFT JOIN models m ON m.model_key = e.model_key
        LEFT JOIN stage_runs b ON b.unit_key = e.model_key AND b.stage = 'baselines'
        WHERE e.campaign = $campaign AND e.task_id = $task
        ORDER BY e.suite <> 'campaign', e.suite, e.iteration DESC, agent = 'policy' DESC, agent,
                 CASE e.split WHEN 'seen' THEN 0 WHEN 'unseen' THEN 1 ELSE 2 END
    """, {"campaign": campaign, "task": task_id})


def episode_frames(catalog: Catalog, episode_id: str) -> list[bytes]:
    """An episode's stored observations, in step order, then the one after its last action."""
    rows = catalog.query("SELECT image, next_image FROM steps WHERE episode_id = ? ORDER BY step", [episode_id])
    frames = [image for image, _ in rows if image]
    if rows and rows[-1][1]:
        frames.append(rows[-1][1])
    return frames
