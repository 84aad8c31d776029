"""One module per stage: plain typed functions, no Prefect inside. Each unit of work is keyed
(schemas.keys.unit_key), skipped when registered, and registered atomically when done."""
