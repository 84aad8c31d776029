"""Where shard files live: the warehouse folder (the default) or a prefix of an S3 bucket.

The catalog names every shard by its path relative to the warehouse folder
(`shards/steps/iteration=0/<unit>.parquet`); a store maps that name to the file or the object that
holds it, for pyarrow (writes, footers, reads) and for DuckDB (the views' `read_parquet`). The
catalog file itself stays a DuckDB file in the workspace of the host that registers units (the
flow's); only shards move. A warehouse records its store when it is created, and a command told
another one is refused: a warehouse never has shards in two places.

S3: `SIM2ACT_SHARD_STORE=s3://bucket/prefix`, with the variables every S3 client reads
(`AWS_ENDPOINT_URL` for a server other than AWS, `AWS_ACCESS_KEY_ID`, `AWS_SECRET_ACCESS_KEY`,
`AWS_SESSION_TOKEN` with temporary keys, `AWS_REGION`), from the environment or the secrets file (schemas.settings), never a config.
An object is whole once written (S3 has no partial objects), so the temporary name the folder store
needs is not needed there; the registrar checks every shard's bytes before it registers the unit.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import threading
import uuid
from abc import ABC, abstractmethod
from collections.abc import Mapping
from pathlib import Path
from urllib.parse import urlsplit

import duckdb
import pyarrow as pa

from schemas.errors import Sim2ActError
from schemas.retry import retrying
from schemas.settings import cache_dir, redacted

SHARD_STORE_ENV = "SIM2ACT_SHARD_STORE"
FOLDER = "folder"  # the recorded name of the default store: the warehouse folder itself
_DUCKDB_SECRET = "sim2act_shard_store"
CLAIM = "sim2act-warehouse.json"  # at an S3 prefix: which catalog's shards live under it
# An S3 server that does not answer (restarting, a network blip) is waited for this long, trying again
# with backoff, then the command stops with one line; every unit is keyed, so the same command resumes.
STORE_WAIT_S = 60.0
# DuckDB's own reads of the views' objects: httpfs tries again 8 times, 0.5 s apart growing 1.5x (~25 s)
_HTTPFS_RETRIES = {"http_retries": 8, "http_retry_wait_ms": 500, "http_retry_backoff": 1.5}
log = logging.getLogger("sim2act.warehouse")
_PREPARING = threading.Lock()


class ShardStoreError(Sim2ActError, ValueError):
    """A store setting that cannot be used; one line naming the variable and what was expected."""


class ShardConflict(FileExistsError):
    """Another writer already put different bytes at this shard's path."""


class ShardStoreUnreachable(Sim2ActError, OSError):
    """The S3 server did not answer for STORE_WAIT_S; one line naming it and how to resume."""


class ShardStoreRefused(Sim2ActError, PermissionError):
    """The store refused a read or write (credentials, clock, permissions): not a bad shard, never quarantined."""


# S3's refusals of a request (not of a key: NoSuchKey is a missing shard): a wrong, expired or temporary key
# without its token, a signature made by a clock over 15 minutes off
_REFUSALS = ("ACCESS_DENIED", "AccessDenied", "InvalidAccessKeyId", "SignatureDoesNotMatch", "RequestTimeTooSkewed",
             "ExpiredToken", "InvalidToken", "HTTP response code: 403")


def _refused(exc: BaseException) -> bool:
    return isinstance(exc, PermissionError) or (isinstance(exc, OSError) and any(s in str(exc) for s in _REFUSALS))


def _unreachable(exc: BaseException) -> bool:
    """pyarrow's S3 client failing to reach the server (as opposed to a refusal: no such key, access denied)."""
    text = str(exc)
    return isinstance(exc, OSError) and any(sign in text for sign in (
        "NETWORK_CONNECTION", "curlCode", "SERVICE_UNAVAILABLE", "SLOW_DOWN", "INTERNAL_FAILURE"))


def sha256_of(handle: pa.NativeFile) -> str:
    digest = hashlib.sha256()
    for block in iter(lambda: handle.read(1 << 20), b""):
        digest.update(block)
    return digest.hexdigest()


class ShardStore(ABC):
    """A warehouse's shard files by their names relative to the warehouse folder (`rel`)."""

    url: str  # what the catalog records: FOLDER or s3://bucket/prefix

    def __init__(self, warehouse: Path):
        self.warehouse = warehouse

    def rel(self, path: Path | str) -> str:
        """The name of a shard given as a path under the warehouse folder (how workspaces spell them)."""
        path = Path(path)
        return (path.relative_to(self.warehouse) if path.is_absolute() else path).as_posix()

    @abstractmethod
    def location(self, rel: str) -> str:
        """What DuckDB's read_parquet reads for `rel` (and the training reader opens again)."""

    def view_location(self, rel: str) -> str:
        """What the catalog's views name for `rel`: its location (a folder's overrides it)."""
        return self.location(rel)

    def rel_of(self, location: str) -> str:
        """The shard name a location (as read_parquet's `filename` gives it) holds."""
        return self.rel(location)

    @abstractmethod
    def open(self, location: str) -> pa.NativeFile:
        """A random-access reader of a location; FileNotFoundError (an OSError) when there is none."""

    @abstractmethod
    def put_new(self, rel: str, data: pa.Buffer, sha: str) -> None:
        """`data` at `rel`, whole or not at all, never over other bytes (ShardConflict)."""

    @abstractmethod
    def exists(self, rel: str) -> bool: ...

    @abstractmethod
    def files(self, under: str) -> list[str]:
        """Every file's rel under the folder `under` (temporaries included)."""

    @abstractmethod
    def move(self, rel: str, to_rel: str) -> None: ...

    @abstractmethod
    def delete(self, rel: str) -> None: ...

    def read(self, rel: str) -> pa.NativeFile:
        return self.open(self.location(rel))

    def parquet(self, location: str):
        """A Parquet file at `location`, its footer read (row groups are read as asked for)."""
        import pyarrow.parquet as pq

        return pq.ParquetFile(self.open(location))

    def fetch(self, location: str) -> Path:
        """A local file holding `location` (a worker loads the champion's checkpoint from it)."""
        return Path(location)

    def patiently(self, action, *args):
        """`action(*args)`, a read of this store's files (a row group of an opened Parquet file): a folder's
        at once; S3Store's tried again while the server does not answer, as its own reads are."""
        return action(*args)

    def sha256(self, rel: str) -> str:
        with self.read(rel) as handle:
            return sha256_of(handle)

    def abort_uploads(self, under: str) -> list[str]:
        """Abort the unfinished uploads under the folder `under` -> their rels. A folder has none; see S3Store's."""
        return []

    def prepare(self, con: duckdb.DuckDBPyConnection) -> None:
        """Make `con` able to read this store's locations (nothing for a folder)."""

    def check_reachable(self) -> None:
        """Before a command's work: the store answers (a folder always does).

        Raises:
            ShardStoreUnreachable, ShardStoreRefused: it does not answer, or refuses the keys."""

    def claim(self, warehouse_id: str | None, catalog: Path) -> str:
        """Make sure no other warehouse keeps its shards here (a folder belongs to its catalog already).
        `warehouse_id`: the catalog's, None for a new one. Returns the id to record.

        Raises:
            ShardStoreError: another catalog claimed the place.
        """
        return warehouse_id or uuid.uuid4().hex

    def allowed(self) -> list[str]:
        """The prefixes a confined DuckDB connection may read (Catalog.connect)."""
        return [self.warehouse.resolve().as_posix() + "/"]


class FolderStore(ShardStore):
    """Shards as files in the warehouse folder: written to a temporary name, fsynced, then linked."""

    url = FOLDER

    def location(self, rel: str) -> str:
        return (self.warehouse / rel).as_posix()

    def view_location(self, rel: str) -> str:
        """The name relative to the warehouse folder, which every catalog connection searches
        (Catalog.connect): the views stay true when the workspace is copied or moved, for any DuckDB
        client opened in that folder or told it (`SET file_search_path`)."""
        return rel

    def open(self, location: str) -> pa.NativeFile:
        return pa.OSFile(location)

    def put_new(self, rel: str, data: pa.Buffer, sha: str) -> None:
        write_new_file(self.warehouse / rel, data, sha)

    def exists(self, rel: str) -> bool:
        return (self.warehouse / rel).is_file()

    def files(self, under: str) -> list[str]:
        root = self.warehouse / under
        return sorted(p.relative_to(self.warehouse).as_posix() for p in root.rglob("*") if p.is_file())

    def move(self, rel: str, to_rel: str) -> None:
        target = self.warehouse / to_rel
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.move(self.warehouse / rel, target)

    def delete(self, rel: str) -> None:
        (self.warehouse / rel).unlink(missing_ok=True)


def fsync_path(path: Path) -> None:
    """Flush a file's bytes, or a folder's entries (a rename in it), to the disk."""
    handle = os.open(path, os.O_RDONLY)
    try:
        os.fsync(handle)
    finally:
        os.close(handle)


def write_new_file(path: Path, data: pa.Buffer, sha: str) -> None:
    """`data` at `path` through a temporary file (fsynced, then linked): never partial, never over
    other bytes."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    try:
        with tmp.open("wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        try:
            os.link(tmp, path)  # atomic, and unlike rename it never replaces what is there
        except FileExistsError:
            with pa.OSFile(str(path)) as there:
                if sha256_of(there) != sha:
                    raise ShardConflict(f"{path} exists with other content; remove it if no catalog row names it")
    finally:
        tmp.unlink(missing_ok=True)


class S3Store(ShardStore):
    """Shards as objects under s3://bucket/prefix/, through pyarrow's S3 client and DuckDB's httpfs."""

    def __init__(self, warehouse: Path, url: str, environ: Mapping[str, str]):
        super().__init__(warehouse)
        self.url = canonical_url(url)
        self.root = self.url.removeprefix("s3://")  # pyarrow's paths have no scheme
        missing = [name for name in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY") if not environ.get(name)]
        if missing:
            raise ShardStoreError(f"the warehouse's shards are in {self.url}: set {' and '.join(missing)} "
                                  "(environment or secrets file)")
        endpoint = environ.get("AWS_ENDPOINT_URL", "")
        try:
            parts = urlsplit(endpoint)
            parts.port  # noqa: B018 (a bad port or IPv6 host raises here)
        except ValueError:
            parts = urlsplit("")
        scheme = parts.scheme if endpoint else "https"
        if endpoint and (scheme not in ("http", "https") or not parts.netloc or "@" in endpoint):
            raise ShardStoreError(f"AWS_ENDPOINT_URL: expected http(s)://host:port (no credentials: AWS_ACCESS_KEY_ID "
                                  f"and AWS_SECRET_ACCESS_KEY), got {redacted(endpoint)!r}")
        self._key, self._secret = environ["AWS_ACCESS_KEY_ID"], environ["AWS_SECRET_ACCESS_KEY"]
        self._token = environ.get("AWS_SESSION_TOKEN") or None  # temporary keys (STS, SSO) come with one
        self._region = environ.get("AWS_REGION") or environ.get("AWS_DEFAULT_REGION") or "us-east-1"
        self._host, self._scheme = parts.netloc if endpoint else "", scheme
        self._fs = None

    def __getstate__(self) -> dict:  # DataLoader workers get the settings, and make their own client
        return {**self.__dict__, "_fs": None}

    @property
    def filesystem(self):
        if self._fs is None:
            from pyarrow.fs import S3FileSystem

            self._fs = S3FileSystem(access_key=self._key, secret_key=self._secret, session_token=self._token,
                                    region=self._region,
                                    endpoint_override=self._host or None, scheme=self._scheme,
                                    connect_timeout=10, request_timeout=60)
        return self._fs

    def _path(self, rel: str) -> str:
        return f"{self.root}/{rel}"

    def patiently(self, action, *args):
        return self._patient(action, *args)

    def _patient(self, action, *args):
        """`action(*args)`, tried again while the server does not answer, for STORE_WAIT_S at most."""
        try:
            return retrying(_unreachable, within_s=STORE_WAIT_S, wait_s=0.5, backoff_max_s=4.0, log=log,
                            what=f"shard store {self.url}")(action, *args)
        except OSError as exc:
            detail = str(exc).split("; Details:")[0].split(": AWS Error ")[-1]
            if _refused(exc):
                raise ShardStoreRefused(
                    f"the shard store {self.url} refused the request ({detail}): check AWS_ACCESS_KEY_ID, "
                    "AWS_SECRET_ACCESS_KEY (and AWS_SESSION_TOKEN for temporary keys) and this host's clock (S3 "
                    "refuses signatures over 15 minutes off); nothing was changed") from None
            if not _unreachable(exc):
                raise
            raise ShardStoreUnreachable(
                f"the shard store {self.url} ({self._host or 'AWS'}) did not answer for {STORE_WAIT_S:.0f} s "
                f"({detail}): start it, then run the same command again to resume") from None

    def check_reachable(self) -> None:
        self._patient(self.filesystem.get_file_info, self._path(CLAIM))

    def location(self, rel: str) -> str:
        return f"s3://{self._path(rel)}"

    def rel_of(self, location: str) -> str:
        return location.removeprefix(f"{self.url}/")

    def fetch(self, location: str) -> Path:
        """Downloaded once per host into the cache folder's objects/ (`cache_dir`; locations name immutable
        objects: a model version's checkpoint), through a temporary name. Cached by endpoint and location:
        two S3 servers (a lab's and a laptop's SeaweedFS) may each hold a bucket and prefix of the same name."""
        server = f"{self._scheme}://{self._host}" if self._host else "aws"
        cache = cache_dir() / "objects" / hashlib.sha256(f"{server} {location}".encode()).hexdigest()[:32]
        local = cache / location.rsplit("/", 1)[-1]
        if not local.exists():
            cache.mkdir(parents=True, exist_ok=True)
            tmp = local.with_name(f".{local.name}.tmp-{os.getpid()}")
            try:
                with self.open(location) as source, tmp.open("wb") as out:
                    for block in iter(lambda: source.read(1 << 20), b""):
                        out.write(block)
                    out.flush()
                    os.fsync(out.fileno())  # the cache trusts a file once named: whole before it is, past a power loss
                tmp.replace(local)
            except BaseException:
                tmp.unlink(missing_ok=True)
                raise
        return local

    def parquet(self, location: str):
        """Ranged reads: the footer now (tried again while the server does not answer), the row groups
        as they are asked for (a verify or a training reads no more of the object than it needs)."""
        import pyarrow.parquet as pq

        return self._patient(lambda: pq.ParquetFile(self.filesystem.open_input_file(location.removeprefix("s3://"))))

    def open(self, location: str) -> pa.NativeFile:
        """The whole object, read into memory (for hashing and whole reads): a server that blips
        mid-read is waited for like any other request."""
        def whole() -> pa.Buffer:
            with self.filesystem.open_input_file(location.removeprefix("s3://")) as handle:
                return handle.read_buffer()
        return pa.BufferReader(self._patient(whole))

    def put_new(self, rel: str, data: pa.Buffer, sha: str) -> None:
        if self.exists(rel):  # a unit computed twice: the same bytes are kept, others refused
            if self.sha256(rel) != sha:
                raise ShardConflict(f"{self.location(rel)} exists with other content; remove it if no catalog row "
                                    "names it")
            return

        self._upload(rel, data)

    def _upload(self, rel: str, data: pa.Buffer | bytes) -> None:
        def upload() -> None:
            with self.filesystem.open_output_stream(self._path(rel)) as out:  # the object appears whole, or not at all
                out.write(data)
        self._patient(upload)

    def abort_uploads(self, under: str) -> list[str]:
        """Abort the multipart uploads under the folder `under` that never completed -> their rels. An upload
        killed midway (a compacted file of up to 256 MB goes up in parts) leaves one: no listing shows it, so
        the orphan sweep never would, and the server keeps its parts until it is aborted. Like that sweep,
        call it only where no other writer is at work here. A server that does not answer the listing is
        left for the next sweep (a warning): the parts cost space, not correctness."""
        import boto3
        from botocore.exceptions import BotoCoreError, ClientError

        bucket, _, prefix = self.root.partition("/")
        base = f"{prefix}/" if prefix else ""
        client = boto3.client("s3", endpoint_url=f"{self._scheme}://{self._host}" if self._host else None,
                              aws_access_key_id=self._key, aws_secret_access_key=self._secret,
                              aws_session_token=self._token, region_name=self._region)
        aborted = []
        try:
            for page in client.get_paginator("list_multipart_uploads").paginate(Bucket=bucket, Prefix=f"{base}{under}/"):
                for upload in page.get("Uploads", []):
                    client.abort_multipart_upload(Bucket=bucket, Key=upload["Key"], UploadId=upload["UploadId"])
                    aborted.append(upload["Key"].removeprefix(base))
        except (BotoCoreError, ClientError) as exc:
            log.warning("shard store %s: unfinished uploads not listed (%s); the next sweep tries again", self.url, exc)
        return aborted

    def exists(self, rel: str) -> bool:
        from pyarrow.fs import FileType

        return self._patient(self.filesystem.get_file_info, self._path(rel)).type == FileType.File

    def files(self, under: str) -> list[str]:
        from pyarrow.fs import FileSelector, FileType

        selector = FileSelector(self._path(under), recursive=True, allow_not_found=True)
        infos = self._patient(self.filesystem.get_file_info, selector)
        return sorted(i.path.removeprefix(self.root + "/") for i in infos if i.type == FileType.File)

    def move(self, rel: str, to_rel: str) -> None:
        self._patient(self.filesystem.copy_file, self._path(rel), self._path(to_rel))
        self._patient(self.filesystem.delete_file, self._path(rel))

    def delete(self, rel: str) -> None:
        if self.exists(rel):
            self._patient(self.filesystem.delete_file, self._path(rel))

    def prepare(self, con: duckdb.DuckDBPyConnection) -> None:
        """httpfs from the duckdb-extension-httpfs package (no download), and this store's key as a
        temporary secret scoped to its prefix. A connection of a process whose DuckDB instance already
        has them (concurrent connections share it) leaves them be."""
        with _PREPARING:  # the instance's extensions, settings and secrets are shared by the process's threads
            self._prepare(con)

    def _prepare(self, con: duckdb.DuckDBPyConnection) -> None:
        loaded = con.execute("SELECT loaded FROM duckdb_extensions() WHERE extension_name = 'httpfs'").fetchone()
        if not (loaded and loaded[0]):
            con.execute(f"LOAD '{_httpfs_extension()}'")
        if con.execute("SELECT 1 FROM duckdb_secrets() WHERE name = ?", [_DUCKDB_SECRET]).fetchone():
            return
        for name, value in _HTTPFS_RETRIES.items():
            con.execute(f"SET {name} = {value}")
        quote = lambda value: "'" + value.replace("'", "''") + "'"  # noqa: E731 (CREATE SECRET takes no parameters)
        options = {"KEY_ID": self._key, "SECRET": self._secret, "REGION": self._region, "URL_STYLE": "path",
                   "SCOPE": self.url + "/"}
        if self._host:
            options["ENDPOINT"] = self._host
        if self._token:
            options["SESSION_TOKEN"] = self._token
        settings = ", ".join(f"{name} {quote(value)}" for name, value in options.items())
        con.execute(f"CREATE TEMPORARY SECRET {_DUCKDB_SECRET} (TYPE s3, {settings}, "
                    f"USE_SSL {'true' if self._scheme == 'https' else 'false'})")

    def allowed(self) -> list[str]:
        return [*super().allowed(), self.url + "/"]

    def claim(self, warehouse_id: str | None, catalog: Path) -> str:
        """A marker object at the prefix names the catalog whose shards live under it: a second
        workspace pointed at the same prefix (one secrets file shared by two campaigns) would take the
        first one's shards for orphans of its own, and delete them."""
        import json
        import socket

        host = socket.gethostname()
        if self.exists(CLAIM):
            with self.read(CLAIM) as handle:
                owner = json.loads(handle.read().decode())
            ours = (owner.get("catalog"), owner.get("host")) == (str(catalog), host)
            if owner.get("warehouse_id") == warehouse_id or (warehouse_id is None and ours):
                return owner["warehouse_id"]  # (a new catalog whose first creation stopped after claiming)
            raise ShardStoreError(f"{self.url} keeps the shards of another warehouse (catalog {owner.get('catalog')} "
                                  f"on {owner.get('host')}): give this workspace its own prefix in {SHARD_STORE_ENV}")
        warehouse_id = warehouse_id or uuid.uuid4().hex
        marker = json.dumps({"warehouse_id": warehouse_id, "catalog": str(catalog), "host": host})
        self._upload(CLAIM, marker.encode())
        return warehouse_id


def _httpfs_extension() -> str:
    try:
        import duckdb_extension_httpfs
    except ImportError:
        raise ShardStoreError("reading shards on S3 needs DuckDB's httpfs: pip install "
                              f"duckdb-extension-httpfs=={duckdb.__version__}") from None
    found = sorted(Path(duckdb_extension_httpfs.__file__).parent.glob("extensions/*/httpfs.duckdb_extension"))
    if not found:
        raise ShardStoreError(f"no httpfs.duckdb_extension in {Path(duckdb_extension_httpfs.__file__).parent}")
    return found[-1].as_posix()


def canonical_url(url: str) -> str:
    """FOLDER, or s3://bucket/prefix with no trailing slash.

    Raises:
        ShardStoreError: anything else.
    """
    url = url.strip()
    if url in ("", "file", FOLDER):
        return FOLDER
    try:
        parts = urlsplit(url)
    except ValueError:
        parts = urlsplit("")
    if "@" in parts.netloc or ":" in parts.netloc:  # keys go in AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY, never in a URL that
        # is logged; a bucket name holds no ":" (a raw "/" in a password ends urlsplit's host at "user:…")
        said = "without credentials (set AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY)" if "@" in url else \
            "(a bucket name holds no ':': the server's host and port go in AWS_ENDPOINT_URL)"
        raise ShardStoreError(f"{SHARD_STORE_ENV}: expected s3://bucket/prefix {said}, got {redacted(url)}")
    if parts.scheme != "s3" or not parts.netloc or parts.query or parts.fragment:
        raise ShardStoreError(f"{SHARD_STORE_ENV}: expected s3://bucket/prefix (or unset: the warehouse folder), "
                              f"got {redacted(url)!r}")
    return f"s3://{parts.netloc}/{parts.path.strip('/')}".rstrip("/")


def open_store(warehouse: Path, recorded: str | None = None, environ: Mapping[str, str] | None = None) -> ShardStore:
    """The store of the warehouse at `warehouse`: the one its catalog recorded (`recorded`), else the one
    SIM2ACT_SHARD_STORE names, else the folder.

    Raises:
        ShardStoreError: the variable names another store than the recorded one; an s3 URL without its keys.
    """
    environ = os.environ if environ is None else environ
    wanted = canonical_url(environ[SHARD_STORE_ENV]) if environ.get(SHARD_STORE_ENV) else None
    url = recorded or wanted or FOLDER
    if wanted is not None and wanted != url:
        raise ShardStoreError(f"{SHARD_STORE_ENV}: expected {url} (where the warehouse at {warehouse} keeps "
                              f"its shards), got {wanted}")
    return FolderStore(warehouse) if url == FOLDER else S3Store(warehouse, url, environ)
