"""`sim2act bench warehouse` measures every figure side by side with its reference."""

import json

import pytest

from flows.cli import main


def test_bench_warehouse_reports_each_measure_with_its_reference(tmp_path, capsys):
    assert main(["bench", "warehouse", "--quick", "--json", "--scratch", str(tmp_path)]) == 0
    measures = {m["name"]: m for m in json.loads(capsys.readouterr().out)}
    ingest = measures["ingest: shard writer"]
    assert ingest["value"] > 0 and ingest["reference"] > 0
    assert ingest["ratio"] == pytest.approx(ingest["value"] / ingest["reference"])
    assert 100 < measures["bytes per triplet on disk"]["value"] < 20_000
    sql = measures["SQL: success per task over 20,000 steps"]
    assert sql["unit"] == "ms" and sql["value"] > 0 and sql["reference"] > 0
    compacted = measures["SQL: success per task over 20,000 steps, compacted"]
    assert compacted["reference"] == sql["reference"] and "40 shards into 2 files" in compacted["note"]  # steps, episodes
    tasks = measures["SQL: task_success over 20,000 steps, compacted"]
    assert tasks["value"] > 0 and tasks["ratio"] == pytest.approx(tasks["reference"] / tasks["value"])
    reads = measures["training reads: DataLoader over the warehouse"]
    assert reads["value"] > 0 and reads["reference"] > reads["value"]  # nothing beats frames already in memory
    registration = measures["registration: unit 200 (after 199)"]
    assert registration["value"] > 0 and registration["reference"] > 0
    assert "418 shards registered" in registration["note"]  # (10 timed + 189 in bulk + 10 timed) units x 2 shards
    after = measures["registration: unit 211, its iteration 0 compacted"]
    assert after["value"] > 0 and after["reference"] == registration["reference"]
    assert list(tmp_path.iterdir()) == []  # the throwaway warehouses are gone


def test_bench_warehouse_refuses_bad_sizes(capsys):
    assert main(["bench", "warehouse", "--sql-steps", "0"]) == 2
    assert "--sql-steps must be positive" in capsys.readouterr().err
