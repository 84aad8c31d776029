"""Failure drills (issue 8) through the real CLI: a disk that fills while a campaign writes its
shards, and a corrupt shard in a finished warehouse. Real processes, real files, a real tmpfs;
each drill ends with exactly the reference campaign's rows.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

from schemas.workspace import Workspace
from tests.campaign import iteration_zero_snapshot, run_campaign, snapshot
from tests.conftest import SIM2ACT, sim2act_env
from warehouse.catalog import Catalog

# A drill runs up to two campaigns beside the shared fixture's, which this file pays alone (`pytest
# tests/flows/test_drills.py`): ~10 minutes in all on 2 loaded cores, 20 at worst.
pytestmark = pytest.mark.timeout(1800)


def _sim2act(prefect_api: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([SIM2ACT, *args], env=sim2act_env(prefect_api), capture_output=True, text=True, timeout=600)


def _mount(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["mount", *args], capture_output=True, text=True)


def test_a_full_disk_stops_the_run_in_one_line_and_the_next_run_resumes(finished_campaign, tmp_path, prefect_api):
    """The shards folder is a 512 KiB tmpfs: iteration 0's explore shards (~130 KB a unit) fill it
    after three or four units. The run stops with one line naming the shard and what to do,
    registers nothing partial; with room again, the same command resumes at the unit that failed and
    ends iteration 0 with the reference's rows, shard bytes, dataset and model."""
    ws = Workspace.at(tmp_path / "full").create()
    mounted = _mount("-t", "tmpfs", "-o", "size=512k", "tmpfs", str(ws.shards))
    if mounted.returncode != 0:
        # as the browser fixture: a drill that cannot run fails, so a green suite means it ran
        pytest.fail(f"cannot mount a tmpfs (run the suite as root or with CAP_SYS_ADMIN): {mounted.stderr.strip()}")
    try:
        full = _sim2act(prefect_api, "run", "--preset", "smoke", "--workspace", str(ws.root))
        assert full.returncode != 0
        last = full.stderr.rstrip().splitlines()[-1]
        said = re.fullmatch(r"sim2act: no space left on device writing the (?:steps|episodes) shard of unit "
                            r"(explore-[0-9a-f]+) \(.+\.parquet\); the unit is not registered: free space on that "
                            r"disk, then run the same command again to resume at the first unfinished unit", last)
        assert said, full.stderr[-3000:]
        catalog = Catalog(ws.catalog)
        [(explored, steps_rows)] = catalog.query(
            "SELECT count(*), sum(json_extract(summary, '$.steps')::INT) FROM stage_runs WHERE stage = 'explore'")
        assert 0 < explored < 6 and not catalog.is_registered(said.group(1))  # stopped partway, its unit unregistered
        # every registered shard is whole and named by its final path; the views read exactly them
        assert catalog.verify(full=True) == []
        assert all(not Path(path).name.startswith(".") for (path,) in catalog.query("SELECT path FROM shards"))
        assert catalog.query("SELECT count(*) FROM steps") == [(steps_rows,)]

        grown = _mount("-o", "remount,size=200m", str(ws.shards))
        assert grown.returncode == 0, grown.stderr
        # the same command resumes; iteration 0 is enough to show it (the other drills run iteration 1 too)
        resumed = _sim2act(prefect_api, "run", "--preset", "smoke", "--workspace", str(ws.root), "--set", "iterations=1")
        assert resumed.returncode == 0, resumed.stderr[-3000:]
        assert re.search(rf"explore it0: 6 shards \({explored} already registered\)", resumed.stderr), \
            resumed.stderr[-3000:]
        assert iteration_zero_snapshot(ws.root) == iteration_zero_snapshot(finished_campaign[0])
        assert catalog.verify(full=True) == []
    finally:
        subprocess.run(["umount", "--lazy", str(ws.shards)], capture_output=True)  # detached even if a run holds it


def test_a_corrupt_shard_is_quarantined_by_a_query_and_by_verify_and_the_next_run_redoes_it(
        finished_campaign, tmp_path, prefect_api):
    """Two steps shards go bad in a copy of the finished campaign: one with bytes overwritten
    inside a data page (its footer whole: found by the query that reads the page), one truncated
    (found by `sim2act warehouse verify`). Queries keep working, each bad shard is quarantined
    with a line naming it, and the next run redoes both units to the reference's rows."""
    reference = finished_campaign[0]
    ws = Workspace.at(tmp_path / "corrupt")
    shutil.copytree(reference, ws.root)
    catalog = Catalog(ws.catalog)
    [(paged, paged_rows)] = catalog.query(
        "SELECT path, num_rows FROM shards WHERE table_name = 'steps' AND iteration = 0 ORDER BY path LIMIT 1")
    [(truncated,)] = catalog.query(  # a unit the champion explored too: its redo must roll the policy out the same
        "SELECT DISTINCT s.path FROM shards s JOIN episodes e ON e.shard_key = s.unit_key WHERE s.table_name = 'steps' "
        "AND s.iteration = 1 AND e.explorer LIKE 'policy:%' ORDER BY 1 LIMIT 1")
    [(episodes, steps)] = catalog.query("SELECT (SELECT count(*) FROM episodes), (SELECT count(*) FROM steps)")

    page = ws.warehouse / paged
    data = bytearray(page.read_bytes())
    data[len(data) // 2: len(data) // 2 + 4096] = b"\xff" * 4096
    page.write_bytes(bytes(data))
    counted = _sim2act(prefect_api, "sql", "--workspace", str(ws.root), "--format", "csv",
                       "SELECT count(*) AS n FROM episodes")
    assert counted.returncode == 0 and counted.stdout.split() == ["n", str(episodes)], counted.stderr
    read = _sim2act(prefect_api, "sql", "--workspace", str(ws.root), "--format", "csv",
                    "SELECT count(*) AS n, count(*) FILTER (WHERE octet_length(image) > 0) AS framed FROM steps")
    assert read.returncode == 0, read.stderr
    assert read.stdout.split() == ["n,framed", f"{steps - paged_rows},{steps - paged_rows}"]
    assert re.search(rf"^quarantined {re.escape(paged)} \(.*{re.escape(paged)}.*\); the query ran without it$",
                     read.stderr, re.MULTILINE), read.stderr
    assert not page.exists() and (catalog.quarantine_folder / paged).exists()

    cut = ws.warehouse / truncated
    cut.write_bytes(cut.read_bytes()[: cut.stat().st_size // 2])
    verified = _sim2act(prefect_api, "warehouse", "verify", "--workspace", str(ws.root))
    assert verified.returncode == 1, verified.stderr
    [quarantined, summary] = verified.stdout.splitlines()
    assert quarantined.startswith(f"quarantined {truncated}: {cut}: not a readable Parquet file ("), quarantined
    [(left,)] = catalog.query("SELECT count(*) FROM shards")
    assert summary == (f"{left} registered file(s) verified, 1 quarantined to {catalog.quarantine_folder}; "
                       "the next `sim2act run` redoes their units")
    assert catalog.query("SELECT count(*) FROM quarantine") == [(4,)]  # each bad steps shard and its episodes sibling

    output, _ = run_campaign(ws.root, prefect_api)
    assert "explore it0: 6 shards (5 already registered)" in output and "explore it1: 6 shards (5 already registered)" \
        in output, output[-3000:]
    assert snapshot(ws.root) == snapshot(reference)
    assert catalog.verify(full=True) == []
