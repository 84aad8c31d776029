"""The dashboard's HTTP app: the page, its panels' rows, the episode browser and the videos.

Every request reads the catalog afresh (read-only, briefly), so the page follows a campaign
that is still running; the server writes nothing into the workspace.
"""

from __future__ import annotations

import ipaddress
import os
import socket
import tempfile
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import duckdb
import uvicorn
from fastapi import FastAPI, HTTPException, Query, Request
from fastapi.middleware.trustedhost import TrustedHostMiddleware
from fastapi.responses import FileResponse, JSONResponse
from fastapi.staticfiles import StaticFiles

from dashboards import reads
from dashboards.media import EpisodeVideos, media_file, media_url
from dashboards.panels import PanelError, load_panels, run_panel
from schemas.errors import Sim2ActError
from schemas.workspace import Workspace
from warehouse.catalog import Catalog, CatalogMissing

STATIC = Path(__file__).with_name("static")
PAGE_SIZE = 50
VIDEO_FOLDER_PREFIX = "sim2act-dashboard-"  # + the server's pid: a killed server's folder is found by it


def _sweep_dead_dashboards_folders() -> None:
    """Remove the video folders of dashboards that were killed (SIGKILL: no shutdown to remove them), found by
    the pid in their name; a folder of a server still running, or of an older sim2act (no pid), is left."""
    import shutil

    import psutil

    for folder in Path(tempfile.gettempdir()).glob(f"{VIDEO_FOLDER_PREFIX}*-*"):
        pid = folder.name.removeprefix(VIDEO_FOLDER_PREFIX).split("-", 1)[0]
        if pid.isdecimal() and not psutil.pid_exists(int(pid)):
            shutil.rmtree(folder, ignore_errors=True)


def create_app(workspace: Workspace, allowed_hosts: list[str] | None = None) -> FastAPI:
    """The dashboard's app over `workspace`. `allowed_hosts`: the Host headers it answers (`serve` gives the
    loopback names where it listens on loopback, so a page elsewhere cannot read it by DNS rebinding);
    None: any."""
    catalog = Catalog(workspace.catalog)
    panels = load_panels()
    by_id = {panel.id: panel for panel in panels}
    _sweep_dead_dashboards_folders()
    video_folder = tempfile.TemporaryDirectory(prefix=f"{VIDEO_FOLDER_PREFIX}{os.getpid()}-")
    videos = EpisodeVideos(catalog, Path(video_folder.name))

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        yield
        # here, not at interpreter exit: uvicorn re-raises SIGTERM (`sim2act down`) after its shutdown,
        # and the rendered videos of every stopped dashboard stayed in /tmp
        video_folder.cleanup()

    app = FastAPI(title="Sim2Act dashboard", docs_url=None, redoc_url=None, openapi_url=None, lifespan=lifespan)
    app.state.video_folder = video_folder  # removed when the app goes
    if allowed_hosts is not None:
        app.add_middleware(TrustedHostMiddleware, allowed_hosts=allowed_hosts)
    app.mount("/static", StaticFiles(directory=STATIC), name="static")

    def a_file_failed(exc: duckdb.Error) -> bool:
        """A shard could not be read: missing (IOException), or a registered one DuckDB names (torn, damaged)."""
        if isinstance(exc, duckdb.IOException):
            return True
        try:
            return catalog.registered_shard_in(str(exc)) is not None
        except Exception:  # the catalog itself unreadable: not a shard's failure
            return False

    @app.exception_handler(duckdb.Error)
    def unreadable_file(request: Request, exc: duckdb.Error) -> JSONResponse:
        """A shard missing or damaged (moved by hand, a disk error, a torn file: DuckDB's IOException or
        InvalidInputException), the catalog busy, or any other read failing: said in one line, not a bare 500."""
        first = str(exc).splitlines()[0][:300] if str(exc) else type(exc).__name__
        if isinstance(exc, duckdb.IOException) and "lock" in first.lower():  # a writer held it past the wait
            return JSONResponse(status_code=503, content={"detail": "the warehouse catalog is busy (a campaign is "
                                                                    "registering work): try again in a moment"})
        if a_file_failed(exc):
            return JSONResponse(status_code=503, content={"detail": (
                f"a warehouse file could not be read ({first}): run `sim2act warehouse verify --workspace "
                f"{workspace.root}` to quarantine it; the next `sim2act run` redoes its unit")})
        return JSONResponse(status_code=500, content={"detail": f"the warehouse could not be read: {first}"})

    @app.exception_handler(Sim2ActError)
    def known_failure(request: Request, exc: Sim2ActError) -> JSONResponse:
        """A catalog that is not DuckDB's, or another known failure: its own line, which says what to do."""
        return JSONResponse(status_code=503, content={"detail": str(exc)})

    def known_campaigns() -> tuple[list[str], str | None]:
        """(campaigns, why there is nothing to show when there are none)."""
        try:
            found = reads.campaigns(catalog)
        except CatalogMissing:
            return [], f"No data yet: there is no warehouse at {workspace.warehouse}. Start a campaign with `sim2act run`."
        except duckdb.CatalogException:  # created, its tables not yet
            found = []
        return found, None if found else "No data yet: the warehouse holds no campaign. Start one with `sim2act run`."

    def campaign_of(requested: str | None) -> str:
        found, message = known_campaigns()
        if not found:
            raise HTTPException(404, message)
        if requested is None:
            return found[0]
        if requested not in found:
            raise HTTPException(404, f"no campaign {requested!r} in the warehouse (it has {', '.join(found)})")
        return requested

    @app.get("/health")
    def health() -> dict[str, Any]:
        return {"status": "ok", "workspace": str(workspace.root), "catalog": workspace.catalog.exists()}

    @app.get("/", include_in_schema=False)
    def page() -> FileResponse:
        return FileResponse(STATIC / "index.html")

    @app.get("/api/panels")
    def panel_list() -> dict[str, Any]:
        found, message = known_campaigns()
        return {"campaigns": found, "message": message, "panels": [p.model_dump(exclude={"sql"}) for p in panels]}

    @app.get("/api/panels/{panel_id}")
    def panel_rows(panel_id: str, campaign: str | None = None) -> dict[str, Any]:
        panel = by_id.get(panel_id)
        if panel is None:
            raise HTTPException(404, f"no panel {panel_id!r} (panels: {', '.join(by_id)})")
        chosen = campaign_of(campaign)
        try:
            rows = run_panel(catalog, panel, chosen)
        except duckdb.Error as exc:
            if a_file_failed(exc):
                raise  # a file, not the panel: `unreadable_file` says what to do
            raise HTTPException(500, f"panel {panel_id}: {str(exc).splitlines()[0]}") from None
        except PanelError as exc:
            raise HTTPException(500, f"panel {panel_id}: {str(exc).splitlines()[0]}") from None
        return {"id": panel.id, "campaign": chosen, "columns": rows.columns, "rows": rows.rows}

    @app.get("/api/episodes")
    def episode_page(campaign: str | None = None, iteration: int | None = None, task: str | None = None,
                     explorer: str | None = None, reason: str | None = None,
                     offset: int = Query(0, ge=0, le=1 << 62), limit: int = PAGE_SIZE) -> dict[str, Any]:
        query = reads.EpisodeQuery(campaign_of(campaign), iteration, task or None, explorer or None, reason or None)
        total, rows, choices = reads.episodes(catalog, query, offset, min(max(1, limit), 500))
        return {"campaign": query.campaign, "total": total, "offset": offset, "rows": rows.rows, "choices": choices}

    @app.api_route("/api/episodes/{episode_id}/video", methods=["GET", "HEAD"])  # HEAD: a player's or a checker's
    def episode_video(episode_id: str) -> FileResponse:
        try:
            path = videos.path(episode_id)
        except (CatalogMissing, duckdb.CatalogException):  # no warehouse yet, or its tables not yet
            path = None
        if path is None:
            raise HTTPException(404, f"episode {episode_id!r} has no stored frames")
        return FileResponse(path, media_type="video/mp4")

    @app.get("/api/evaluations")
    def evaluations(task: str, campaign: str | None = None) -> dict[str, Any]:
        rows = reads.task_evaluations(catalog, campaign_of(campaign), task).rows
        return {"rows": [{**{k: v for k, v in row.items() if not k.endswith("_video")},
                          "success_url": media_url(workspace, row["success_video"]),
                          "failure_url": media_url(workspace, row["failure_video"])} for row in rows]}

    @app.api_route("/media/{name:path}", methods=["GET", "HEAD"])
    def media(name: str) -> FileResponse:
        path = media_file(workspace, name)
        if path is None:
            raise HTTPException(404, f"no video {name!r} in the workspace's media folder")
        return FileResponse(path, media_type="video/mp4")

    return app


class DashboardUnservable(Sim2ActError, OSError):
    """The dashboard's address cannot be listened on (a port in use, a host that does not resolve)."""


def listening_socket(host: str, port: int) -> socket.socket:
    """The dashboard's socket, bound before anyone is told where it serves.

    Raises:
        DashboardUnservable: naming the address and why (uvicorn's own bind says it after the banner, and exits 3)."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
    except (socket.gaierror, UnicodeError) as exc:
        raise DashboardUnservable(f"--host {host}: not an address this machine can listen on ({exc})") from None
    sock = socket.socket(family, kind, proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind(address)
    except OSError as exc:
        sock.close()
        raise DashboardUnservable(f"cannot serve the dashboard at {host}:{port}: {exc.strerror} "
                                  "(another --port or --host)") from None
    return sock


LOOPBACK_NAMES = ["localhost", "127.0.0.1", "::1", "[::1]"]


def serve(workspace: Workspace, sock: socket.socket, name: str = "127.0.0.1") -> None:
    """Serve the dashboard over the workspace's warehouse on `sock` (`listening_socket`) until interrupted
    (blocking). On a loopback address it answers only requests naming a loopback host, or `name` (the
    --host it was given: a host name may resolve to 127.0.1.1)."""
    host = ipaddress.ip_address(sock.getsockname()[0])
    app = create_app(workspace, [*LOOPBACK_NAMES, name] if host.is_loopback else None)
    uvicorn.Server(uvicorn.Config(app, log_level="warning")).run(sockets=[sock])
