// The dashboard page: panels from /api/panels drawn as inline SVG or tables, and the episode
// browser. No libraries: the page must work offline, served by `python -m dashboards`.
"use strict";

const SVG = "http://www.w3.org/2000/svg";
// Colours that mean the same thing on every panel; anything else takes the palette in order.
const NAMED_COLOURS = {
  seen: "#2563eb", unseen: "#dc2626", unseen_paraphrase: "#9333ea",
  kept: "#059669", rejected: "#dc2626", not_successful: "#f59e0b", low_return: "#dc2626",
  duplicate: "#8b5cf6", env_error: "#111827", invalid_values: "#be185d",
  action_out_of_bounds: "#0891b2", bad_image: "#6b7280", expert: "#64748b",
};
const PALETTE = ["#2563eb", "#0891b2", "#7c3aed", "#db2777", "#65a30d", "#ea580c", "#0d9488", "#9333ea", "#475569"];

const PAGE = 50;  // episodes per page of the browser
const state = { campaign: null, panels: [], offset: 0, total: 0, filters: {}, selected: null };

// -- small helpers ------------------------------------------------------------------------

function node(name, attrs = {}, parent = null, text = null) {
  const element = name.startsWith("svg:") ? document.createElementNS(SVG, name.slice(4)) : document.createElement(name);
  for (const [key, value] of Object.entries(attrs)) element.setAttribute(key, value);
  if (text !== null) element.textContent = text;
  if (parent) parent.appendChild(element);
  return element;
}

async function getJSON(url) {
  const response = await fetch(url);
  const body = await response.json().catch(() => ({}));
  if (!response.ok) throw new Error(body.detail || `${response.status} ${response.statusText}`);
  return body;
}

function query(params) {
  const search = new URLSearchParams();
  for (const [key, value] of Object.entries(params)) if (value !== null && value !== undefined && value !== "") search.set(key, value);
  return search.toString();
}

function formatValue(value, percent) {
  if (value === null || value === undefined) return "—";
  if (typeof value === "boolean") return value ? "yes" : "no";
  if (typeof value !== "number") return String(value);
  if (percent) return `${Math.round(value * 100)}%`;
  if (Number.isInteger(value)) return value.toLocaleString("en");
  return Math.abs(value) >= 100 ? value.toFixed(0) : value.toFixed(2);
}

function colourScale(names) {
  let next = 0;
  const colours = {};
  for (const name of names) colours[name] = NAMED_COLOURS[name] || PALETTE[next++ % PALETTE.length];
  return colours;
}

function distinct(values) {
  return [...new Set(values)];
}

// An axis from 0 past `max` in round steps (whole numbers: the counts are episodes); shares run 0-100%.
function axisTicks(max, percent) {
  if (percent) return { top: Math.max(1, max), ticks: [0, 0.25, 0.5, 0.75, 1] };
  const raw = Math.max(max, 1) / 5;
  const magnitude = 10 ** Math.floor(Math.log10(raw));
  const step = Math.max(1, [1, 2, 5, 10].map((m) => m * magnitude).find((s) => s >= raw));
  const top = Math.max(step, Math.ceil(max / step) * step);
  const ticks = [];
  for (let tick = 0; tick <= top; tick += step) ticks.push(tick);
  return { top, ticks };
}

function rowTitle(row) {
  return Object.entries(row).map(([k, v]) => `${k}: ${formatValue(v, false)}`).join("\n");
}

function legend(container, title, colours) {
  const box = node("div", { class: "legend" }, container);
  if (title) node("span", { class: "name" }, box, title);
  for (const [name, colour] of Object.entries(colours)) {
    const item = node("span", {}, box);
    node("span", { class: "swatch", style: `background:${colour}` }, item);
    item.appendChild(document.createTextNode(name));
  }
}

// -- charts -------------------------------------------------------------------------------

function yAxis(svg, panel, box, axis) {
  const percent = panel.percent.includes(panel.y);
  for (const tick of axis.ticks) {
    const y = box.bottom - (tick / axis.top) * (box.bottom - box.top);
    node("svg:line", { class: "grid-line", x1: box.left, x2: box.right, y1: y, y2: y }, svg);
    node("svg:text", { x: box.left - 6, y: y + 4, "text-anchor": "end" }, svg, formatValue(tick, percent));
  }
  node("svg:text", { class: "title", x: 12, y: (box.top + box.bottom) / 2, "text-anchor": "middle",
    transform: `rotate(-90 12 ${(box.top + box.bottom) / 2})` }, svg, panel.y.replaceAll("_", " "));
}

function lineChart(body, panel, rows) {
  const width = Math.max(320, body.clientWidth);
  const height = 270;
  const box = { left: 52, right: width - 16, top: 14, bottom: height - 38 };
  const svg = node("svg:svg", { class: "chart", viewBox: `0 0 ${width} ${height}`, height }, body);
  const numeric = rows.every((r) => typeof r[panel.x] === "number");
  const xs = distinct(rows.map((r) => r[panel.x]));
  if (numeric) xs.sort((a, b) => a - b);
  const series = panel.series ? distinct(rows.map((r) => r[panel.series])) : [panel.y];
  const colours = colourScale(series);
  const percent = panel.percent.includes(panel.y);
  const highs = rows.map((r) => Math.max(r[panel.y] ?? 0, panel.high ? r[panel.high] ?? 0 : 0));
  const axis = axisTicks(Math.max(...highs), percent);
  yAxis(svg, panel, box, axis);
  const step = (box.right - box.left) / Math.max(1, xs.length);
  const xOf = (value) => box.left + step * (xs.indexOf(value) + 0.5);
  const yOf = (value) => box.bottom - (value / axis.top) * (box.bottom - box.top);
  for (const value of xs) node("svg:text", { x: xOf(value), y: box.bottom + 16, "text-anchor": "middle" }, svg, String(value));
  node("svg:text", { class: "title", x: (box.left + box.right) / 2, y: height - 4, "text-anchor": "middle" }, svg,
    panel.x.replaceAll("_", " "));
  series.forEach((name, index) => {
    // series side by side at each x, so their intervals do not hide each other
    const dodge = (index - (series.length - 1) / 2) * 7;
    const mine = rows.filter((r) => !panel.series || r[panel.series] === name)
      .sort((a, b) => xs.indexOf(a[panel.x]) - xs.indexOf(b[panel.x]));
    const colour = colours[name];
    const points = mine.filter((r) => r[panel.y] !== null).map((r) => `${xOf(r[panel.x]) + dodge},${yOf(r[panel.y])}`);
    node("svg:polyline", { points: points.join(" "), fill: "none", stroke: colour, "stroke-width": 2, class: "series-line" }, svg);
    for (const row of mine) {
      const x = xOf(row[panel.x]) + dodge;
      if (panel.low && row[panel.low] !== null && row[panel.high] !== null) {
        const [low, high] = [yOf(row[panel.low]), yOf(row[panel.high])];
        const bar = node("svg:g", { class: "interval", stroke: colour, "stroke-width": 1.5, opacity: 0.7 }, svg);
        node("svg:line", { x1: x, x2: x, y1: low, y2: high }, bar);
        node("svg:line", { x1: x - 4, x2: x + 4, y1: low, y2: low }, bar);
        node("svg:line", { x1: x - 4, x2: x + 4, y1: high, y2: high }, bar);
      }
      const point = node("svg:circle", { class: "point", cx: x, cy: yOf(row[panel.y] ?? 0), r: 5, fill: colour }, svg);
      node("svg:title", {}, point, rowTitle(row));
    }
  });
  if (panel.series) legend(body, panel.series, colours);
}

function barChart(body, panel, rows) {
  const categories = distinct(rows.map((r) => r[panel.x]));
  const series = panel.series ? distinct(rows.map((r) => r[panel.series])) : [panel.y];
  const colours = colourScale(series.map(String));
  const percent = panel.percent.includes(panel.y);
  const totals = new Map(categories.map((c) => [c, 0]));
  for (const row of rows) totals.set(row[panel.x], totals.get(row[panel.x]) + (row[panel.y] ?? 0));
  const axis = axisTicks(Math.max(...totals.values()), percent);
  const width = Math.max(320, body.clientWidth);
  const longest = Math.max(...categories.map((c) => String(c).length));
  const box = panel.horizontal
    ? { left: Math.min(260, 16 + longest * 6.6), right: width - 40, top: 8, bottom: 8 + categories.length * 24 }
    : { left: 52, right: width - 16, top: 14, bottom: 232 };
  const height = box.bottom + 38;
  const svg = node("svg:svg", { class: "chart", viewBox: `0 0 ${width} ${height}`, height }, body);
  const band = ((panel.horizontal ? box.bottom - box.top : box.right - box.left) / categories.length);
  const thickness = Math.min(panel.horizontal ? 18 : 56, band * 0.7);
  const length = (value) => (value / axis.top) * (panel.horizontal ? box.right - box.left : box.bottom - box.top);
  if (panel.horizontal) {
    for (const tick of axis.ticks) {
      const x = box.left + (tick / axis.top) * (box.right - box.left);
      node("svg:line", { class: "grid-line", x1: x, x2: x, y1: box.top, y2: box.bottom }, svg);
      node("svg:text", { x, y: box.bottom + 14, "text-anchor": "middle" }, svg, formatValue(tick, percent));
    }
    node("svg:text", { class: "title", x: (box.left + box.right) / 2, y: height - 6, "text-anchor": "middle" }, svg,
      panel.y.replaceAll("_", " "));
  } else {
    yAxis(svg, panel, box, axis);
    node("svg:text", { class: "title", x: (box.left + box.right) / 2, y: height - 4, "text-anchor": "middle" }, svg,
      panel.x.replaceAll("_", " "));
  }
  const stacked = new Map(categories.map((c) => [c, 0]));
  categories.forEach((category, index) => {
    const centre = (panel.horizontal ? box.top : box.left) + band * (index + 0.5);
    const label = panel.horizontal
      ? node("svg:text", { x: box.left - 6, y: centre + 4, "text-anchor": "end" }, svg, String(category))
      : node("svg:text", { x: centre, y: box.bottom + 16, "text-anchor": "middle" }, svg, String(category));
    label.classList.add("category");
    if (!percent) {  // the stack's total at its end; shares of 100% need none
      const end = length(totals.get(category));
      node("svg:text", panel.horizontal
        ? { class: "total", x: box.left + end + 4, y: centre + 4 }
        : { class: "total", x: centre, y: box.bottom - end - 4, "text-anchor": "middle" }, svg,
      formatValue(totals.get(category), false));
    }
  });
  for (const row of rows) {
    const category = row[panel.x];
    const centre = (panel.horizontal ? box.top : box.left) + band * (categories.indexOf(category) + 0.5);
    const start = length(stacked.get(category));
    const size = length(row[panel.y] ?? 0);
    stacked.set(category, stacked.get(category) + (row[panel.y] ?? 0));
    const colour = colours[panel.series ? String(row[panel.series]) : panel.y];
    const rect = node("svg:rect", panel.horizontal
      ? { class: "bar", x: box.left + start, y: centre - thickness / 2, width: size, height: thickness, fill: colour }
      : { class: "bar", x: centre - thickness / 2, y: box.bottom - start - size, width: thickness, height: size, fill: colour },
    svg);
    node("svg:title", {}, rect, rowTitle(row));
  }
  const baseline = panel.horizontal
    ? { x1: box.left, x2: box.left, y1: box.top, y2: box.bottom }
    : { x1: box.left, x2: box.right, y1: box.bottom, y2: box.bottom };
  node("svg:line", { class: "axis", ...baseline }, svg);
  if (panel.series) legend(body, panel.series, colours);
}

function table(body, panel, columns, rows) {
  const wrap = node("div", { class: "table-wrap" }, body);
  const element = node("table", { class: "panel-table" }, wrap);
  const head = node("tr", {}, node("thead", {}, element));
  const numeric = columns.map((c) => rows.some((r) => typeof r[c] === "number"));
  columns.forEach((c, i) => node("th", numeric[i] ? { class: "num" } : {}, head, c.replaceAll("_", " ")));
  const tbody = node("tbody", {}, element);
  for (const row of rows) {
    const tr = node("tr", {}, tbody);
    columns.forEach((c, i) => {
      const value = row[c];
      const kind = value === null ? "null" : typeof value === "boolean" ? (value ? "yes" : "no") : numeric[i] ? "num"
        : String(value).length > 40 ? "text" : "";
      node("td", kind ? { class: kind } : {}, tr, formatValue(value, panel.percent.includes(c)));
    });
  }
}

// -- panels -------------------------------------------------------------------------------

function panelShell(panel) {
  const section = node("section", { class: `panel${panel.wide ? " wide" : ""}`, "data-panel": panel.id, "data-kind": panel.kind },
    document.getElementById("panels"));
  node("h2", {}, section, panel.title);
  if (panel.description) node("p", { class: "description" }, section, panel.description);
  return node("div", { class: "body" }, section);
}

async function drawPanel(panel) {
  const section = document.querySelector(`section[data-panel="${panel.id}"]`);
  const body = section.querySelector(".body");
  section.dataset.state = "loading";
  try {
    const data = await getJSON(`/api/panels/${panel.id}?${query({ campaign: state.campaign })}`);
    body.replaceChildren();
    if (!data.rows.length) {
      node("p", { class: "status" }, body, "No rows for this campaign (yet).");
    } else if (panel.kind === "line") {
      lineChart(body, panel, data.rows);
    } else if (panel.kind === "bar") {
      barChart(body, panel, data.rows);
    } else {
      table(body, panel, data.columns, data.rows);
    }
    section.dataset.rows = data.rows.length;
    section.dataset.state = "ready";
  } catch (error) {
    body.replaceChildren();
    node("p", { class: "status error" }, body, error.message);
    section.dataset.state = "error";
  }
}

// -- the episode browser ------------------------------------------------------------------

function fillSelect(select, values, current, label) {
  select.replaceChildren();
  node("option", { value: "" }, select, `all ${label}`);
  for (const value of values) {
    const option = node("option", { value: String(value) }, select, String(value));
    if (String(value) === current) option.selected = true;
  }
}

function play(src, caption) {
  const player = document.getElementById("player");
  player.src = src;
  document.getElementById("caption").textContent = caption;
  player.play().catch(() => {});  // refused before any user gesture in some browsers: the controls remain
}

function showEpisode(row, tr) {
  state.selected = row.episode_id;
  for (const other of document.querySelectorAll("#episodes tr.selected")) other.classList.remove("selected");
  tr.classList.add("selected");
  play(`/api/episodes/${encodeURIComponent(row.episode_id)}/video`,
    `${row.episode_id}: as explored, ${row.num_steps} steps, from the frames stored in the warehouse`);
  const info = document.getElementById("episode-info");
  info.replaceChildren();
  node("p", { class: "instruction-text" }, info, `“${row.instruction}”`);
  const facts = node("dl", { class: "facts" }, info);
  const outcome = row.kept === null ? "not filtered yet" : row.kept ? "kept" : `rejected: ${row.reason}${row.detail ? ` (${row.detail})` : ""}`;
  for (const [name, value] of [["task", `${row.task_id} (${row.family}, ${row.split})`], ["iteration", row.iteration],
    ["explorer", row.explorer], ["return", formatValue(row.episode_return, false)], ["success", formatValue(row.success, false)],
    ["filter", outcome], ["error", row.error]]) {
    if (value === null || value === undefined) continue;
    node("dt", {}, facts, name);
    node("dd", {}, facts, String(value));
  }
  return showRollouts(row.task_id);
}

async function showRollouts(task) {
  const box = document.getElementById("rollouts");
  box.replaceChildren();
  const data = await getJSON(`/api/evaluations?${query({ campaign: state.campaign, task })}`);
  if (!data.rows.length) node("p", { class: "caption" }, box, "No evaluation of this task yet.");
  for (const row of data.rows) {
    const line = node("div", { class: "rollout" }, box);
    node("span", { class: "what", title: `${row.model_key}: “${row.instruction}”` }, line,
      `it. ${row.iteration} · ${row.agent} · ${row.split} · ${row.successes}/${row.episodes}`
      + (row.suite === "campaign" ? "" : ` · ${row.suite}`));  // another task set or other frames: said
    for (const [kind, url] of [["success", row.success_url], ["failure", row.failure_url]]) {
      if (!url) {  // keeps the buttons in their columns
        node("span", {}, line);
        continue;
      }
      const button = node("button", { type: "button", "data-video": url }, line, `▶ ${kind}`);
      button.addEventListener("click", () => {
        for (const other of box.querySelectorAll("button.playing")) other.classList.remove("playing");
        button.classList.add("playing");
        play(url, `evaluation of ${row.model_key} (iteration ${row.iteration}), ${row.split}, “${row.instruction}”: its first ${kind}`);
      });
    }
  }
}

// "policy:sim2act-curriculum/1 via subtasks" -> "policy v1 via subtasks": the list is narrow, the
// model's name is the campaign's own; the full name is in the row's tooltip and the details.
function shortExplorer(explorer) {
  return explorer.replace(/^policy:[^/\s]+\/(\d+)/, "policy v$1");
}

let episodeRequests = 0;  // which page request is the latest: an earlier one answering after it is dropped

async function loadEpisodes() {
  document.getElementById("browser").dataset.state = "loading";
  const asked = ++episodeRequests;
  const offset = state.offset;
  const data = await getJSON(`/api/episodes?${query({ campaign: state.campaign, offset, limit: PAGE, ...state.filters })}`);
  if (asked !== episodeRequests) return;  // "next" twice, or a filter changed meanwhile: its rows would be mislabelled
  state.total = data.total;
  for (const select of document.querySelectorAll("[data-filter]")) {
    const name = select.dataset.filter;
    fillSelect(select, data.choices[{ iteration: "iterations", task: "tasks", explorer: "explorers", reason: "reasons" }[name]],
      state.filters[name] || "", { iteration: "iterations", task: "tasks", explorer: "explorers", reason: "decisions" }[name]);
  }
  const tbody = document.querySelector("#episodes tbody");
  tbody.replaceChildren();
  for (const row of data.rows) {
    const tr = node("tr", { "data-episode": row.episode_id }, tbody);
    node("td", { class: "num" }, tr, String(row.iteration));
    node("td", {}, tr, row.task_id);
    node("td", { class: "instruction" }, tr, row.instruction);
    node("td", { class: "explorer", title: row.explorer }, tr, shortExplorer(row.explorer));
    node("td", { class: "num" }, tr, formatValue(row.episode_return, false));
    node("td", { class: "num" }, tr, String(row.num_steps));
    node("td", { class: row.success ? "yes" : "no" }, tr, row.success ? "✓" : "✗");
    const decision = node("td", {}, tr);
    node("span", { class: `tag ${row.kept ? "kept" : row.kept === false ? "rejected" : ""}` }, decision, row.reason || "not filtered yet");
    tr.addEventListener("click", () => showEpisode(row, tr));
    if (row.episode_id === state.selected) tr.classList.add("selected");
  }
  const last = Math.min(offset + data.rows.length, state.total);
  document.getElementById("page-info").textContent = state.total ? `${offset + 1}–${last} of ${state.total}` : "no episodes";
  document.getElementById("prev").disabled = offset === 0;
  document.getElementById("next").disabled = last >= state.total;
  if (!state.selected && data.rows.length) await showEpisode(data.rows[0], tbody.firstElementChild);
  document.getElementById("browser").dataset.state = "ready";
}

// -- the page -----------------------------------------------------------------------------

async function load() {
  const data = await getJSON("/api/panels");
  const message = document.getElementById("message");
  const picker = document.getElementById("campaign-picker");
  const select = document.getElementById("campaign");
  document.getElementById("panels").replaceChildren();
  if (!data.campaigns.length) {
    message.textContent = data.message;
    message.hidden = false;
    document.getElementById("browser").hidden = true;
    return;
  }
  message.hidden = true;
  if (!data.campaigns.includes(state.campaign)) {
    state.campaign = data.campaigns[0];
    state.selected = null;
  }
  select.replaceChildren(...data.campaigns.map((c) => node("option", { value: c }, null, c)));
  select.value = state.campaign;
  picker.hidden = data.campaigns.length < 2;  // one campaign: named, nothing to pick
  document.getElementById("campaign-name").textContent = data.campaigns.length < 2 ? `campaign ${state.campaign}` : "";
  state.panels = data.panels;
  for (const panel of data.panels) panelShell(panel);
  document.getElementById("browser").hidden = false;
  await Promise.all([...data.panels.map(drawPanel), loadEpisodes()]);
}

function start() {
  document.getElementById("campaign").addEventListener("change", (event) => {
    Object.assign(state, { campaign: event.target.value, offset: 0, filters: {}, selected: null });
    load();
  });
  document.getElementById("refresh").addEventListener("click", () => load());
  let timer = null;
  document.getElementById("auto-refresh").addEventListener("change", (event) => {
    clearInterval(timer);
    if (event.target.checked) timer = setInterval(() => load(), 30000);
  });
  for (const select of document.querySelectorAll("[data-filter]")) {
    select.addEventListener("change", () => {
      state.filters[select.dataset.filter] = select.value;
      state.offset = 0;
      loadEpisodes();
    });
  }
  document.getElementById("prev").addEventListener("click", () => {
    state.offset = Math.max(0, state.offset - PAGE);
    loadEpisodes();
  });
  document.getElementById("next").addEventListener("click", () => {
    state.offset += PAGE;
    loadEpisodes();
  });
  load().then(() => { document.body.dataset.ready = "true"; },
    (error) => {
      const message = document.getElementById("message");
      message.textContent = `The dashboard could not read the warehouse: ${error.message}`;
      message.hidden = false;
      document.body.dataset.ready = "true";
    });
}

start();
