"""Shards on a real S3 server (SeaweedFS on loopback, tests/s3.py): written by the same writer, registered
by the same catalog, read by DuckDB (httpfs) and pyarrow, verified, quarantined and cleaned where they
live; the warehouse folder holds only the catalog. Then the settings' refusals, which need no server."""

from __future__ import annotations

import duckdb
import pytest

from schemas.workspace import Workspace
from tests.s3 import s3_server
from tests.warehouse.filled import fill
from warehouse.catalog import Catalog
from warehouse.shard_writer import ShardConflict, write_shard
from warehouse.sql import run_sql
from warehouse.store import FOLDER, SHARD_STORE_ENV, ShardStoreError, ShardStoreRefused, canonical_url, open_store
from warehouse.training_reader import StepBatches, select_rows

COUNTS = ("SELECT (SELECT count(*) FROM steps), (SELECT count(*) FROM episodes), "
          "(SELECT count(*) FILTER (WHERE kept) FROM filter_decisions), (SELECT count(*) FROM kept_steps)")


@pytest.fixture(scope="module")
def s3():
    with s3_server(("shards",)) as server:
        yield server


def _filled(root, environ: dict[str, str], monkeypatch) -> Workspace:
    for name, value in environ.items():
        monkeypatch.setenv(name, value)
    workspace = Workspace.at(root).create()
    fill(workspace, iterations=2, units=2, episodes=2, steps=6)
    return workspace


def _batches(ranges, store) -> list[tuple]:
    batches = StepBatches(ranges, 4, 8, seed=0, epochs=1, store=store, collate=lambda rows: {"rows": rows})
    return sorted((row["instruction"], tuple(row["action"])) for batch in batches for row in batch["rows"])


def _answers(catalog: Catalog) -> tuple:
    """What a folder's warehouse and an S3 one must agree on."""
    ranges = select_rows(catalog, "success")
    return (catalog.query(COUNTS), catalog.query(COUNTS, as_of_iteration=0),
            run_sql(catalog, "SELECT count(*) AS n FROM steps", "csv"), [(r.start, r.stop) for r in ranges],
            _batches(ranges, catalog.store))


def test_a_warehouse_on_s3_answers_as_one_in_its_folder(s3, tmp_path, monkeypatch):
    local = Catalog(_filled(tmp_path / "folder", {}, monkeypatch).catalog)
    assert local.store.url == FOLDER
    expected = _answers(local)
    on_s3 = _filled(tmp_path / "s3", s3.environ("s3://shards/lab/one"), monkeypatch)
    catalog = Catalog(on_s3.catalog)
    assert catalog.store.url == "s3://shards/lab/one"
    # the shards are objects under the prefix, the same names as in a folder; the folder holds the catalog only
    registered = [path for (path,) in catalog.query("SELECT path FROM shards ORDER BY path")]
    assert registered and s3.keys("shards") == sorted([f"lab/one/{path}" for path in registered]
                                                      + ["lab/one/sim2act-warehouse.json"])  # and the prefix's claim
    assert [p.name for p in on_s3.warehouse.rglob("*") if p.is_file()] == ["catalog.duckdb"]
    # the same counts, snapshot, sim2act sql answer, selection and training rows
    assert _answers(catalog) == expected and expected[0][0][0] > 0
    assert all(r.path.startswith("s3://shards/lab/one/shards/steps/") for r in select_rows(catalog, "success"))
    # sim2act sql's confined connection reads the prefix and nothing else
    for sql in ("SELECT * FROM read_csv('/etc/passwd')", "SELECT * FROM read_parquet('s3://shards/lab/other/x.parquet')"):
        with pytest.raises(duckdb.Error, match="file system operations are disabled"):
            run_sql(catalog, sql)
    # compacted on S3: the objects replaced by a few, the same answers
    from warehouse.compaction import compact

    assert compact(catalog).files == 6
    assert len([key for key in s3.keys("shards") if "/shards/" in key]) == 6 and _answers(catalog) == expected
    assert catalog.verify(full=True) == [] and catalog.clean_orphans() == []


def test_verify_quarantines_and_clean_orphans_deletes_objects_on_s3(s3, tmp_path, monkeypatch):
    workspace = _filled(tmp_path, s3.environ("s3://shards/lab/two"), monkeypatch)
    catalog = Catalog(workspace.catalog)
    fs, root = s3.filesystem(), "shards/lab/two"
    [(bad, unit)] = catalog.query("SELECT path, unit_key FROM shards WHERE table_name = 'steps' ORDER BY path LIMIT 1")
    with fs.open_output_stream(f"{root}/{bad}") as out:  # bit rot: the same name, other bytes
        out.write(b"not parquet at all")
    stray = "shards/steps/iteration=0/killed-mid-unit.parquet"
    with fs.open_output_stream(f"{root}/{stray}") as out:  # an unregistered leftover
        out.write(b"half")
    found = catalog.verify(full=True)
    assert [path for path, _ in found] == [bad] and "not a readable Parquet file" in found[0][1]
    assert catalog.query("SELECT count(*) FROM shards WHERE unit_key = ?", [unit]) == [(0,)]
    keys = s3.keys("shards")
    assert f"lab/two/quarantine/{bad}" in keys and f"lab/two/{bad}" not in keys
    assert catalog.query("SELECT count(*) FROM steps")[0][0] > 0  # the views hold the other shards
    # a compacted file's upload killed midway: parts up, never completed (no listing shows it)
    import boto3

    client = boto3.client("s3", endpoint_url=s3.endpoint, aws_access_key_id=s3.access_key,
                          aws_secret_access_key=s3.secret_key, region_name="us-east-1")
    killed_upload = "shards/steps/iteration=1/compacted-0123456789abcdef.parquet"
    upload = client.create_multipart_upload(Bucket="shards", Key=f"lab/two/{killed_upload}")
    client.upload_part(Bucket="shards", Key=f"lab/two/{killed_upload}", UploadId=upload["UploadId"], PartNumber=1,
                       Body=b"x" * (5 << 20))
    assert catalog.clean_orphans() == [workspace.warehouse / stray, workspace.warehouse / killed_upload]
    assert f"lab/two/{stray}" not in s3.keys("shards")
    assert not client.list_multipart_uploads(Bucket="shards", Prefix="lab/two/").get("Uploads")
    assert catalog.clean_orphans() == []
    # a unit computed twice keeps the object when the bytes agree, and refuses other bytes
    [(path,)] = catalog.query("SELECT path FROM shards WHERE table_name = 'filter_decisions' ORDER BY path LIMIT 1")
    again = catalog.query_arrow(f"SELECT * FROM read_parquet('{catalog.store.location(path)}')")
    from warehouse.shard_writer import read_shard

    same = read_shard("filter_decisions", workspace.warehouse / path, store=catalog.store)
    assert write_shard("filter_decisions", same, workspace.warehouse / path, catalog.store).sha256 == \
        catalog.query("SELECT sha256 FROM shards WHERE path = ?", [path])[0][0]
    with pytest.raises(ShardConflict, match="exists with other content"):
        write_shard("filter_decisions", same.slice(1), workspace.warehouse / path, catalog.store)
    assert again.num_rows == same.num_rows


def test_a_refused_key_is_one_line_and_quarantines_nothing(s3, tmp_path, monkeypatch):
    """A wrong (rotated, expired) secret or a skewed clock makes S3 refuse every request (403): that is the store's
    answer, not a bad shard; verify stops on it in one line, and every unit stays registered."""
    workspace = _filled(tmp_path, s3.environ("s3://shards/lab/refused"), monkeypatch)
    registered = Catalog(workspace.catalog).query("SELECT count(*) FROM shards")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "a-rotated-secret")
    catalog = Catalog(workspace.catalog)
    with pytest.raises(ShardStoreRefused, match=r"refused the request .*AWS_SECRET_ACCESS_KEY.*nothing was changed"):
        catalog.verify(full=True)
    assert Catalog(workspace.catalog).query("SELECT count(*) FROM shards") == registered
    assert not [key for key in s3.keys("shards") if key.startswith("lab/refused/quarantine/")]


def test_store_settings_are_refused_in_one_line(tmp_path):
    assert canonical_url("s3://bucket/a/b/") == "s3://bucket/a/b" and canonical_url("") == FOLDER
    with pytest.raises(ShardStoreError, match=r"expected s3://bucket/prefix .*got 'gs://x/y'"):
        canonical_url("gs://x/y")
    with pytest.raises(ShardStoreError, match="set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY"):
        open_store(tmp_path, None, {SHARD_STORE_ENV: "s3://b/p"})
    keys = {"AWS_ACCESS_KEY_ID": "k", "AWS_SECRET_ACCESS_KEY": "s"}
    with pytest.raises(ShardStoreError, match=r"expected folder \(where the warehouse at .* keeps its shards\), got s3://b/p"):
        open_store(tmp_path, FOLDER, {SHARD_STORE_ENV: "s3://b/p", **keys})
    with pytest.raises(ShardStoreError, match="expected s3://b/p .*got s3://b/q"):
        open_store(tmp_path, "s3://b/p", {SHARD_STORE_ENV: "s3://b/q/", **keys})
    with pytest.raises(ShardStoreError, match="AWS_ENDPOINT_URL: expected http"):
        open_store(tmp_path, None, {SHARD_STORE_ENV: "s3://b/p", "AWS_ENDPOINT_URL": "127.0.0.1:9000", **keys})
    # credentials in a URL that is logged and said in errors: refused, never shown
    with pytest.raises(ShardStoreError, match=r"without credentials .*got s3://lab:\*\*\*@b/p$") as error:
        open_store(tmp_path, None, {SHARD_STORE_ENV: "s3://lab:hunter2@b/p", **keys})
    assert "hunter2" not in str(error.value)
    with pytest.raises(ShardStoreError, match=r"AWS_ENDPOINT_URL: .*got 'http://lab:\*\*\*@127.0.0.1:9000'$") as error:
        open_store(tmp_path, None, {SHARD_STORE_ENV: "s3://b/p", "AWS_ENDPOINT_URL": "http://lab:hunter2@127.0.0.1:9000", **keys})
    assert "hunter2" not in str(error.value)
    assert open_store(tmp_path, "s3://b/p", keys).url == "s3://b/p"  # the recorded store, the keys from the environment
    # temporary keys (STS, SSO) come with a session token: every client signs with it
    temporary = open_store(tmp_path, "s3://b/p", {**keys, "AWS_SESSION_TOKEN": "a-session-token"})
    assert temporary.filesystem.__reduce__()[1][0]["session_token"] == "a-session-token"
    with duckdb.connect() as con:
        temporary.prepare(con)
        [(secret,)] = con.execute("SELECT secret_string FROM duckdb_secrets()").fetchall()  # values redacted
        assert "session_token=redacted" in secret
    # a catalog made before stores existed keeps its shards in its folder, whatever the variable says
    workspace = Workspace.at(tmp_path / "old").create()
    Catalog(workspace.catalog).initialise()
    with duckdb.connect(str(workspace.catalog)) as con:
        con.execute("DELETE FROM catalog_meta WHERE key = 'shard_store'")
    from warehouse import catalog as catalog_module

    catalog_module._RECORDED_STORES.clear()
    assert Catalog(workspace.catalog).store.url == FOLDER


def test_a_store_that_restarts_is_waited_for_and_one_that_stays_down_is_one_line(s3, tmp_path, monkeypatch):
    import hashlib
    import threading
    import time

    import pyarrow as pa

    from tests.s3 import start, stop
    from warehouse import store as store_module
    from warehouse.store import ShardStoreUnreachable

    workspace = _filled(tmp_path / "ws", s3.environ("s3://shards/down"), monkeypatch)  # to verify while it is down
    catalog = Catalog(workspace.catalog)
    store = open_store(tmp_path, None, s3.environ("s3://shards/blip"))
    data = b"a shard's bytes" * 100
    stop(s3)  # killed; back in 3 s on the same ports and data
    threading.Timer(3.0, start, [s3]).start()
    began = time.monotonic()
    store.put_new("shards/a.bin", pa.py_buffer(data), hashlib.sha256(data).hexdigest())
    assert 2.5 < time.monotonic() - began < store_module.STORE_WAIT_S
    assert store.exists("shards/a.bin") and store.sha256("shards/a.bin") == hashlib.sha256(data).hexdigest()
    # a training's ranged read of an opened shard (its row groups, read as its batches need them) waits the same
    [(path,)] = catalog.query("SELECT path FROM shards WHERE table_name = 'steps' ORDER BY path LIMIT 1")
    parquet = catalog.store.parquet(catalog.store.location(path))
    stop(s3)
    threading.Timer(3.0, start, [s3]).start()
    began = time.monotonic()
    assert catalog.store.patiently(lambda: parquet.read_row_group(0)).num_rows > 0
    assert 2.5 < time.monotonic() - began < store_module.STORE_WAIT_S
    monkeypatch.setattr(store_module, "STORE_WAIT_S", 2.0)
    stop(s3)
    registered = catalog.query("SELECT count(*) FROM shards")
    try:
        with pytest.raises(ShardStoreUnreachable, match=r"^the shard store s3://shards/blip \(127\.0\.0\.1:\d+\) did not "
                           r"answer for 2 s \(.*Could not connect to server\): start it, then run the same command "
                           r"again to resume$"):
            store.exists("shards/a.bin")
        with pytest.raises(ShardStoreUnreachable):  # the server is down, not the shards: nothing quarantined
            catalog.verify()
    finally:
        start(s3)
        monkeypatch.setattr(store_module, "STORE_WAIT_S", 60.0)  # its patience back
    assert catalog.query("SELECT count(*) FROM shards") == registered and catalog.verify() == []


def test_a_second_warehouse_on_the_same_prefix_is_refused_before_it_writes(s3, tmp_path, monkeypatch):
    first = _filled(tmp_path / "first", s3.environ("s3://shards/shared"), monkeypatch)
    objects = s3.keys("shards")
    second = Workspace.at(tmp_path / "second").create()
    with pytest.raises(ShardStoreError, match=rf"^s3://shards/shared keeps the shards of another warehouse \(catalog "
                       rf"{first.catalog.resolve()} on .*\): give this workspace its own prefix in SIM2ACT_SHARD_STORE$"):
        Catalog(second.catalog).initialise()
    assert not second.catalog.exists() and s3.keys("shards") == objects  # nothing written, nothing cleaned
    Catalog(first.catalog).initialise()  # its owner opens it again as before
    assert Catalog(first.catalog).clean_orphans() == [] and s3.keys("shards") == objects


def test_a_checkpoint_is_cached_per_server_not_per_name_alone(s3, tmp_path, monkeypatch):
    """Two S3 servers may each hold a bucket and prefix of the same name (a lab's and a laptop's): a checkpoint
    fetched from one was handed out for the other's location from the host's cache."""
    monkeypatch.setenv("SIM2ACT_CACHE_DIR", str(tmp_path / "cache"))
    environ = s3.environ("s3://shards/lab/cached")
    here = open_store(tmp_path, "s3://shards/lab/cached", environ)
    fs, key = s3.filesystem(), "shards/lab/cached/models/train-x/policy.pt"
    with fs.open_output_stream(key) as out:
        out.write(b"this server's weights")
    location = here.location("models/train-x/policy.pt")
    assert here.fetch(location).read_bytes() == b"this server's weights"
    with fs.open_output_stream(key) as out:  # the same name on "another" server: the same one, reached by another name
        out.write(b"another server's weights")
    other = open_store(tmp_path, "s3://shards/lab/cached", {**environ, "AWS_ENDPOINT_URL": s3.endpoint.replace("127.0.0.1", "localhost")})
    assert other.fetch(location).read_bytes() == b"another server's weights"
    assert here.fetch(location).read_bytes() == b"this server's weights"  # each server's copy cached once, by server
