"""Arrow schemas of the Parquet tables and DDL of the catalog's own tables.

Layout version: schemas.version.SCHEMA_VERSION, stamped into every shard's metadata.
Big, append-only data (episodes, steps, filter decisions, instruction embeddings) lives in
immutable Parquet shards; small bookkeeping tables live inside the DuckDB catalog file.
"""

from __future__ import annotations

import pyarrow as pa

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
    ]
)

# One row per transition (o_t, l, a_t, o_{t+1}). o_{t+1} is the next row's `image`; the last
# step of an episode carries it in `next_image`. The `triplets` view joins them.
STEPS = pa.schema(
    [
        ("campaign", pa.string()),
        ("iteration", pa.int32()),
        ("episode_id", pa.string()),
        ("task_id", pa.string()),
        ("step", pa.int32()),
        ("instruction", pa.string()),
        ("image", pa.binary()),  # PNG, RGB, image_size x image_size, upright
        ("proprio", pa.list_(pa.float32())),
        ("action", pa.list_(pa.float32())),
        ("reward", pa.float32()),
        ("done", pa.bool_()),
        ("success", pa.bool_()),
        ("next_image", pa.binary()),
        ("qpos", pa.list_(pa.float64())),  # MuJoCo state, for replay and re-rendering
        ("qvel", pa.list_(pa.float64())),
        ("sim_time", pa.float64()),
    ]
)

FILTER_DECISIONS = pa.schema(
    [
        ("campaign", pa.string()),
        ("iteration", pa.int32()),
        ("episode_id", pa.string()),
        ("task_id", pa.string()),
        ("kept", pa.bool_()),
        ("reason", pa.string()),  # "kept", "low_return", "not_successful", "env_error"
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

CATALOG_DDL = """
CREATE TABLE IF NOT EXISTS catalog_meta (key VARCHAR PRIMARY KEY, value VARCHAR);
CREATE TABLE IF NOT EXISTS stage_runs (
    unit_key VARCHAR PRIMARY KEY, stage VARCHAR, campaign VARCHAR, iteration INTEGER,
    finished_at TIMESTAMP, wall_s DOUBLE, summary JSON);
CREATE TABLE IF NOT EXISTS shards (
    path VARCHAR PRIMARY KEY, table_name VARCHAR, unit_key VARCHAR, campaign VARCHAR, iteration INTEGER,
    num_rows BIGINT, num_bytes BIGINT, sha256 VARCHAR, schema_version INTEGER);
CREATE TABLE IF NOT EXISTS tasks (
    campaign VARCHAR, task_id VARCHAR, spec VARCHAR, family VARCHAR, env_name VARCHAR, instruction VARCHAR,
    instructions VARCHAR[], unseen_instructions VARCHAR[], object_colours JSON, split VARCHAR, horizon INTEGER,
    unit_key VARCHAR,
    PRIMARY KEY (unit_key, task_id));
CREATE TABLE IF NOT EXISTS iterations (
    unit_key VARCHAR PRIMARY KEY, campaign VARCHAR, iteration INTEGER, dataset_digest VARCHAR,
    explore_units VARCHAR[], filter_units VARCHAR[], episodes BIGINT, kept_episodes BIGINT, triplets BIGINT);
CREATE TABLE IF NOT EXISTS models (
    model_key VARCHAR PRIMARY KEY, campaign VARCHAR, iteration INTEGER, checkpoint_path VARCHAR,
    dataset_digest VARCHAR, train_samples BIGINT, final_loss DOUBLE, unit_key VARCHAR);
CREATE TABLE IF NOT EXISTS deployments (
    unit_key VARCHAR PRIMARY KEY, model_key VARCHAR, campaign VARCHAR, iteration INTEGER,
    registered_model VARCHAR, version INTEGER, alias VARCHAR, champion_version INTEGER,
    champion_model_key VARCHAR, mlflow_run_id VARCHAR);
CREATE TABLE IF NOT EXISTS evaluations (
    unit_key VARCHAR PRIMARY KEY, campaign VARCHAR, iteration INTEGER, model_key VARCHAR, task_id VARCHAR,
    split VARCHAR, instruction VARCHAR, episodes INTEGER, successes INTEGER, success_rate DOUBLE, mean_return DOUBLE,
    mean_length DOUBLE, media_path VARCHAR);
"""

# Views built over the tables above once shards are registered (see warehouse.catalog).
DERIVED_VIEWS = {
    "triplets": """
        SELECT s.campaign, s.iteration, s.episode_id, s.task_id, s.step, s.instruction,
               s.image AS obs, s.action, s.reward, s.done, s.success,
               COALESCE(n.image, s.next_image) AS next_obs
        FROM steps s LEFT JOIN steps n ON n.episode_id = s.episode_id AND n.step = s.step + 1""",
    "kept_steps": """
        SELECT s.* FROM steps s
        JOIN filter_decisions f ON f.episode_id = s.episode_id AND f.kept""",
}
