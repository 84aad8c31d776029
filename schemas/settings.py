"""Settings that come from the environment, never from a campaign config: where MLflow tracking goes,
the stack's databases, and their credentials.

A campaign config is logged everywhere on purpose (MLflow params, Prefect parameters, the workspace),
so a database URL with its password must not be one of its fields. These are the tools' own variables
(MLflow's and Prefect's names, so their documentation applies), read from the environment, or from a
secrets file that SIM2ACT_SECRETS_FILE names: KEY=VALUE lines, `#` comments, mode 600. The environment
wins over the file.
"""

from __future__ import annotations

import os
import re
import shutil
import sqlite3
import stat
from collections.abc import Iterator, MutableMapping
from contextlib import closing, contextmanager
from pathlib import Path

from schemas.errors import Sim2ActError
from schemas.workspace import Workspace

SECRETS_FILE_ENV = "SIM2ACT_SECRETS_FILE"
CACHE_DIR_ENV = "SIM2ACT_CACHE_DIR"
# How many scenes (an environment per family, env and render settings) a rollout worker keeps open
# between units; beyond it the least recently used is closed. A scene holds ~0.08 GB (MetaWorld) to
# ~0.3 GB (robosuite) of the worker's memory (docs/evaluation.md); 16 keep a worker under ~3.5 GB.
SCENES_PER_WORKER_ENV, DEFAULT_SCENES_PER_WORKER = "SIM2ACT_SCENES_PER_WORKER", 16
# MLflow's: where runs are logged (default: the workspace's SQLite file); an http(s) URL is an MLflow server.
TRACKING_URI_ENV = "MLFLOW_TRACKING_URI"
# MLflow's: where models are registered and looked up, for a lab whose registry is not its tracking store
# (default: where runs are logged, as MLflow's own default).
REGISTRY_URI_ENV = "MLFLOW_REGISTRY_URI"
# MLflow's, read by `sim2act up`'s MLflow server: its database (default: the workspace's SQLite file)
# and, with a database of its own, where it keeps the artifacts it proxies (default: the workspace's folder).
BACKEND_STORE_ENV, ARTIFACTS_DESTINATION_ENV = "MLFLOW_BACKEND_STORE_URI", "MLFLOW_ARTIFACTS_DESTINATION"
# Prefect's, read by `sim2act up`'s Prefect server: its database (default: SQLite in the workspace's Prefect home).
PREFECT_DATABASE_ENV = "PREFECT_SERVER_DATABASE_CONNECTION_URL"
_KEY = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class SecretsFileError(Sim2ActError, ValueError):
    pass


class SettingError(Sim2ActError, ValueError):
    pass


def read_secrets_file(path: Path) -> dict[str, str]:
    """KEY=VALUE per line (blank lines and `#` comments skipped, one pair of quotes around a value
    dropped). A refusal never shows a line's text: it may hold a secret.

    Raises:
        SecretsFileError: no such file; readable or writable by group or others; a line that is not KEY=VALUE.
    """
    try:
        mode = path.stat().st_mode
    except FileNotFoundError:
        raise SecretsFileError(f"secrets file {path} ({SECRETS_FILE_ENV}): no such file") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise SecretsFileError(f"secrets file {path}: expected mode 600 (only its owner reads it), got "
                               f"{stat.S_IMODE(mode):03o}: chmod 600 {path}")
    try:
        text = path.read_text()
    except (OSError, UnicodeError) as exc:
        raise SecretsFileError(f"secrets file {path}: expected a readable UTF-8 text file, got {type(exc).__name__}: "
                               f"{getattr(exc, 'strerror', None) or exc}") from None
    values = {}
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        key, sep, value = line.partition("=")
        key, value = key.strip().removeprefix("export ").strip(), value.strip()
        if not sep or not _KEY.fullmatch(key):
            raise SecretsFileError(f"secrets file {path} line {number}: expected KEY=VALUE")
        if len(value) >= 2 and value[0] == value[-1] and value[0] in "'\"":
            value = value[1:-1]
        values[key] = value
    return values


def apply_secrets_file(environ: MutableMapping[str, str] | None = None) -> list[str]:
    """Load the file SIM2ACT_SECRETS_FILE names (if any) into the environment, where a variable is not
    already set; -> the names it set. Child processes (the servers, workers) inherit them."""
    environ = os.environ if environ is None else environ
    if not environ.get(SECRETS_FILE_ENV):
        return []
    loaded = read_secrets_file(Path(environ[SECRETS_FILE_ENV]).expanduser())
    added = [key for key in loaded if key not in environ]
    for key in added:
        environ[key] = loaded[key]
    return added


def cache_dir() -> Path:
    """Where derived files that any workspace may reuse live (decimated meshes): SIM2ACT_CACHE_DIR, else
    $XDG_CACHE_HOME/sim2act, else ~/.cache/sim2act. Per host: a rollout worker on another machine fills its own."""
    if os.environ.get(CACHE_DIR_ENV):
        return Path(os.environ[CACHE_DIR_ENV])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "sim2act"


def scenes_per_worker() -> int:
    """SIM2ACT_SCENES_PER_WORKER, else 16.

    Raises:
        SettingError: the variable is set to anything but a whole number ≥ 1.
    """
    raw = os.environ.get(SCENES_PER_WORKER_ENV, "").strip()
    if not raw:
        return DEFAULT_SCENES_PER_WORKER
    if not raw.isdecimal() or not raw.isascii() or int(raw) < 1:
        raise SettingError(f"{SCENES_PER_WORKER_ENV}: expected a whole number of scenes, at least 1, got {raw!r}")
    return int(raw)


def tracking_uri(workspace: Workspace) -> str:
    """Where this process logs MLflow runs and registers models: MLFLOW_TRACKING_URI, else the
    workspace's own SQLite file (made whole first, if it is not there yet: `whole_sqlite_store`)."""
    configured = os.environ.get(TRACKING_URI_ENV)
    if configured:
        return configured
    whole_sqlite_store(workspace)
    return workspace.tracking_uri


def registry_uri(workspace: Workspace) -> str:
    """Where this process registers models and resolves `models:/` references: MLFLOW_REGISTRY_URI, else
    where it logs runs (`tracking_uri`). Every registry call goes through it: registering in one store and
    looking up in another found no model (`sim2act eval --model champion`)."""
    return os.environ.get(REGISTRY_URI_ENV) or tracking_uri(workspace)


def whole_sqlite_store(workspace: Workspace) -> None:
    """Create the workspace's MLflow SQLite store if it does not exist, all at once.

    MLflow creates its store on first use through ~100 schema migrations, and SQLite commits each
    statement on its own: a run killed among them (a soak's kill, Ctrl-C in a run's first seconds) left a
    store that no later run could open ("table _alembic_tmp_experiments already exists"). So the store
    is made under a name of this process's, then linked into place, which fails if another process was
    first (its store, maybe with runs already, is kept). A kill leaves a temporary file, removed by the
    next process that makes the store. The migrations run once per host and MLflow version
    (`_migrated_store`, ~3 s); a workspace's store is a copy of that one, given its Default experiment.
    """
    path = workspace.tracking_db
    if path.exists():
        store_at_home(workspace)
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    template = _migrated_store()
    with _made_aside(path) as making:
        if template is not None:
            shutil.copyfile(template, making)
        # on the copy: MLflow's check of the schema, and the Default experiment under this workspace's folder
        SqlAlchemyStore(f"sqlite:///{making}", workspace.artifact_root.as_uri()).engine.dispose()


# The MLflow SQLite store's columns that name artifacts by absolute path, under the artifact root it was made for.
_ARTIFACT_COLUMNS = (("experiments", "artifact_location"), ("runs", "artifact_uri"),
                     ("logged_models", "artifact_location"), ("model_versions", "storage_location"))
_AT_HOME: set[tuple[Path, str]] = set()  # (store, artifact root) this process found or put at home


def store_at_home(workspace: Workspace) -> None:
    """The workspace's own MLflow SQLite store names its artifacts under this workspace's folder.

    MLflow stores artifact locations as absolute `file://` paths: a workspace folder moved elsewhere
    could not download its registered models (the paths named a folder that was gone), and a copy's new
    runs wrote their artifacts into the original's folder. The root the store was made for is read from
    its Default experiment (`<root>/0`, `whole_sqlite_store`) and rewritten to this one in every such
    column, in one transaction; a store at home is left as it is (checked once per process).
    """
    root = workspace.artifact_root.as_uri()
    if (workspace.tracking_db, root) in _AT_HOME:
        return
    with closing(sqlite3.connect(workspace.tracking_db, timeout=60)) as con:
        row = con.execute("SELECT artifact_location FROM experiments WHERE experiment_id = 0").fetchone()
        old = row[0].removesuffix("/0") if row and row[0].startswith("file://") and row[0].endswith("/0") else root
        if old != root:
            try:
                with con:
                    for table, column in _ARTIFACT_COLUMNS:
                        con.execute(f"UPDATE {table} SET {column} = ? || substr({column}, ?) "
                                    f"WHERE substr({column}, 1, ?) = ? AND substr({column}, ?, 1) IN ('', '/')",
                                    [root, len(old) + 1, len(old), old, len(old) + 1])
            except sqlite3.OperationalError:  # a store this process may not write (a read-only copy): read as it is
                return
    _AT_HOME.add((workspace.tracking_db, root))


def _migrated_store() -> Path | None:
    """An MLflow SQLite store migrated to this MLflow's schema, with no experiment in it, kept in the cache
    folder (`cache_dir`) for every workspace of this host; None where that folder cannot be written (each
    workspace's store is then migrated on its own)."""
    import mlflow
    from mlflow.store.tracking.sqlalchemy_store import SqlAlchemyStore

    path = cache_dir() / "mlflow" / f"empty-store-{mlflow.__version__}.db"
    if path.exists():
        return path
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        if not os.access(path.parent, os.W_OK | os.X_OK):
            return None
        with _made_aside(path) as making:
            SqlAlchemyStore(f"sqlite:///{making}", (path.parent / "unused-artifacts").as_uri()).engine.dispose()
            # the Default experiment names an artifact folder: each workspace's copy makes its own
            with closing(sqlite3.connect(making)) as db, db:
                db.execute("DELETE FROM experiments")
    except OSError:
        return None
    return path


@contextmanager
def _made_aside(path: Path) -> Iterator[Path]:
    """Yield a temporary name beside `path` to make a SQLite file under; then link it into place, unless
    another process was first (its file is kept). Temporary files of killed makers are removed first; every
    connection to the file must be closed on return (so that no journal is left beside it)."""
    # a killed maker's file and its SQLite journal (`.making-<pid>-journal`); a live one's is still being made
    for stale in path.parent.glob(f"{path.name}.making-*"):
        pid = stale.name.removeprefix(f"{path.name}.making-").split("-")[0]
        if not (pid.isdigit() and process_alive(int(pid))):
            stale.unlink(missing_ok=True)
    making = path.with_name(f"{path.name}.making-{os.getpid()}")
    making.unlink(missing_ok=True)  # this process's own, left by an attempt that raised
    try:
        yield making
        try:
            os.link(making, path)
        except FileExistsError:
            pass
    finally:
        making.unlink(missing_ok=True)


def process_alive(pid: int) -> bool:
    """Whether process `pid` runs on this host (another user's counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return pid > 0


# scheme://user:password@host...: the password runs to the last "@" (SQLAlchemy, hence MLflow, takes a raw "/",
# "?" or "#" in it, where urlsplit would end the host at the first "/" and show the rest as a path)
_CREDENTIALS = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]*://[^:@/?#]*):.*@")


def redacted(url: str) -> str:
    """A URL as it may be shown: its password replaced by ***, and any query (`?token=…`) by `?***`."""
    shown = _CREDENTIALS.sub(r"\1:***@", url, count=1)
    head, query, _ = shown.partition("?")
    return head + ("?***" if query else "")
