"""Shard writer, DuckDB catalog (the single point of truth), SQL access and the training reader."""
