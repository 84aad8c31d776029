"""Version of the warehouse layout and of every table schema; written into each shard's metadata.

2: episodes.randomisation (per-episode domain randomisation); tasks.unseen_instructions and
   evaluations.instruction (held-out paraphrases).
3: every catalog table declared as an Arrow schema; steps.act and steps.mocap (MuJoCo state for
   replay); filter_decisions.detail; the quarantine table.
"""

SCHEMA_VERSION = 3
