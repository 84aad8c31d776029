"""Version of the warehouse layout and of every table schema; written into each shard's metadata."""

SCHEMA_VERSION = 1
