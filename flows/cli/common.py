"""What every `sim2act` command shares: the workspace option and its catalog, the campaign options
(preset, config file, --set), the process environment, and how a report is printed or written."""

from __future__ import annotations

import argparse
import base64
import os
import re
import urllib.request
from pathlib import Path
from urllib.parse import unquote, urlsplit, urlunsplit

from schemas.config import PRESETS, CampaignConfig, deep_merge, load_config, parse_settings
from schemas.errors import Sim2ActError
from schemas.settings import BACKEND_STORE_ENV, REGISTRY_URI_ENV, TRACKING_URI_ENV, apply_secrets_file, redacted
from schemas.workspace import Workspace, write_text_atomically

Commands = "argparse._SubParsersAction[argparse.ArgumentParser]"  # what each group's register() adds to


def output_file(text: str) -> Path:
    """argparse's type for an option naming a file to write (--out, --record): a path that could not be
    written (a folder, under a file, in a folder not writable) is refused as the flags are read, before
    the command's work, not after it. Folders missing on the way are made when it is written."""
    path = Path(text)
    if path.is_dir():
        raise argparse.ArgumentTypeError(f"expected a file to write, got the folder {path}")
    folder = _first_existing(path.parent)
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"expected a file to write, got {path}, under {folder}: a file, not a folder")
    if not os.access(folder, os.W_OK):
        raise argparse.ArgumentTypeError(f"cannot write {path}: the folder {folder} is not writable")
    return path


def _first_existing(path: Path) -> Path:
    """`path`, or the nearest folder above it that exists (a relative path ends at '.', an absolute one at '/')."""
    return next(p for p in (path, *path.parents) if p.exists())


def non_negative_int(text: str) -> int:
    """argparse's type for an iteration number: 0 or more."""
    value = int(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"expected 0 or more, got {value}")
    return value


def positive_int(text: str) -> int:
    """argparse's type for a count that must be 1 or more (episodes, workers)."""
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected 1 or more, got {value}")
    return value


def port_number(text: str) -> int:
    """argparse's type for a TCP port."""
    value = int(text)
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port from 1 to 65535, got {value}")
    return value


def noise_level(text: str) -> float:
    """argparse's type for an expert's action noise: 0 to 1, as the config's (NoiseLevel)."""
    value = float(text)
    if not 0 <= value <= 1:  # NaN and inf too
        raise argparse.ArgumentTypeError(f"expected a noise from 0 to 1, got {text}")
    return value


def scratch_folder(text: str) -> Path:
    """argparse's type for a folder to work in (bench --scratch): made if missing, so not a file, nor under one."""
    path = Path(text)
    found = _first_existing(path)
    if not found.is_dir():
        raise argparse.ArgumentTypeError(f"expected a folder (made if missing), got {path}"
                                         f"{'' if found == path else f', under {found}'}: a file")
    return path


def default_workspace() -> str:
    return os.environ.get("SIM2ACT_WORKSPACE", "workspace")


def workspace_folder(text: str) -> str:
    """argparse's type for --workspace (and $SIM2ACT_WORKSPACE, its default): a folder, or none yet, not under a
    file either (a campaign made its catalog there and failed at its first shard folder, a traceback)."""
    path = Path(text)
    found = _first_existing(path)
    if not found.is_dir():
        from_env = "" if text != os.environ.get("SIM2ACT_WORKSPACE") else " (from $SIM2ACT_WORKSPACE)"
        raise argparse.ArgumentTypeError(f"expected a workspace folder (or a path for a new one), got {text}{from_env}"
                                         f"{'' if found == path else f', under {found}'}: a file")
    return text


def add_workspace_option(command: argparse.ArgumentParser) -> argparse.ArgumentParser:
    command.add_argument("--workspace", type=workspace_folder, default=default_workspace(),
                         help="default: $SIM2ACT_WORKSPACE or ./workspace")
    return command


def add_config_options(command: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """A command that reads a campaign config: preset, file, --set."""
    command.add_argument("--preset", choices=PRESETS, default="default")
    command.add_argument("--config", type=Path, help="YAML file whose fields override the preset's")
    command.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                         help="override one config field, e.g. --set train.contrastive_weight=0 (repeatable)")
    return command


def add_campaign_options(command: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """A command that reads a campaign config (preset, file, --set) and a workspace, as `run` does."""
    return add_workspace_option(add_config_options(command))


def campaign_config(args: argparse.Namespace, overrides: dict | None = None) -> CampaignConfig:
    """The campaign the options name, with a command's own `overrides` (nested dicts, over --set's),
    validated: a bad field costs one line, before any work."""
    return load_config(args.preset, args.config, deep_merge(parse_settings(args.set), overrides or {}))


def open_catalog(args: argparse.Namespace):
    """The workspace the options name and its catalog, checked to be of this code's layout (one line
    otherwise): every command that reads a warehouse opens it here."""
    from warehouse.catalog import Catalog

    workspace = Workspace.at(args.workspace)
    catalog = Catalog(workspace.catalog)
    catalog.check_version()
    return workspace, catalog


def campaign_flags(args: argparse.Namespace) -> list[str]:
    """The flags that name this campaign again, as the user gave them, one argument each."""
    flags = ["--preset", args.preset] + (["--config", str(args.config)] if args.config else [])
    for setting in args.set:
        flags += ["--set", setting]
    return flags + ["--workspace", str(args.workspace)]


def same_campaign_flags(args: argparse.Namespace) -> str:
    """The flags that name this campaign again, as a line to print."""
    return " ".join(campaign_flags(args))


def configure_environment(workspace: Workspace) -> None:
    """The secrets file's settings (schemas/settings.py), the running stack's URLs, then embedded
    defaults: Prefect's ephemeral API with its home in the workspace, MLflow on SQLite in the workspace
    (unless MLFLOW_TRACKING_URI says otherwise), no telemetry, no hub downloads (the env modules choose
    the renderer)."""
    from flows.service import running_urls
    from schemas.settings import scenes_per_worker

    apply_secrets_file()
    scenes_per_worker()  # a bad SIM2ACT_SCENES_PER_WORKER: one line now, not from the first worker, minutes in
    # While `sim2act up` runs on this workspace, runs report to its servers and show in its UIs.
    for key, value in running_urls(workspace).items():
        os.environ.setdefault(key, value)
    defaults = {
        "PREFECT_HOME": str(workspace.prefect_home),
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",
        "DO_NOT_TRACK": "1",
        "PREFECT_LOGGING_EXTRA_LOGGERS": "sim2act",
        "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "90",
        "MLFLOW_DISABLE_TELEMETRY": "true",
        "HF_HUB_OFFLINE": "1",
        "TOKENIZERS_PARALLELISM": "false",
        "PYTHONWARNINGS": "ignore::DeprecationWarning,ignore::FutureWarning",
        "TRANSFORMERS_VERBOSITY": "error",
        "HF_HUB_DISABLE_PROGRESS_BARS": "1",
        "MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR": "false",
    }
    for key, value in defaults.items():
        os.environ.setdefault(key, value)


# the tracking URIs MLflow takes (a plain path is its file store); "postgresql+psycopg2" is postgresql's. MLflow 3
# refuses its file store (./mlruns, file://) unless MLFLOW_ALLOW_FILE_STORE is set: then "file" is taken too.
TRACKING_SCHEMES = ("sqlite", "postgresql", "mysql", "mssql", "http", "https", "databricks")
# and the registry's own (Unity Catalog): MLFLOW_REGISTRY_URI may name one
REGISTRY_SCHEMES = ("databricks-uc", "uc")
BARE_URIS = ("databricks", "databricks-uc")  # a profile's default, with no "://"


class TrackingUnreachable(Sim2ActError, RuntimeError):
    pass


def _scheme(uri: str) -> str:
    """A tracking URI's scheme as MLflow reads it, less a SQLAlchemy driver ("postgresql+psycopg2" -> "postgresql"),
    "" for a plain path. Not urlsplit's: a database URL's password may hold a raw "/" or "?", which it misreads."""
    return uri.partition(":")[0].split("+")[0].lower() if re.match(r"^[A-Za-z][A-Za-z0-9+.-]*:", uri) else ""


def check_tracking_uris() -> None:
    """MLFLOW_TRACKING_URI, MLFLOW_REGISTRY_URI and MLFLOW_BACKEND_STORE_URI are of a scheme MLflow takes: its
    own refusal prints the whole URL, password too (the terminal, the flow run's state in Prefect, the MLflow
    server's log).

    Raises:
        TrackingUnreachable: one that is not, shown with its password replaced."""
    file_store = os.environ.get("MLFLOW_ALLOW_FILE_STORE", "").lower() in ("1", "true")
    for name in (TRACKING_URI_ENV, REGISTRY_URI_ENV, BACKEND_STORE_ENV):
        value = os.environ.get(name)
        if not value or value in BARE_URIS:
            continue
        scheme = _scheme(value)
        schemes = (*TRACKING_SCHEMES, *(REGISTRY_SCHEMES if name == REGISTRY_URI_ENV else ()),
                   *(("file", "") if file_store else ()))
        if scheme not in schemes:
            raise TrackingUnreachable(f"{name}: expected a URI of {', '.join(TRACKING_SCHEMES)}, got {redacted(value)}")


def check_tracking_server(workspace: Workspace) -> None:
    """Where MLFLOW_TRACKING_URI (or MLFLOW_REGISTRY_URI) names an MLflow server, it answers before any work
    starts (MLflow's own client would retry for minutes, mid-campaign); and a stack database named without a
    server to log through (`sim2act down` since) is refused rather than logging to the workspace's SQLite file.

    Raises:
        TrackingUnreachable: no answer from its /health, or no server for the named database.
    """
    uri = os.environ.get(TRACKING_URI_ENV) or workspace.tracking_uri  # not tracking_uri(): it makes the SQLite store
    if os.environ.get(BACKEND_STORE_ENV) and not os.environ.get(TRACKING_URI_ENV):
        raise TrackingUnreachable(f"{BACKEND_STORE_ENV} names the stack's tracking database, but no MLflow server "
                                  f"runs for {workspace.root}: start it (`sim2act up`) or set {TRACKING_URI_ENV}")
    check_tracking_uris()
    _server_answers(TRACKING_URI_ENV, uri)
    _database_answers(TRACKING_URI_ENV, uri)
    if (registry := os.environ.get(REGISTRY_URI_ENV)) and registry != uri:
        _server_answers(REGISTRY_URI_ENV, registry)
        _database_answers(REGISTRY_URI_ENV, registry)


# the option that bounds how long a connection may take to open, by SQLAlchemy driver (another driver: none)
_CONNECT_TIMEOUT = {"psycopg2": {"connect_timeout": 10}, "psycopg": {"connect_timeout": 10},
                    "pg8000": {"timeout": 10}, "mysqldb": {"connect_timeout": 10}, "pymysql": {"connect_timeout": 10}}


def _database_answers(name: str, uri: str) -> None:
    """A database URI (postgresql, mysql, mssql) MLflow would log to directly answers, with its driver
    installed; MLflow's own client retried for minutes and ended in a 200-line traceback. Other schemes:
    nothing to ask."""
    if _scheme(uri) not in ("postgresql", "mysql", "mssql"):
        return
    import sqlalchemy
    from sqlalchemy.exc import ArgumentError, NoSuchModuleError

    try:
        url = sqlalchemy.engine.make_url(uri)  # as MLflow reads it: a raw "/" or "?" in the password is the password's
        engine = sqlalchemy.create_engine(url, connect_args=_CONNECT_TIMEOUT.get(url.get_driver_name(), {}))
    except ModuleNotFoundError as exc:  # the dialect's driver (MySQLdb, pyodbc, ...)
        raise TrackingUnreachable(f"{name}={redacted(uri)}: its database driver is not installed (no module "
                                  f"{exc.name!r}): install it beside sim2act") from None
    except (ArgumentError, NoSuchModuleError, ValueError) as exc:  # not a URL SQLAlchemy reads, an unknown driver
        raise TrackingUnreachable(f"{name}={redacted(uri)}: not a database URL SQLAlchemy reads "
                                  f"({str(exc).splitlines()[0]})") from None
    password = url.password
    try:
        with engine.connect():
            pass
    except Exception as exc:  # the driver's own error: refused, unknown host, bad password, no database
        why = str(getattr(exc, "orig", None) or exc).strip().splitlines()[0]
        raise TrackingUnreachable(f"{name}={redacted(uri)}: the database does not answer "
                                  f"({why.replace(password, '***') if password else why})") from None
    finally:
        engine.dispose()


def _server_answers(name: str, uri: str) -> None:
    """An http(s) `uri` (named by variable `name`) answers on /health; any other scheme is not a server."""
    if not re.match(r"^https?://", uri, re.IGNORECASE):
        return
    try:
        parts = urlsplit(uri)
        if "@" in uri.partition("?")[0] and "@" not in parts.netloc:  # a raw "/" in the password ended the host
            raise ValueError("its password holds a character a URL must escape: %2F for /, %3F for ?, %23 for #")
        parts.port  # noqa: B018 (a bad port or IPv6 host raises here)
    except ValueError as exc:  # (urllib's own words may quote a piece of the password: not shown)
        why = str(exc) if str(exc).startswith("its password") else "urllib cannot read its host and port"
        raise TrackingUnreachable(f"{name}={redacted(uri)}: not a URL ({why})") from None
    # urllib takes no user:password@ in a URL: MLflow's own client sends them as basic auth; the query (a token)
    # is not the health check's
    health = urlunsplit(parts._replace(netloc=parts.netloc.rpartition("@")[2], path=f"{parts.path.rstrip('/')}/health",
                                       query="", fragment=""))
    request = urllib.request.Request(health)
    if parts.username is not None:
        token = base64.b64encode(f"{unquote(parts.username)}:{unquote(parts.password or '')}".encode()).decode()
        request.add_header("Authorization", f"Basic {token}")
    try:
        with urllib.request.urlopen(request, timeout=10) as response:
            if response.status == 200:
                return
            why = f"HTTP {response.status}"
    except (OSError, ValueError) as exc:  # ValueError: not a URL urllib can open
        why = str(getattr(exc, "reason", None) or exc)
    raise TrackingUnreachable(f"{name}={redacted(uri)}: no MLflow server answers at {health} ({why})")


def print_or_write(args: argparse.Namespace, as_json: str, table: str) -> int:
    """A bench's result: its table (or its JSON with --json) printed, the table written to --out."""
    print(as_json if args.json else table)
    if args.out:
        write_text_atomically(args.out, table)
    return 0
