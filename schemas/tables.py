"""Arrow schemas of every warehouse table, the catalog DDL derived from them, and the views.

Layout version: schemas.version.SCHEMA_VERSION, stamped into every shard's metadata and into
the catalog. Big, append-only data (episodes, steps, filter decisions, instruction embeddings)
lives in immutable Parquet shards; small bookkeeping tables live inside the DuckDB catalog
file. Both kinds are declared here, once, as Arrow schemas: the shard writer checks shards
against them, the catalog creates its tables from them and checks rows before inserting.
"""

from __future__ import annotations

from dataclasses import dataclass

import pyarrow as pa

# A JSON document in a string column; the catalog types it JSON so `summary->>'x'` works.
_SQL_TYPE = b"sql_type"


def _json(name: str) -> pa.Field:
    return pa.field(name, pa.string(), metadata={_SQL_TYPE: b"JSON"})


# One episode's domain randomisation (envs.randomisation): null where its family does not apply
# an aspect; the whole struct is null when the campaign turned randomisation off.
RANDOMISATION = pa.struct(
    [
        ("light", pa.float64()),
        ("camera_shift", pa.list_(pa.float64())),
        ("camera_rotation_deg", pa.list_(pa.float64())),
        ("tint", pa.list_(pa.float64())),
        ("colour_jitter", pa.list_(pa.float64())),
        ("size", pa.float64()),
        ("mass", pa.float64()),
        ("friction", pa.float64()),
    ]
)

# The visual settings an episode was rendered with (schemas.config.RenderConfig): replay and
# evaluation render alike from them.
RENDER = pa.struct(
    [
        ("camera", pa.string()),
        ("image_size", pa.int32()),
        ("shadows", pa.bool_()),
        ("reflections", pa.bool_()),
        ("multisamples", pa.int32()),
        ("depth", pa.bool_()),
    ]
)

# -- shard tables: immutable Parquet files ---------------------------------------------------

EPISODES = pa.schema(
    [
        ("campaign", pa.string()),
        ("iteration", pa.int32()),
        ("episode_id", pa.string()),
        ("task_id", pa.string()),
        ("instruction", pa.string()),
        ("explorer", pa.string()),  # "expert" or "policy:<registered model>/<version>"
        ("seed", pa.int64()),
        ("shard_key", pa.string()),
        ("num_steps", pa.int32()),
        ("episode_return", pa.float64()),
        ("success", pa.bool_()),
        ("error", pa.string()),  # null, or why the environment failed mid-episode
        ("randomisation", RANDOMISATION),
        ("render", RENDER),
        # what the explorer reports about the episode: the expert its noise level, a VLM its calls,
        # retries, timeouts, invalid answers
        _json("explorer_stats"),
    ]
)

# One row per transition (o_t, l, a_t, o_{t+1}). o_{t+1} is the next row's `image` (and `depth`);
# the last step of an episode carries it in `next_image` (`next_depth`). The `triplets` view joins them. The MuJoCo
# state before the action (qpos, qvel, act, mocap, sim_time) is what replay and re-rendering
# set back into the model.
STEPS = pa.schema(
    [
        ("campaign", pa.string()),
        ("iteration", pa.int32()),
        ("episode_id", pa.string()),
        ("task_id", pa.string()),
        ("step", pa.int32()),
        ("instruction", pa.string()),
        ("image", pa.binary()),  # raw RGB frame, image_size square (or two side by side: render.wrist_camera), upright
        ("depth", pa.binary()),  # its depth map, uint16 millimetres (schemas.frames); null unless render.depth
        ("proprio", pa.list_(pa.float32())),
        ("action", pa.list_(pa.float32())),
        ("reward", pa.float32()),
        ("done", pa.bool_()),
        ("success", pa.bool_()),
        ("next_image", pa.binary()),
        ("next_depth", pa.binary()),
        ("qpos", pa.list_(pa.float64())),
        ("qvel", pa.list_(pa.float64())),
        ("act", pa.list_(pa.float64())),  # actuator activations (empty for models without any)
        ("mocap", pa.list_(pa.float64())),  # mocap body pos (3 each) then quat (4 each): MetaWorld's hand
        ("sim_time", pa.float64()),
        # the scripted expert's noiseless action at this state (DAgger labels), where the campaign
        # records them (explore.expert_labels); null otherwise
        ("expert_action", pa.list_(pa.float32())),
    ]
)

FILTER_DECISIONS = pa.schema(
    [
        ("campaign", pa.string()),
        ("iteration", pa.int32()),
        ("episode_id", pa.string()),
        ("task_id", pa.string()),
        ("kept", pa.bool_()),
        # "kept", "env_error", "invalid_values", "action_out_of_bounds", "bad_image",
        # "duplicate", "not_successful", "low_return"
        ("reason", pa.string()),
        ("detail", pa.string()),  # what exactly failed, for the rejections that have one
        ("episode_digest", pa.string()),  # of its actions and observations: identical episodes match
        ("episode_return", pa.float64()),
        ("filter_key", pa.string()),
    ]
)

INSTRUCTIONS = pa.schema(
    [
        ("task_id", pa.string()),
        ("instruction", pa.string()),
        ("encoder", pa.string()),
        ("embedding", pa.list_(pa.float32())),
    ]
)

SHARD_TABLES: dict[str, pa.Schema] = {
    "episodes": EPISODES,
    "steps": STEPS,
    "filter_decisions": FILTER_DECISIONS,
    "instructions": INSTRUCTIONS,
}

# -- catalog tables: rows inside the DuckDB file ---------------------------------------------


@dataclass(frozen=True)
class CatalogTable:
    schema: pa.Schema
    primary_key: tuple[str, ...] = ()


CATALOG_TABLES: dict[str, CatalogTable] = {
    "catalog_meta": CatalogTable(pa.schema([("key", pa.string()), ("value", pa.string())]), ("key",)),
    "stage_runs": CatalogTable(
        pa.schema([
            ("unit_key", pa.string()), ("stage", pa.string()), ("campaign", pa.string()), ("iteration", pa.int32()),
            ("finished_at", pa.timestamp("us")), ("wall_s", pa.float64()), _json("summary"),
        ]),
        # no PRIMARY KEY (layout 10): register_unit refuses a known unit_key in its transaction, and a key's
        # index cost every registration a rewrite of it (schemas/version.py)
    ),
    "shards": CatalogTable(
        pa.schema([
            ("path", pa.string()),  # relative to the warehouse folder
            ("table_name", pa.string()), ("unit_key", pa.string()), ("campaign", pa.string()),
            ("iteration", pa.int32()), ("num_rows", pa.int64()), ("num_bytes", pa.int64()), ("sha256", pa.string()),
            ("schema_version", pa.int32()),
            # which of its table's part views names this shard (Catalog._refresh_views): parts fill in
            # registration order, VIEW_PART_SHARDS each, so a registration rewrites one small view
            ("view_part", pa.int32()),
            # after `sim2act compact`: the compacted file (`compacted.path`) that now holds this shard's rows,
            # from its row `row_offset` on (path, sha256 and unit stay: lineage and dataset digests hold);
            # NULL while the shard is its own file
            ("stored_in", pa.string()), ("row_offset", pa.int64()),
        ]),
        # no PRIMARY KEY (layout 10): a shard's path names its unit, registered once (stage_runs)
    ),
    # Files `sim2act compact` wrote: a finished iteration's small shards of one table and campaign,
    # concatenated in path order (warehouse/compaction.py). Their sources' rows say where they went.
    "compacted": CatalogTable(
        pa.schema([
            ("path", pa.string()),  # relative to the warehouse folder
            ("table_name", pa.string()), ("campaign", pa.string()), ("iteration", pa.int32()),
            ("num_rows", pa.int64()), ("num_bytes", pa.int64()), ("sha256", pa.string()),
            ("sources", pa.int32()),  # shard files it replaced
            ("compacted_at", pa.timestamp("us")),
        ]),
        ("path",),
    ),
    # Shards found corrupt or unreadable, moved aside to warehouse/quarantine/<path>.
    "quarantine": CatalogTable(
        pa.schema([
            ("path", pa.string()), ("table_name", pa.string()), ("unit_key", pa.string()),
            ("iteration", pa.int32()), ("reason", pa.string()), ("quarantined_at", pa.timestamp("us")),
        ]),
    ),
    "tasks": CatalogTable(
        pa.schema([
            ("campaign", pa.string()), ("task_id", pa.string()), ("spec", pa.string()), ("family", pa.string()),
            ("env_name", pa.string()), ("instruction", pa.string()), ("instructions", pa.list_(pa.string())),
            ("unseen_instructions", pa.list_(pa.string())), _json("object_colours"), ("split", pa.string()),
            ("horizon", pa.int32()), ("unit_key", pa.string()),
        ]),
        ("unit_key", "task_id"),
    ),
    "iterations": CatalogTable(
        pa.schema([
            ("unit_key", pa.string()), ("campaign", pa.string()), ("iteration", pa.int32()),
            ("dataset_digest", pa.string()), ("explore_units", pa.list_(pa.string())),
            ("filter_units", pa.list_(pa.string())), ("episodes", pa.int64()), ("kept_episodes", pa.int64()),
            ("triplets", pa.int64()),
        ]),
        ("unit_key",),
    ),
    "models": CatalogTable(
        pa.schema([
            ("model_key", pa.string()), ("campaign", pa.string()), ("iteration", pa.int32()),
            ("checkpoint_path", pa.string()), ("dataset_digest", pa.string()),
            ("dataset_shards", pa.list_(pa.string())),  # the steps shards training read, exactly
            ("train_samples", pa.int64()),
            ("final_loss", pa.float64()), ("unit_key", pa.string()),
        ]),
        ("model_key",),
    ),
    "deployments": CatalogTable(
        pa.schema([
            ("unit_key", pa.string()), ("model_key", pa.string()), ("campaign", pa.string()),
            ("iteration", pa.int32()), ("registered_model", pa.string()), ("version", pa.int32()),
            ("alias", pa.string()), ("champion_version", pa.int32()), ("champion_model_key", pa.string()),
            # whether the evaluation moved the alias to this version, and why (stages.evaluate.Promotion)
            ("promoted", pa.bool_()), ("decision", pa.string()),
            ("mlflow_run_id", pa.string()),
        ]),
        ("unit_key",),
    ),
    "evaluations": CatalogTable(
        pa.schema([
            ("unit_key", pa.string()), ("campaign", pa.string()), ("iteration", pa.int32()),
            # what asked: "campaign" (the flow's evaluate stage), or `sim2act eval`'s task set
            ("suite", pa.string()),
            ("model_key", pa.string()), ("task_id", pa.string()), ("family", pa.string()), ("split", pa.string()),
            ("instruction", pa.string()), ("episodes", pa.int32()), ("successes", pa.int32()),
            ("success_rate", pa.float64()),
            ("ci_low", pa.float64()), ("ci_high", pa.float64()),  # Wilson 95% interval of success_rate
            ("mean_return", pa.float64()), ("mean_length", pa.float64()),
            ("episode_lengths", pa.list_(pa.int32())), ("episode_successes", pa.list_(pa.bool_())),  # seed order
            # the policy's mean per-step uncertainty: entropy (discrete) or log det Sigma (continuous)
            ("uncertainty", pa.float64()),
            ("success_video", pa.string()), ("failure_video", pa.string()),  # MP4s: first success, first failure
            # per episode, seed order: the task the agent ended doing (the evaluated task when it succeeded,
            # another task of the evaluated set whose goal it ended at, or null); null list: not recorded
            ("episode_achieved", pa.list_(pa.string())),
        ]),
        ("unit_key",),
    ),
}

_SQL_TYPES = {
    pa.string(): "VARCHAR", pa.int32(): "INTEGER", pa.int64(): "BIGINT", pa.float32(): "FLOAT",
    pa.float64(): "DOUBLE", pa.bool_(): "BOOLEAN", pa.timestamp("us"): "TIMESTAMP", pa.binary(): "BLOB",
}


def sql_type(field: pa.Field) -> str:
    """The DuckDB type a catalog column of this Arrow field has."""
    if field.metadata and _SQL_TYPE in field.metadata:
        return field.metadata[_SQL_TYPE].decode()
    if pa.types.is_list(field.type):
        return sql_type(field.type.value_field) + "[]"
    return _SQL_TYPES[field.type]


def catalog_ddl(name: str) -> str:
    table = CATALOG_TABLES[name]
    columns = [f"{f.name} {sql_type(f)}" for f in table.schema]
    if table.primary_key:
        columns.append(f"PRIMARY KEY ({', '.join(table.primary_key)})")
    return f"CREATE TABLE IF NOT EXISTS {name} ({', '.join(columns)})"


# Tables a snapshot (`--as-of-iteration K`) cuts at iteration K. `tasks` are per campaign.
ITERATION_TABLES = ("stage_runs", "shards", "compacted", "quarantine", "iterations", "models", "deployments",
                    "evaluations")

# The deployment that counts for each campaign's iteration: its latest (a campaign run again in its workspace with
# another training recipe deploys a second model for the same iteration). A subquery, not one of the views below:
# read-only commands (`sim2act report`) open catalogs whose views an older sim2act made. dashboards/panels.yaml
# spells the same query out.
CURRENT_DEPLOYMENTS = """(
    SELECT d.* FROM deployments d LEFT JOIN stage_runs r ON r.unit_key = d.unit_key
    QUALIFY row_number() OVER (PARTITION BY d.campaign, d.iteration
                               ORDER BY r.finished_at DESC NULLS LAST, d.unit_key DESC) = 1)"""

# One dataset per campaign iteration: its latest registered. A campaign run again in its workspace with another
# filter.* (or explore.*) indexes the same iteration again.
CURRENT_ITERATIONS = """(
    SELECT i.* FROM iterations i LEFT JOIN stage_runs r ON r.unit_key = i.unit_key
    QUALIFY row_number() OVER (PARTITION BY i.campaign, i.iteration ORDER BY r.finished_at DESC NULLS LAST,
                               i.unit_key DESC) = 1)"""

# One filter decision per episode: its latest filter unit's. A campaign run again in its workspace with another
# `filter.*` decides its episodes again (stages/filter.py keeps each setting's lineage apart); counted together, a
# view would count those episodes once per setting. A subquery, as CURRENT_DEPLOYMENTS (dashboards/panels.yaml
# spells it out).
CURRENT_FILTER_DECISIONS = """(
    SELECT f.* FROM filter_decisions f LEFT JOIN stage_runs r ON r.unit_key = f.filter_key
    QUALIFY row_number() OVER (PARTITION BY f.episode_id ORDER BY r.finished_at DESC NULLS LAST, f.filter_key DESC) = 1)"""

# Which task does an id name: one row per (campaign, task), its latest tasks unit's (a changed tasks.* can say
# another split or family for the same id). The task_families view; a subquery for the readers that may open a
# catalog whose views an older sim2act made (views are made again when a run next writes the catalog).
CURRENT_TASK_FAMILIES = """(
    SELECT t.campaign, t.task_id, t.family, t.spec, t.split FROM tasks t LEFT JOIN stage_runs r ON r.unit_key = t.unit_key
    QUALIFY row_number() OVER (PARTITION BY t.campaign, t.task_id ORDER BY r.finished_at DESC NULLS LAST,
                               t.unit_key DESC) = 1)"""

# Views over the tables above, ready for `sim2act sql` and the dashboards.
VIEWS = {
    # One row per evaluation case (campaign, model, suite, task, split, wording): the one of most episodes, then
    # the latest. A case evaluated again (a new evaluate stage version, `sim2act eval --episodes`) keeps its
    # earlier rows, on the same episode seeds: summing them all would count those episodes twice. The campaign:
    # its seeds are another's episodes, and the expert's model key is every campaign's.
    "current_evaluations": """
        SELECT e.* FROM evaluations e LEFT JOIN stage_runs r ON r.unit_key = e.unit_key
        QUALIFY row_number() OVER (PARTITION BY e.campaign, e.model_key, e.suite, e.task_id, e.split, e.instruction
                                   ORDER BY e.episodes DESC, r.finished_at DESC NULLS LAST, e.unit_key) = 1
    """,
    "triplets": """
        SELECT s.campaign, s.iteration, s.episode_id, s.task_id, s.step, s.instruction,
               s.image AS obs, s.depth AS obs_depth, s.action, s.reward, s.done, s.success,
               COALESCE(n.image, s.next_image) AS next_obs, COALESCE(n.depth, s.next_depth) AS next_obs_depth
        FROM steps s LEFT JOIN steps n ON n.episode_id = s.episode_id AND n.step = s.step + 1""",
    "kept_steps": f"""
        SELECT s.* FROM steps s
        WHERE s.episode_id IN (SELECT episode_id FROM {CURRENT_FILTER_DECISIONS} WHERE kept)""",
    "task_families": f"SELECT * FROM {CURRENT_TASK_FAMILIES}",
    "task_success": """
        SELECT e.campaign, e.iteration, e.task_id, t.family, t.split, e.explorer,
               count(*) AS episodes, count(*) FILTER (WHERE e.success) AS successes,
               avg(e.success::INTEGER) AS success_rate, avg(e.episode_return) AS mean_return,
               avg(e.num_steps) AS mean_length
        FROM episodes e LEFT JOIN task_families t USING (campaign, task_id)
        GROUP BY ALL""",
    "filter_pass_rates": f"""
        SELECT campaign, iteration, reason, count(*) AS episodes,
               count(*) / sum(count(*)) OVER (PARTITION BY campaign, iteration) AS fraction
        FROM {CURRENT_FILTER_DECISIONS} GROUP BY campaign, iteration, reason""",
    "dataset_composition": f"""
        SELECT e.campaign, e.iteration, t.family, e.task_id, e.explorer,
               count(*) AS episodes, count(*) FILTER (WHERE f.kept) AS kept_episodes,
               sum(e.num_steps) AS triplets, coalesce(sum(e.num_steps) FILTER (WHERE f.kept), 0) AS kept_triplets
        FROM episodes e
        LEFT JOIN task_families t USING (campaign, task_id)
        LEFT JOIN {CURRENT_FILTER_DECISIONS} f USING (episode_id)
        GROUP BY ALL""",
}
