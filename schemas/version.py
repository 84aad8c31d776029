"""Version of the warehouse layout and of every table schema; written into each shard's metadata.

2: episodes.randomisation (per-episode domain randomisation); tasks.unseen_instructions and
   evaluations.instruction (held-out paraphrases).
3: every catalog table declared as an Arrow schema; steps.act and steps.mocap (MuJoCo state for
   replay); filter_decisions.detail; the quarantine table.
4: episodes.render (the visual settings each episode was rendered with, for replay and
   evaluation); episodes.explorer_stats (the expert's noise level; a VLM's calls, retries,
   timeouts, invalid answers); steps.expert_action (DAgger labels: the expert's noiseless action at each state).
5: evaluations.uncertainty (the policy's mean per-step uncertainty on the task); deployments.promoted
   and deployments.decision (the alias moves only when the evaluation says the new model is better).

6: steps.depth and steps.next_depth (depth maps, where the campaign's render.depth records them);
   episodes.render.depth; evaluations.suite (the flow's, or `sim2act eval`'s task set), family,
   ci_low, ci_high (Wilson 95%), episode_lengths, episode_successes, success_video and
   failure_video (MP4s; were media_path, a GIF).
7: evaluations.episode_achieved (per episode, the task the agent ended doing: the evaluated one, another
   goal of the same scene, or none). A layout-6 catalog is brought to 7 in place (MIGRATIONS): no shard
   table changed, so its shards stay as they are.
8: shards.view_part (the catalog's shard views in parts of at most VIEW_PART_SHARDS files: a
   registration rewrites one part, not a view naming every shard). Brought in place from 7; the
   next command that writes assigns the existing shards their parts.
9: shards.stored_in and shards.row_offset, and the `compacted` table (`sim2act compact` concatenates a
   finished iteration's small shards into large files; the shards' rows say where their rows went).
   Brought in place from 8: no shard moves until a compaction.
10: stage_runs and shards without their PRIMARY KEYs: DuckDB rewrote each key's index at every checkpoint,
   ~30 ms more per registration at 20,000 shards (docs/bench-warehouse.md). Registration refuses a registered
   unit inside its own transaction, and a shard's path names its unit, so neither key caught anything.
   Brought in place from 9: the two tables rebuilt (DuckDB cannot drop a key), their rows kept.
"""

SCHEMA_VERSION = 10
# layout -> (catalog table, column) added to bring a catalog of that layout to the next, in place;
# the column's type is the one schemas/tables.py declares (the last of its table: ALTER TABLE appends); a
# table a layout adds is created whole (Catalog._migrate)
MIGRATIONS: dict[int, list[tuple[str, str]]] = {
    6: [("evaluations", "episode_achieved")],
    7: [("shards", "view_part")],
    8: [("shards", "stored_in"), ("shards", "row_offset")],
    9: [],
}
# layout -> catalog tables rebuilt whole to bring a catalog of that layout to the next (a table's key
# changed: DuckDB can neither add nor drop one in place)
REBUILT: dict[int, tuple[str, ...]] = {
    9: ("stage_runs", "shards"),
}
