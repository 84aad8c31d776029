"""The dashboard: its panel file, its refusals, and the page itself in headless Chromium over a
finished smoke campaign (charts drawn from the rows, the per-task table, videos that play)."""

from __future__ import annotations

import http.client
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import uvicorn

from dashboards.panels import PanelError, load_panels
from dashboards.server import create_app
from schemas.workspace import Workspace
from tests.conftest import SIM2ACT, _free_port
from warehouse.catalog import Catalog


@contextmanager
def serving(workspace: Workspace) -> Iterator[int]:
    """The dashboard app on a free local port, in a thread, for the duration -> the port."""
    server = uvicorn.Server(uvicorn.Config(create_app(workspace), host="127.0.0.1", port=0, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "the dashboard did not start"
        time.sleep(0.05)
    try:
        yield server.servers[0].sockets[0].getsockname()[1]
    finally:
        server.should_exit = True
        thread.join(timeout=10)


def get(port: int, path: str) -> tuple[int, bytes]:
    """A request sent with its path exactly as written (no client-side `..` clean-up)."""
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    connection.request("GET", path)
    response = connection.getresponse()
    return response.status, response.read()


# -- panels.yaml --------------------------------------------------------------------------


def test_the_panel_file_validates():
    panels = load_panels()
    assert [p.id for p in panels][:2] == ["success_by_iteration", "filter_pass_rates"]
    kinds = {p.id: p.kind for p in panels}
    assert kinds["per_task"] == "table" and kinds["success_by_iteration"] == "line"
    assert {"episodes_by_iteration", "episodes_by_family", "episodes_by_task"} <= set(kinds)
    assert all(p.parameters <= {"campaign"} for p in panels)


def test_the_success_panels_read_what_the_report_reads(tmp_path):
    """The deployed model's current evaluation of each case, as `sim2act report` pools it: another
    training seed of the same iteration and a case evaluated again do not add episodes."""
    from dashboards.panels import run_panel
    from dashboards.report import success_by_iteration
    from tests.dashboards.test_results import CAMPAIGN, _catalog_with_tasks, _evaluated, _register, _training

    catalog = _catalog_with_tasks(tmp_path)
    _register(catalog, 0, {("nav-room-red", "seen"): 6, ("nav-room-sequence-purple-red", "unseen"): 3})
    _training(catalog, "train-s1", seed=1, chunk=8)  # a second seed of iteration 0, never deployed
    _evaluated(catalog, "train-s1", 10)
    _evaluated(catalog, "train-0", 4)  # the deployed model's seen case evaluated again: the later one counts
    panels = {p.id: p for p in load_panels()}

    pooled = {row["split"]: (row["successes"], row["episodes"])
              for row in run_panel(catalog, panels["success_by_iteration"], CAMPAIGN).rows}
    report = {g.group: (g.successes, g.episodes) for g in success_by_iteration(catalog, CAMPAIGN)[0]}
    assert pooled == {"seen": (4, 10), "unseen": (3, 10)} == {k: report[k] for k in ("seen", "unseen")}
    per_task = {row["task"]: row["evaluation"] for row in run_panel(catalog, panels["per_task"], CAMPAIGN).rows}
    assert per_task["nav-room-red"].startswith("4/10") and per_task["nav-room-sequence-purple-red"].startswith("3/10")

    # the campaign run again in its workspace with another recipe: iteration 0 deploys a second model, which counts
    _register(catalog, 0, {("nav-room-red", "seen"): 9, ("nav-room-sequence-purple-red", "unseen"): 1}, model="train-0b")
    pooled = {row["split"]: (row["successes"], row["episodes"])
              for row in run_panel(catalog, panels["success_by_iteration"], CAMPAIGN).rows}
    report = {g.group: (g.successes, g.episodes) for g in success_by_iteration(catalog, CAMPAIGN)[0]}
    assert pooled == {"seen": (9, 10), "unseen": (1, 10)} == {k: report[k] for k in ("seen", "unseen")}
    per_task = {row["task"]: row["evaluation"] for row in run_panel(catalog, panels["per_task"], CAMPAIGN).rows}
    assert per_task["nav-room-red"].startswith("9/10")


def test_the_success_panel_weighs_a_case_evaluated_again_with_more_episodes_as_the_report_does(tmp_path):
    from dashboards.panels import run_panel
    from dashboards.report import success_by_iteration
    from tests.dashboards.test_results import CAMPAIGN, _catalog_with_tasks, _evaluated, _register

    catalog = _catalog_with_tasks(tmp_path)
    _register(catalog, 0, {("nav-room-red", "seen"): 0, ("nav-room-sequence-red-green", "seen"): 10})
    _evaluated(catalog, "train-0", 1, episodes=50, unit="evaluate-0-again")  # its first episode succeeded
    panel = next(p for p in load_panels() if p.id == "success_by_iteration")
    pooled = {row["split"]: (row["successes"], row["episodes"]) for row in run_panel(catalog, panel, CAMPAIGN).rows}
    report = {g.group: (g.successes, g.episodes) for g in success_by_iteration(catalog, CAMPAIGN)[0]}
    assert pooled["seen"] == report["seen"] == (11, 20)


def test_the_iterations_panel_has_one_row_an_iteration_with_the_model_it_deployed(tmp_path):
    """Three training seeds of an iteration gave three rows, two of them blank."""
    from dashboards.panels import run_panel
    from tests.dashboards.test_results import CAMPAIGN, _catalog_with_tasks, _explored, _register, _training

    catalog = _catalog_with_tasks(tmp_path)
    _explored(catalog, Workspace.at(tmp_path), {"nav-room-red": [5, 6]})
    for key, seed in (("train-0", 0), ("train-s1", 1), ("train-s2", 2)):
        _training(catalog, key, seed=seed, chunk=8)
    _register(catalog, 0, {("nav-room-red", "seen"): 6})
    panel = next(p for p in load_panels() if p.id == "iterations")
    rows = run_panel(catalog, panel, CAMPAIGN).rows
    assert [(row["iteration"], row["model"], row["promoted"]) for row in rows] == [(0, "train-0", True)]


def test_the_task_page_names_an_evaluation_outside_the_campaigns_cases(tmp_path):
    """`sim2act eval --set render.mesh_detail=1.0` of the deployed model on a campaign task: its own row, named by
    its suite, after the campaign's, not indistinguishable from the model's figure beside it."""
    from dashboards.reads import task_evaluations
    from tests.dashboards.test_results import CAMPAIGN, _catalog_with_tasks, _evaluated, _register

    catalog = _catalog_with_tasks(tmp_path)
    _register(catalog, 0, {("nav-room-red", "seen"): 6})
    _evaluated(catalog, "train-0", 2, unit="evaluate-full-meshes")
    with catalog.connect() as con:  # as `sim2act eval` files it under other frames
        con.execute("UPDATE evaluations SET suite = 'campaign @ render.mesh_detail=1.0' "
                    "WHERE unit_key = 'evaluate-full-meshes'")
    rows = task_evaluations(catalog, CAMPAIGN, "nav-room-red").rows
    assert [(row["suite"], row["model_key"], row["successes"]) for row in rows] == [
        ("campaign", "train-0", 6), ("campaign @ render.mesh_detail=1.0", "train-0", 2)]


@pytest.mark.parametrize("panel, message", [
    ("{id: wipe, title: Wipe, kind: table, sql: 'DELETE FROM episodes'}",
     "panel wipe: the warehouse is read-only here: DELETE statements are refused (use SELECT)"),
    ("{id: copy, title: Copy, kind: table, sql: \"COPY episodes TO '/tmp/x.csv'\"}",
     "panel copy: the warehouse is read-only here: COPY statements are refused"),
    ("{id: odd, title: Odd, kind: table, sql: 'SELECT * FROM episodes WHERE task_id = $task'}",
     "panel odd: unknown SQL parameter(s) task"),
    ("{id: flat, title: Flat, kind: line, x: iteration, sql: 'SELECT 1 AS iteration'}",
     "panel flat: a line chart needs x and y columns"),
    ("{id: pie, title: Pie, kind: pie, sql: 'SELECT 1'}", "panel pie: kind: Input should be 'line', 'bar' or 'table'"),
])
def test_a_bad_panel_is_refused_naming_it(tmp_path, panel, message):
    path = tmp_path / "panels.yaml"
    path.write_text(f"panels:\n  - {panel}\n")
    with pytest.raises(PanelError) as refused:
        load_panels(path)
    assert message in str(refused.value) and str(path) in str(refused.value)


# -- the server alone ---------------------------------------------------------------------


def test_media_serves_the_media_folder_only(tmp_path):
    workspace = Workspace.at(tmp_path / "ws").create()
    (workspace.media / "evaluate-x-success.mp4").write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(100))
    (workspace.root / "secret.mp4").write_bytes(b"not for the page")
    (workspace.media / "link.mp4").symlink_to(workspace.root / "secret.mp4")
    (workspace.media / "notes.txt").write_text("not a video")
    with serving(workspace) as port:
        status, body = get(port, "/media/evaluate-x-success.mp4")
        assert status == 200 and body.startswith(b"\x00\x00\x00\x18ftyp")
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        connection.request("GET", "/media/evaluate-x-success.mp4", headers={"Range": "bytes=4-7"})
        response = connection.getresponse()
        assert response.status == 206 and response.read() == b"ftyp"  # what <video> asks for
        connection.request("HEAD", "/media/evaluate-x-success.mp4")  # was 405
        response = connection.getresponse()
        assert response.status == 200 and response.getheader("content-type") == "video/mp4" and response.read() == b""
        for path in ("/media/../secret.mp4", "/media/..%2Fsecret.mp4", "/media/%2e%2e/secret.mp4",
                     f"/media/{workspace.root}/secret.mp4", "/media/link.mp4", "/media/notes.txt",
                     "/media/../warehouse/catalog.duckdb", "/media/missing.mp4", "/media/a%00.mp4"):
            status, body = get(port, path)
            assert status == 404 and b"not for the page" not in body, path
        status, _ = get(port, f"/media/{'a' * 300}.mp4")  # a name the file system refuses (ENAMETOOLONG): was a 500
        assert status == 404
        status, _ = get(port, "/api/episodes/ep-1/video")  # no warehouse yet: no frames, not a 500
        assert status == 404


def test_an_empty_workspace_says_so(tmp_path):
    workspace = Workspace.at(tmp_path / "ws")
    with serving(workspace) as port:
        status, _ = get(port, "/health")
        assert status == 200
        status, body = get(port, "/api/panels")
        assert status == 200 and b'"campaigns":[]' in body and b"No data yet" in body
        Catalog(workspace.catalog).initialise()  # a warehouse with nothing in it yet
        status, body = get(port, "/api/panels")
        assert status == 200 and b'"campaigns":[]' in body and b"holds no campaign" in body
        status, _ = get(port, "/api/panels/per_task")
        assert status == 404


def test_a_missing_shard_says_what_to_do_and_a_bad_offset_is_refused(tmp_path):
    """A shard moved away by hand broke every endpoint with a bare 500; an offset past 64 bits reached DuckDB."""
    from tests.warehouse.filled import fill

    workspace = Workspace.at(tmp_path / "ws").create()
    fill(workspace, iterations=1, units=2, episodes=2, steps=5)
    with serving(workspace) as port:
        status, body = get(port, "/api/episodes?offset=99999999999999999999")
        assert status == 422
        status, body = get(port, "/api/episodes?offset=1")
        assert status == 200 and b'"offset":1' in body
        [(path,)] = Catalog(workspace.catalog).query(
            "SELECT path FROM shards WHERE table_name = 'episodes' ORDER BY path LIMIT 1")
        (workspace.warehouse / path).rename(tmp_path / "moved.parquet")
        for request in ("/api/episodes", "/api/panels/per_task"):
            status, body = get(port, request)
            assert status == 503 and b"run `sim2act warehouse verify --workspace" in body, (request, body)
        (tmp_path / "moved.parquet").rename(workspace.warehouse / path)
        # torn (DuckDB's InvalidInputException, not an IOException): was a bare 500 on every endpoint
        data = (workspace.warehouse / path).read_bytes()
        (workspace.warehouse / path).write_bytes(data[: len(data) // 2])
        for request in ("/api/episodes", "/api/panels/per_task", "/api/panels/episodes_by_iteration", "/api/panels"):
            status, body = get(port, request)
            assert status == 503 and b"run `sim2act warehouse verify --workspace" in body, (request, body)
    workspace.catalog.write_bytes(b"not a DuckDB file")  # a catalog that is not one: its own line, not a bare 500
    with serving(workspace) as port:
        status, body = get(port, "/api/episodes")
        assert status == 503 and b"catalog" in body and b"Traceback" not in body, body


def test_the_episode_browser_answers_a_page_its_count_and_its_filters_choices_in_one_read(tmp_path):
    """Six connections a page (count, rows, four choice lists), each building the views over every shard."""
    import json

    from tests.warehouse.filled import fill

    workspace = Workspace.at(tmp_path / "ws").create()
    fill(workspace, iterations=2, units=2, episodes=2, steps=5)
    catalog = Catalog(workspace.catalog)
    [(campaign,)] = catalog.query("SELECT DISTINCT campaign FROM episodes")
    expected = {"iterations": [0, 1], "tasks": sorted({t for (t,) in catalog.query("SELECT task_id FROM episodes")}),
                "explorers": sorted({e for (e,) in catalog.query("SELECT explorer FROM episodes")})}
    with serving(workspace) as port:
        status, body = get(port, "/api/episodes?limit=3&offset=1")
        assert status == 200
        page = json.loads(body)
        assert page["total"] == catalog.query("SELECT count(*) FROM episodes")[0][0] and len(page["rows"]) == 3
        assert {name: page["choices"][name] for name in expected} == expected and page["choices"]["reasons"]
        [(task,)] = catalog.query("SELECT min(task_id) FROM episodes WHERE iteration = 1")
        status, body = get(port, f"/api/episodes?iteration=1&task={task}")
        narrowed = json.loads(body)  # the choices are the campaign's, whatever the filters
        assert narrowed["choices"] == page["choices"] and narrowed["total"] < page["total"]
        assert {row["iteration"] for row in narrowed["rows"]} == {1}


# -- the page in Chromium -----------------------------------------------------------------


def _direct_rows(catalog: Catalog, sql: str, campaign: str) -> int:
    """A panel's row count with its SQL run straight on the catalog, not through the dashboard."""
    with catalog.connect(read_only=True) as con:
        return len(con.execute(sql, {"campaign": campaign}).fetchall())


def open_page(browser, url: str):
    """A page at `url` and the console errors and uncaught exceptions it has shown."""
    page = browser.new_page(viewport={"width": 1400, "height": 1000})
    errors: list[str] = []
    page.on("console", lambda message: errors.append(message.text) if message.type == "error" else None)
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.goto(url)
    page.wait_for_selector("body[data-ready=true]", state="attached", timeout=30_000)
    return page, errors


def wait_playing(page, timeout_ms: int = 20_000) -> dict:
    """Play the player and wait until it has decoded frames and its time advances."""
    page.wait_for_function("document.getElementById('player').readyState >= 2", timeout=timeout_ms)
    page.evaluate("document.getElementById('player').play()")
    page.wait_for_function("document.getElementById('player').currentTime > 0", timeout=timeout_ms)
    return page.evaluate("(({currentSrc, currentTime, readyState, videoWidth, error}) => "
                         "({src: currentSrc, time: currentTime, ready: readyState, width: videoWidth, error}))"
                         "(document.getElementById('player'))")


def test_the_page_over_a_finished_campaign(finished_campaign, browser, tmp_path):
    workspace = Workspace.at(finished_campaign[0])
    catalog = Catalog(workspace.catalog)
    shots = tmp_path / "screenshots"
    shots.mkdir()
    with serving(workspace) as port:
        page, errors = open_page(browser, f"http://127.0.0.1:{port}/")
        page.wait_for_function("[...document.querySelectorAll('section[data-panel]')]"
                               ".every(s => s.dataset.state === 'ready')", timeout=30_000)
        page.wait_for_selector("#browser[data-state=ready]", state="attached", timeout=30_000)
        page.screenshot(path=shots / "overview.png", full_page=True)

        assert page.text_content("#campaign-name") == "campaign smoke"
        for panel in load_panels():
            rows = _direct_rows(catalog, panel.sql, "smoke")
            section = page.locator(f"section[data-panel={panel.id}]")
            assert rows > 0, f"{panel.id}: the smoke campaign gives it no rows"
            drawn = {"line": "svg .point", "bar": "svg .bar", "table": "tbody tr"}[panel.kind]
            assert section.locator(drawn).count() == rows, panel.id
            if panel.kind == "line" and panel.low:
                assert section.locator("svg .interval").count() == rows  # every point has its Wilson interval

        # the per-task table: one row per task of the campaign, the task first
        tasks = [row[0] for row in catalog.query("SELECT DISTINCT task_id FROM tasks WHERE campaign = 'smoke'")]
        cells = page.locator("section[data-panel=per_task] tbody tr td:first-child").all_text_contents()
        assert sorted(cells) == sorted(tasks)

        # the episode browser lists the episodes and plays the first one, drawn from its stored frames
        episodes = catalog.query("SELECT count(*) FROM episodes WHERE campaign = 'smoke'")[0][0]
        assert page.locator("#episodes tbody tr").count() == min(episodes, 50)
        assert page.text_content("#page-info").endswith(f"of {episodes}")
        first = page.get_attribute("#episodes tbody tr.selected", "data-episode")
        instruction = catalog.query("SELECT instruction FROM episodes WHERE episode_id = ?", [first])[0][0]
        assert instruction in page.text_content("#episode-info")
        played = wait_playing(page)
        assert played["src"].endswith(f"/api/episodes/{first}/video") and played["width"] >= 256, played
        page.locator("#browser").screenshot(path=shots / "episode.png")

        # an evaluation rollout of the same task: the evaluate stage's own MP4 from the media folder
        page.locator("#rollouts button[data-video]").first.click()
        played = wait_playing(page)
        assert "/media/evaluate-" in played["src"] and played["error"] is None, played
        page.locator("#browser").screenshot(path=shots / "rollout.png")
        assert errors == [], errors
    print(f"screenshots: {shots}")


def test_the_page_without_data_says_so(browser, tmp_path):
    with serving(Workspace.at(tmp_path / "empty")) as port:
        page, errors = open_page(browser, f"http://127.0.0.1:{port}/")
        assert page.is_visible("#message") and "No data yet" in page.text_content("#message")
        assert page.locator("section[data-panel]").count() == 0 and page.is_hidden("#browser")
        assert errors == [], errors


def test_sim2act_dashboard_serves_and_answers_health(tmp_path):
    """The entry point `sim2act up` runs: a process that answers /health."""
    import os
    import sys

    port = _free_port()
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    # video folders left by a SIGKILLed dashboard (no shutdown to remove them), a running one's, an older sim2act's
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    left = {f"sim2act-dashboard-{gone.stdout.strip()}-x1y2", f"sim2act-dashboard-{os.getpid()}-a1b2", "sim2act-dashboard-q9w8"}
    for name in left:
        (scratch / name).mkdir()
    process = subprocess.Popen([SIM2ACT, "dashboard", "--workspace", str(tmp_path / "ws"), "--port", str(port)],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               env={**os.environ, "TMPDIR": str(scratch)})
    try:
        deadline = time.monotonic() + 60
        while True:
            try:
                status, body = get(port, "/health")
                break
            except OSError:
                assert process.poll() is None and time.monotonic() < deadline, process.stdout.read()
                time.sleep(0.2)
        assert status == 200 and b'"status":"ok"' in body
        [own] = [p.name for p in scratch.iterdir() if p.name.startswith(f"sim2act-dashboard-{process.pid}-")]  # its videos
        assert {p.name for p in scratch.iterdir()} == {own} | left - {f"sim2act-dashboard-{gone.stdout.strip()}-x1y2"}
        # on loopback it answers loopback names only: a page elsewhere cannot read it through DNS rebinding
        connection = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
        connection.request("GET", "/health", headers={"Host": f"attacker.example:{port}"})
        assert connection.getresponse().status == 400
    finally:
        process.terminate()  # what `sim2act down` sends
        process.wait(timeout=30)
    assert own not in {p.name for p in scratch.iterdir()}  # its videos gone with it


def test_bench_panels_times_every_panel_on_a_finished_campaign(finished_campaign, tmp_path):
    """`sim2act bench panels`: one row per panel, each with the rows the page would draw."""
    out = tmp_path / "panels.md"
    done = subprocess.run([SIM2ACT, "bench", "panels", "--workspace", str(finished_campaign[0]), "--repeats", "1",
                           "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    catalog = Catalog(Workspace.at(finished_campaign[0]).catalog)
    table = {line.split(" | ")[0].lstrip("| "): line.split(" | ") for line in out.read_text().splitlines()
             if line.startswith("| ") and not line.startswith("| panel")}
    assert list(table) == [panel.id for panel in load_panels()]
    for panel in load_panels():
        assert int(table[panel.id][1].replace(",", "")) == _direct_rows(catalog, panel.sql, "smoke"), panel.id
    wrong = subprocess.run([SIM2ACT, "bench", "panels", "--workspace", str(finished_campaign[0]), "--campaign", "nope"],
                           capture_output=True, text=True, timeout=120)
    assert wrong.returncode == 2 and "expected --campaign, one of smoke; got nope" in wrong.stderr
