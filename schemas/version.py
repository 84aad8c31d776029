"""Version of the warehouse layout and of every table schema; written into each shard's metadata.

2: episodes.randomisation (per-episode domain randomisation); tasks.unseen_instructions and
   evaluations.instruction (held-out paraphrases).
"""

SCHEMA_VERSION = 2
