// Tessera's dashboard: three views (renders, one render, workers) over the coordinator's JSON
// API, kept current by its event stream. Every value from the server goes into the page as
// text, never as markup.
"use strict";

let session = null;      // { user, role, csrf, login }
let latest = null;       // the last "state" event, with the "changes" since: { renders, workers }
let map = "none";        // the tile map drawn over the preview: none, samples or error
let oneToOne = false;     // the preview at its own pixels, or fitted to the window
let exposure = 0;         // stops of exposure the page shows the preview at
let target = null;        // the open render's target error, if adaptive
let quote = null;         // the open render's quote while it runs (Core::forecast)
let raw = false;          // a denoised render's preview shows its raw colour
const evText = () => (exposure > 0 ? "+" : "") + exposure + " EV";
let lastTiles = 0;       // when the tile map was last fetched

const $ = (id) => document.getElementById(id);

function el(tag, attrs, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "class") e.className = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else e.setAttribute(k, v);
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined) continue;
    e.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return e;
}

async function api(path, options) {
  const r = await fetch(path, Object.assign({ credentials: "same-origin" }, options || {}));
  if (r.status === 401) { location.reload(); throw new Error("logged out"); }
  const body = r.headers.get("content-type")?.includes("json") ? await r.json() : null;
  if (!r.ok) throw new Error(body?.error || r.statusText);
  return body;
}

function act(path) {
  return api(path, { method: "POST", headers: { "x-tessera-csrf": session.csrf } });
}

// A render's state as the page shows it: a running render that is paused shows "paused".
const stateOf = (r) => (r.state === "running" && r.paused ? "paused" : r.state);

// The server's clock minus this page's, in seconds: a running render's elapsed time is counted
// here from when it started by the server's clock (its row need not change every second).
let skew = 0;

function elapsedOf(r) {
  if (r.started_at === null || r.started_at === undefined) return r.elapsed_seconds;
  return Math.max(0, Date.now() / 1000 + skew - r.started_at);
}

// A scene as the lists show it: its file's name, not the submitter's path to it (which the
// tooltip and the render's settings keep).
const sceneName = (s) => String(s).split(/[\\/]/).pop();

// A time (seconds since the Unix epoch) in the browser's local time: the hour today, the
// date and hour before.
function when(t) {
  if (!t) return "–";
  const d = new Date(t * 1000);
  const hm = d.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" });
  return d.toDateString() === new Date().toDateString() ? hm : d.toLocaleDateString() + " " + hm;
}

// A render's or a sequence's stored log into `pre`: each line with its local time, newest
// last, and how many older lines were dropped.
let logRead = 0; // when a render page last read its log (at most every 2 s as it updates)
async function loadLog(id, pre) {
  const page = await api("/api/renders/" + encodeURIComponent(id) + "/log");
  const lines = page.lines.map((l) => new Date(l.at * 1000).toLocaleTimeString() + "  " + l.line);
  if (page.dropped) lines.unshift(`(${page.dropped} older lines dropped)`);
  pre.textContent = lines.join("\n");
  pre.scrollTop = pre.scrollHeight;
}

function duration(s) {
  if (s === null || s === undefined || !isFinite(s) || s < 0) return "–";
  if (s < 60) return s.toFixed(0) + " s";
  if (s < 3600) return Math.floor(s / 60) + " min " + Math.floor(s % 60) + " s";
  return Math.floor(s / 3600) + " h " + Math.floor((s % 3600) / 60) + " min";
}

function count(n) {
  if (n >= 1e9) return (n / 1e9).toFixed(2) + " G";
  if (n >= 1e6) return (n / 1e6).toFixed(2) + " M";
  if (n >= 1e3) return (n / 1e3).toFixed(1) + " k";
  return String(Math.round(n));
}

function progress(r) {
  const f = r.passes_total ? r.passes_done / r.passes_total : 0;
  return el("span", {}, el("span", { class: "bar" }, el("i", {})), " " + (100 * f).toFixed(1) + " %");
}

function setBar(node, r) {
  const f = r.passes_total ? r.passes_done / r.passes_total : 0;
  node.querySelector(".bar > i").style.width = (100 * f).toFixed(1) + "%";
}

function strip(seq) {
  const s = el("span", { class: "strip", title: `${seq.frames_done} done, ${seq.frames_running} running, ${seq.frames_queued} queued, ${seq.frames_failed} failed` });
  const kinds = [["done", seq.frames_done], ["failed", seq.frames_failed], ["running", seq.frames_running], ["", seq.frames_queued]];
  for (const [kind, n] of kinds) for (let i = 0; i < Math.min(n, 400); i++) s.append(el("i", { class: kind }));
  return s;
}

// ---- the renders ----------------------------------------------------------------------------

// The list's filters, order and page, kept while the page lives.
const listing = { owner: "", state: "", sort: "newest", page: 0, gone: "" };
const PAGE_ROWS = 50;

// A select of `options` ([value, label]) bound to listing[key]; a change redraws the list.
function chooser(key, options, label) {
  const s = el("select", { id: "list-" + key, title: label }, options.map(([v, l]) => el("option", { value: v }, l)));
  s.value = listing[key];
  s.addEventListener("change", () => { listing[key] = s.value; listing.page = 0; route(); });
  return el("label", { class: "exposure" }, label, s);
}

function rendersView() {
  const all = latest?.renders || [];
  const owners = [...new Set(all.map((r) => r.owner))].sort();
  let rows = all.filter((r) => (!listing.owner || r.owner === listing.owner) && (!listing.state || stateOf(r) === listing.state));
  if (listing.sort === "priority") rows = [...rows].sort((a, b) => b.priority - a.priority);
  const pages = Math.max(1, Math.ceil(rows.length / PAGE_ROWS));
  listing.page = Math.min(listing.page, pages - 1);
  const shown = rows.slice(listing.page * PAGE_ROWS, (listing.page + 1) * PAGE_ROWS);
  const turn = (by, label, id) => {
    const b = el("button", { id }, label);
    b.disabled = listing.page + by < 0 || listing.page + by >= pages;
    b.addEventListener("click", () => { listing.page += by; route(); });
    return b;
  };
  const controls = el("div", { class: "controls" },
    chooser("owner", [["", "everyone"], ...owners.map((o) => [o, o || "(no owner)"])], "owner"),
    chooser("state", [["", "any"], ...["running", "paused", "done", "failed", "cancelled"].map((s) => [s, s])], "state"),
    chooser("sort", [["newest", "newest first"], ["priority", "highest priority first"]], "order"),
    turn(-1, "Newer", "page-prev"), el("span", { class: "dim", id: "page-of" }, `page ${listing.page + 1} of ${pages} (${rows.length} renders)`), turn(1, "Older", "page-next"));
  const table = el("table", { id: "renders" },
    el("tr", {}, ["render", "scene", "state", "priority / pool", "owner", "submitted", "progress", "samples", "error", "ran", "ETA", "workers"].map((h) => el("th", {}, h))));
  for (const r of shown) {
    const bar = progress(r);
    setBar(bar, r);
    table.append(el("tr", { id: "render-" + r.id, "data-state": stateOf(r) },
      el("td", {}, el("a", { href: "#/render/" + r.id }, r.id)),
      el("td", { title: r.scene }, r.name ? [el("b", {}, r.name), " ", el("span", { class: "dim" }, sceneName(r.scene))] : sceneName(r.scene)),
      el("td", { class: "state-" + stateOf(r) }, stateOf(r), r.message ? el("div", { class: "dim" }, r.message) : null),
      el("td", { class: "num", title: r.placement ? "runs on " + r.placement : "runs on any worker" }, String(r.priority), r.placement ? el("div", { class: "dim" }, r.placement) : null),
      el("td", {}, r.owner || "–"),
      el("td", { class: "num" }, when(r.submitted_at)),
      el("td", {}, r.sequence ? strip(r.sequence) : bar),
      el("td", { class: "num" }, count(r.samples_done)),
      el("td", { class: "num" }, r.error ? (100 * r.error).toFixed(2) + " %" : "–"),
      el("td", { class: "num elapsed", "data-id": r.id }, duration(elapsedOf(r))),
      el("td", { class: "num" }, eta(r)),
      el("td", { class: "num" }, r.workers)));
  }
  if (!all.length) return [el("h2", {}, "Renders"), el("p", { class: "dim" }, "No renders yet: submit one with tessera submit.")];
  return [el("h2", {}, "Renders"), controls, shown.length ? table : el("p", { class: "dim" }, "No render matches these filters.")];
}

// ---- one render -----------------------------------------------------------------------------

// A button that retries a failed or cancelled render (or a sequence's such frames), keeping
// what it merged.
function retryButton(id, label) {
  const b = el("button", { class: "retry", "data-id": id }, label);
  b.addEventListener("click", async () => {
    b.disabled = true;
    try { await act("/api/renders/" + encodeURIComponent(id) + "/retry"); b.textContent = "Queued again"; }
    catch (e) { b.textContent = "Retry failed: " + e.message; }
  });
  return b;
}

// A sequence's frames, a page of them at a time: each with its state, samples, error, the
// workers on it, how long it ran, its downloads and a retry where it failed or was cancelled.
function framesTable(detail, chosen) {
  const table = el("table", { id: "frames", "data-key": frameKey(detail.info) },
    el("tr", {}, ["frame", "state", "samples", "error", "workers", "ended", "ran", "download", ""].map((h) => el("th", {}, h))));
  for (const f of detail.frames || []) {
    const links = f.state === "done"
      ? [el("a", { class: "frame-exr", href: `/api/renders/${f.id}/image.exr` }, "EXR"), " ", el("a", { href: `/api/renders/${f.id}/image.png` }, "PNG")]
      : "–";
    const row = el("tr", { id: "frame-" + f.frame, "data-state": f.state, class: f.frame === chosen?.frame ? "chosen" : "", title: "show this frame's preview, settings and log below" },
      el("td", {}, el("a", { href: "#/render/" + f.id }, String(f.frame))),
      el("td", { class: "state-" + stateOf(f) }, stateOf(f), f.message ? el("div", { class: "dim" }, f.message) : null),
      el("td", { class: "num" }, count(f.samples_done)),
      el("td", { class: "num" }, f.error ? (100 * f.error).toFixed(2) + " %" : "–"),
      el("td", {}, f.worker_names.length ? f.worker_names.join(", ") : "–"),
      el("td", { class: "num" }, when(f.ended_at)),
      el("td", { class: "num" }, duration(elapsedOf(f))),
      el("td", {}, links),
      el("td", {}, f.state === "failed" || f.state === "cancelled" ? retryButton(f.id, "Retry") : null));
    row.addEventListener("click", (e) => {
      if (e.target.closest("a, button")) return;
      framesChosen.set(detail.info.id, f.frame);
      route();
    });
    table.append(row);
  }
  const shown = (detail.frames || []).length;
  const pager = el("p", { class: "dim" }, `frames ${detail.from + 1}–${detail.from + shown} of ${detail.frames_total} `);
  const go = (from) => { framesFrom.set(detail.info.id, Math.max(0, from)); route(); };
  if (detail.from > 0) pager.append(el("button", { onclick: () => go(detail.from - 200) }, "earlier"));
  if (detail.from + shown < detail.frames_total) pager.append(el("button", { onclick: () => go(detail.from + 200) }, "later"));
  return [table, pager];
}

// Where each sequence's page of frames starts.
const framesFrom = new Map();

// The frame each sequence's page shows under its table (by frame number): the one the user
// clicked, else the first one rendering, else the last one done, else the first listed.
const framesChosen = new Map();
function chosenFrame(detail) {
  const frames = detail.frames || [];
  const want = framesChosen.get(detail.info.id);
  return frames.find((f) => f.frame === want)
    || frames.find((f) => f.state === "running" && f.samples_done > 0)
    || [...frames].reverse().find((f) => f.state === "done")
    || frames[0];
}

// The chosen frame's preview, settings and log, as a still's page shows them.
async function framePanel(f) {
  const d = await api("/api/renders/" + encodeURIComponent(f.id));
  const version = `${d.info.samples_done}:${d.info.state}`;
  const img = el("img", { id: "frame-preview", alt: `frame ${f.frame}'s merged image so far`,
    src: `/api/renders/${encodeURIComponent(f.id)}/preview.jpg?v=${encodeURIComponent(version)}` });
  const log = el("pre", { class: "log", id: "frame-log" });
  loadLog(f.id, log).catch(() => {});
  const settings = el("dl", { id: "frame-settings" }, ...d.settings.flatMap(([k, v]) => [el("dt", {}, k), el("dd", {}, v)]));
  return [
    el("h3", {}, `Frame ${f.frame} `, el("a", { href: "#/render/" + f.id, class: "dim" }, `(render ${f.id}: its own page)`)),
    el("div", { class: "render", id: "frame-chosen", "data-frame": String(f.frame) },
      el("div", { class: "frame" }, el("div", { class: "stage fit" }, img)),
      el("div", {},
        el("div", { class: "panel" }, el("h3", {}, "Settings"), settings),
        el("div", { class: "panel" }, el("h3", {}, "Log"), log))),
  ];
}

// What a sequence's frames table was made from: made again when it changes.
const frameKey = (r) => JSON.stringify([r.state, r.paused, r.priority, r.passes_done, r.samples_done]);

// Pause or resume, and a priority to set: for a running render or a whole sequence.
function steering(r) {
  const path = "/api/renders/" + encodeURIComponent(r.id);
  const pause = el("button", { id: r.paused ? "resume" : "pause" }, r.paused ? "Resume" : "Pause");
  pause.addEventListener("click", async () => {
    pause.disabled = true;
    try { await act(path + (r.paused ? "/resume" : "/pause")); pause.textContent = r.paused ? "Resumed" : "Paused"; }
    catch (e) { pause.textContent = "Failed: " + e.message; }
  });
  const level = el("input", { id: "priority", type: "number", min: "-1000", max: "1000", step: "1", value: String(r.priority) });
  const set = el("button", { id: "set-priority" }, "Set priority");
  set.addEventListener("click", async () => {
    set.disabled = true;
    try { await act(path + "/priority?to=" + encodeURIComponent(level.value)); set.textContent = "Priority set"; }
    catch (e) { set.textContent = "Failed: " + e.message; }
    setTimeout(() => { set.disabled = false; set.textContent = "Set priority"; }, 1500);
  });
  return [pause, el("label", { class: "exposure", title: "higher is served first, -1000 to 1000; from the next job on" }, "priority", level, set)];
}

async function renderView(id) {
  const from = framesFrom.get(id) || 0;
  const detail = await api("/api/renders/" + encodeURIComponent(id) + (id.startsWith("s") ? "?from=" + from : ""));
  const r = detail.info;
  const view = [];
  view.push(el("h2", { title: r.scene }, `Render ${r.id}: ${r.name ? r.name + " (" + sceneName(r.scene) + ")" : sceneName(r.scene)}`));
  const controls = el("div", { class: "controls" });
  if (r.state === "running") {
    const cancel = el("button", { id: "cancel", class: "danger" }, "Cancel render");
    cancel.addEventListener("click", async () => {
      if (cancel.dataset.armed !== "yes") { cancel.dataset.armed = "yes"; cancel.textContent = "Really cancel?"; return; }
      cancel.disabled = true;
      try { await act("/api/renders/" + encodeURIComponent(r.id) + "/cancel"); cancel.textContent = "Cancelled"; }
      catch (e) { cancel.textContent = "Cancel failed: " + e.message; }
    });
    controls.append(cancel, ...steering(r));
    // An adaptive render whose quote rests on too few tiles yet: its pilot, on the farm now.
    const q = detail.quote;
    if (q && q.tiles_judged < q.pilot_tiles && detail.settings.some(([k]) => k === "target error")) {
      const ask = el("button", { id: "quote", title: `renders the first round of ${q.pilot_tiles} tiles spread over the image now, ahead of other work and even while paused, so that the quote rests on them; they are the render's own first passes, none renders twice` }, "Quote");
      ask.addEventListener("click", async () => {
        ask.disabled = true;
        try { await act("/api/renders/" + encodeURIComponent(r.id) + "/quote"); ask.textContent = "Pilot running"; }
        catch (e) { ask.textContent = "Quote failed: " + e.message; }
      });
      controls.append(ask);
    }
  }
  if (r.state === "done" && !r.sequence) {
    controls.append(el("a", { class: "button", id: "download-exr", href: `/api/renders/${r.id}/image.exr` }, "Download EXR"));
    controls.append(el("a", { class: "button", id: "download-png", href: `/api/renders/${r.id}/image.png` }, "Download PNG"));
  }
  if (r.sequence) {
    if (r.sequence.frames_failed > 0 || r.state === "cancelled") controls.append(retryButton(r.id, "Retry failed and cancelled frames"));
    const log = el("pre", { class: "log", id: "log" });
    view.push(controls, el("p", {}, strip(r.sequence)));
    const chosen = chosenFrame(detail);
    view.push(el("h3", {}, "Frames"), ...framesTable(detail, chosen));
    if (chosen) view.push(...await framePanel(chosen));
    view.push(el("h3", {}, "Sequence log"), log);
    loadLog(r.id, log).catch(() => {});
    return view;
  }
  if (r.state === "failed" || r.state === "cancelled") controls.append(retryButton(r.id, "Retry (keeps what it merged)"));
  for (const m of ["none", "samples", "error", "jobs"]) {
    const label = { none: "Image", samples: "Samples per tile", error: "Error per tile", jobs: "Jobs" }[m];
    const b = el("button", { id: "map-" + m, class: m === map ? "on" : "" }, label);
    b.addEventListener("click", () => { map = m; lastTiles = 0; route(); });
    controls.append(b);
  }
  const img = el("img", { id: "preview", alt: "the render's merged image so far", "data-version": "" });
  const canvas = el("canvas", { id: "tiles" });
  const stage = el("div", { class: "stage " + (oneToOne ? "one" : "fit") }, img, canvas);
  // Fit the window, or the preview's own pixels (1:1); and an exposure, as a display control
  // (it changes what the page shows, not the render).
  const size = el("button", { id: "size" }, oneToOne ? "Fit" : "1:1");
  size.addEventListener("click", () => { oneToOne = !oneToOne; route(); });
  const ev = el("input", { id: "exposure", type: "range", min: "-4", max: "4", step: "0.5", value: String(exposure) });
  const evLabel = el("span", {}, evText());
  const expose = () => { img.style.filter = exposure ? `brightness(${Math.pow(2, exposure)})` : ""; evLabel.textContent = evText(); };
  ev.addEventListener("input", () => { exposure = Number(ev.value); expose(); });
  expose();
  controls.append(size, el("label", { class: "exposure" }, "exposure", ev, evLabel));
  // A render that is denoised: its denoised colour (as its PNG; while it runs, its film so far
  // denoised, made again at most every 10 s), or the raw one.
  if ((r.state === "done" || r.state === "running") && detail.settings.some(([k]) => k === "denoise")) {
    const toggle = el("button", { id: "denoised", class: raw ? "" : "on" }, raw ? "Raw" : "Denoised");
    toggle.addEventListener("click", () => { raw = !raw; route(); });
    controls.append(toggle);
  }
  target = detail.settings.find(([k]) => k === "target error")?.[1] || null;
  quote = detail.quote || null;
  const status = el("dl", { id: "status" });
  const side = el("div", {},
    el("div", { class: "panel" }, el("h3", {}, "Progress"), status),
    el("div", { class: "panel" }, el("h3", {}, "Settings"), el("dl", {}, detail.settings.flatMap(([k, v]) => [el("dt", {}, k), el("dd", {}, v)]))),
    el("div", { class: "panel" }, el("h3", {}, "Log"), el("pre", { class: "log", id: "log" })));
  loadLog(r.id, side.querySelector("#log")).catch(() => {});
  view.push(controls, el("div", { class: "render" }, el("div", {}, el("div", { class: "frame" }, stage), el("div", { class: "legend", id: "legend" })), side));
  fillStatus(status, r, detail.workers);
  img.addEventListener("load", () => { drawTiles(canvas, img, detail); });
  refreshPreview(img, r);
  return view;
}

// The noise figure (tessera_film::relative_error): each pixel's standard error over its mean,
// root-mean-squared over the image; the measure an adaptive render stops each tile at.
const NOISE = "each pixel's standard error relative to its value, root-mean-squared over the image (dark pixels count as much as bright ones, so deep shadows raise it); adaptive renders stop each tile at the target";

function fillStatus(dl, r, workers) {
  dl.replaceChildren(...[
    ["state", stateOf(r) + (r.message ? ": " + r.message : "")],
    ["priority", String(r.priority)],
    ["runs on", r.placement || "any worker"],
    ["passes", `${r.passes_done} of ${r.passes_total}`],
    ["samples", count(r.samples_done) + ` (${r.mean_spp.toFixed(1)} per pixel)`],
    ["speed", count(r.samples_per_second) + " samples/s"],
    ["noise", (r.error ? (100 * r.error).toFixed(3) + " %" : "–")
      + (r.confidence > 0 ? `, below ${(100 * r.error_bound).toFixed(3)} % with ${Math.round(1000 * r.confidence) / 10} % confidence` : "")
      + (target ? ` (target ${100 * parseFloat(target)} %)` : "")],
    ["submitted", when(r.submitted_at)],
    ["ran for", r.state === "running" && !r.started_at ? "queued: not started yet" : duration(elapsedOf(r))],
    ["ETA", eta(r)],
    ...(quote ? [["quote", quoteText(quote)]] : []),
    ["workers", workers && workers.length ? workers.join(", ") : String(r.workers)],
  ].flatMap(([k, v]) => [el("dt", k === "noise" ? { title: NOISE } : {}, k), el("dd", { id: "status-" + k.replace(/ /g, "-") }, v)]));
}

// A running render's quote, as `submit --quote` gives one before submitting: the samples it
// is predicted to take (from the tiles judged so far; the range is their error 1.25x each way),
// the core-seconds and the time left at the live workers' measured speed.
function quoteText(q) {
  const range = q.samples_low < q.samples_high ? ` (${count(q.samples_low)}–${count(q.samples_high)})` : "";
  const basis = q.tiles_judged === 0 ? ", at most: no tile judged yet"
    : q.tiles_judged < q.tiles ? `, from ${q.tiles_judged} of ${q.tiles} tiles judged` : "";
  const speed = q.samples_per_second > 0
    ? `; ${count(q.samples * q.threads / q.samples_per_second)} core-seconds, ${duration(Math.max(0, q.samples - q.samples_done) / q.samples_per_second)} left on ${q.workers} live worker${q.workers === 1 ? "" : "s"}`
    : "; no live worker has a measured speed yet";
  return `about ${count(q.samples)} samples${range}${basis}${speed}`;
}

// Loads the preview anew when the render has merged more samples; the version is the
// samples merged, so the image the page shows is tagged with what it holds.
function refreshPreview(img, r) {
  const version = String(r.samples_done) + ":" + r.state + (raw ? ":raw" : "");
  if (img.dataset.version === version) return;
  const next = new Image();
  next.onload = () => {
    img.src = next.src;
    img.dataset.version = version;
    img.dataset.loads = String(Number(img.dataset.loads || 0) + 1);
  };
  next.src = `/api/renders/${encodeURIComponent(r.id)}/preview.jpg?v=${encodeURIComponent(version)}` + (raw ? "&raw=1" : "");
}

async function drawTiles(canvas, img, detail) {
  const ctx = canvas.getContext("2d");
  canvas.width = img.naturalWidth; canvas.height = img.naturalHeight;
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (map === "none") { if ($("legend")) $("legend").textContent = ""; return; }
  if (Date.now() - lastTiles < 1000 && canvas.dataset.tiles) { paint(ctx, JSON.parse(canvas.dataset.tiles), detail); return; }
  lastTiles = Date.now();
  const t = await api(`/api/renders/${encodeURIComponent(detail.info.id)}/tiles`);
  canvas.dataset.tiles = JSON.stringify(t.tiles);
  canvas.dataset.jobs = JSON.stringify(t.jobs);
  paint(ctx, t.tiles, detail);
}

// The jobs map: each tile done (every planned pass merged), being rendered (a job in flight),
// or waiting; and the jobs in flight, each with its tile, passes and worker.
function paintJobs(ctx, tiles, jobs, sx, sy) {
  const busy = new Set(jobs.map((j) => j.tile));
  tiles.forEach((t, i) => {
    ctx.fillStyle = t[6] >= t[7] ? "rgba(111,207,151,0.45)" : busy.has(i) ? "rgba(108,180,255,0.6)" : "rgba(40,40,40,0.55)";
    ctx.fillRect(t[0] * sx, t[1] * sy, t[2] * sx, t[3] * sy);
    ctx.strokeStyle = "rgba(0,0,0,0.35)";
    ctx.strokeRect(t[0] * sx, t[1] * sy, t[2] * sx, t[3] * sy);
  });
  const done = tiles.filter((t) => t[6] >= t[7]).length;
  const legend = $("legend");
  if (legend) {
    legend.replaceChildren(`Tiles: ${done} done (green), ${busy.size} being rendered (blue), ${tiles.length - done - busy.size} waiting (grey).`,
      el("table", { id: "jobs", class: "compact" }, el("tr", {}, ["tile at", "passes", "worker"].map((h) => el("th", {}, h))),
        ...jobs.map((j) => el("tr", {}, el("td", {}, `${j.x}, ${j.y}`), el("td", {}, `${j.first + 1}–${j.first + j.count}`), el("td", {}, j.worker)))));
  }
}

// Each tile tinted by its value against the largest; tiles with no samples yet are greyed.
function paint(ctx, tiles, detail) {
  const sx = ctx.canvas.width / detail.width, sy = ctx.canvas.height / detail.height;
  if (map === "jobs") { paintJobs(ctx, tiles, JSON.parse(ctx.canvas.dataset.jobs || "[]"), sx, sy); return; }
  const values = tiles.map((t) => (map === "samples" ? t[4] : t[5]));
  const most = Math.max(1e-9, ...values);
  tiles.forEach((t, i) => {
    const v = values[i] / most;
    if (t[4] === 0) ctx.fillStyle = "rgba(40,40,40,0.7)";
    else if (map === "samples") ctx.fillStyle = `rgba(108,180,255,${0.15 + 0.6 * v})`;
    else ctx.fillStyle = `rgba(255,${Math.round(200 * (1 - v))},80,${0.15 + 0.6 * v})`;
    ctx.fillRect(t[0] * sx, t[1] * sy, t[2] * sx, t[3] * sy);
    ctx.strokeStyle = "rgba(0,0,0,0.35)";
    ctx.strokeRect(t[0] * sx, t[1] * sy, t[2] * sx, t[3] * sy);
  });
  const legend = $("legend");
  if (legend) {
    legend.textContent = map === "samples"
      ? `Samples per pixel per tile: brightest ${Math.round(most)}; grey tiles have none yet.`
      : `Relative error per tile: reddest ${(100 * most).toFixed(2)} %; grey tiles have no samples yet.`;
  }
}

// A running render's ETA, or why there is none.
function eta(r) {
  if (r.state !== "running") return "–";
  if (r.paused) return "paused";
  if (r.no_worker_fits) return "no connected worker can take it (" + r.placement + ")";
  if (r.no_workers) return "no workers connected";
  return r.samples_per_second > 0 ? duration(r.eta_seconds) : "not known yet (no samples merged)";
}

// ---- workers --------------------------------------------------------------------------------

function workersView() {
  const all = latest?.workers || [];
  // Lost and stopped workers, left out once gone longer than the chosen time (as `tessera
  // workers --hide-gone SECONDS`).
  const gone = Number(listing.gone);
  const workers = all.filter((w) => !gone || !["lost", "stopped"].includes(w.state) || w.seconds_since_seen <= gone);
  const table = el("table", { id: "workers" },
    el("tr", {}, ["worker", "state", "pool", "tags", "host", "threads", "speed", "current jobs", "last heard", "results", "failures"].map((h) => el("th", {}, h))));
  for (const w of workers) {
    const blocked = w.blocked_from?.length ? " (no more jobs of render " + w.blocked_from.join(", ") + ")" : "";
    table.append(el("tr", { id: "worker-" + w.id },
      el("td", {}, w.name), el("td", { class: "state-" + w.state }, w.state + blocked),
      el("td", {}, w.pool || "–"), el("td", { class: "dim" }, (w.tags || []).join(" ") || "–"),
      el("td", {}, w.host || "–"), el("td", { class: "num" }, w.threads),
      el("td", { class: "num" }, w.samples_per_second ? count(w.samples_per_second) + " samples/s" : "–"),
      el("td", {}, w.renders.length ? w.renders.map((id) => el("a", { href: "#/render/" + id }, "render " + id + " ")) : "idle"),
      el("td", { class: "num" }, duration(w.seconds_since_seen) + " ago"),
      el("td", { class: "num" }, w.results), el("td", { class: "num" }, w.failures)));
  }
  const hide = chooser("gone", [["", "never"], ["10", "after 10 s"], ["60", "after 1 min"], ["600", "after 10 min"], ["3600", "after 1 h"]], "hide lost and stopped workers");
  const hidden = all.length - workers.length;
  return [el("h2", {}, "Workers"), el("div", { class: "controls" }, hide, hidden ? el("span", { class: "dim", id: "workers-hidden" }, `${hidden} hidden`) : null),
    all.length ? table : el("p", { class: "dim" }, "No workers have asked for work yet: start one with tessera worker.")];
}

// ---- routing and the event stream -----------------------------------------------------------

let current = "";

async function route() {
  const hash = location.hash || "#/";
  current = hash;
  $("nav-renders").classList.toggle("here", hash === "#/");
  $("nav-workers").classList.toggle("here", hash === "#/workers");
  try {
    let view;
    if (hash.startsWith("#/render/")) view = await renderView(decodeURIComponent(hash.slice(9)));
    else if (hash === "#/workers") view = workersView();
    else view = rendersView();
    if (current === hash) $("view").replaceChildren(...view);
  } catch (e) {
    $("view").replaceChildren(el("p", { class: "error" }, e.message));
  }
}

// A new state: the lists are redrawn; a render's page updates in place.
function update() {
  const hash = location.hash || "#/";
  if (!hash.startsWith("#/render/")) { route(); return; }
  const id = decodeURIComponent(hash.slice(9));
  const r = latest?.renders.find((x) => x.id === id);
  if (r && id.startsWith("s")) {
    // A sequence's page: its frames table again when the sequence has moved on.
    if ($("frames") && $("frames").dataset.key !== frameKey(r)) route();
    return;
  }
  const img = $("preview");
  if (!r || !img) return;
  if ($("cancel") && r.state !== "running" || (r.state === "done" && !$("download-exr") && !r.sequence)) { route(); return; }
  if ($("pause") && r.paused || $("resume") && !r.paused) { route(); return; }
  refreshPreview(img, r);
  api("/api/renders/" + encodeURIComponent(id)).then((d) => {
    quote = d.quote || null;
    fillStatus($("status"), d.info, d.workers);
    if (Date.now() - logRead > 2000) { logRead = Date.now(); loadLog(id, $("log")).catch(() => {}); }
  }).catch(() => {});
}

// A "changes" event carries only the rows that changed, the ids of rows gone, and the workers
// when they changed: the list is kept newest first.
function applyChanges(state, c) {
  const rows = new Map((state?.renders || []).map((r) => [r.id, r]));
  for (const id of c.gone) rows.delete(id);
  for (const r of c.renders) rows.set(r.id, r);
  const number = (id) => Number(String(id).replace(/^s/, ""));
  const renders = [...rows.values()].sort((a, b) => number(b.id) - number(a.id));
  return { renders, workers: c.workers ?? state?.workers ?? [] };
}

// Running renders' elapsed times tick here, once a second, between events.
function tick() {
  const rows = new Map((latest?.renders || []).map((r) => [r.id, r]));
  for (const cell of document.querySelectorAll("td.elapsed")) {
    const r = rows.get(cell.dataset.id);
    if (r && r.started_at !== null && r.started_at !== undefined) cell.textContent = duration(elapsedOf(r));
  }
}

function heard(data) {
  if (typeof data.now === "number") skew = data.now - Date.now() / 1000;
  return data;
}

function listen() {
  const events = new EventSource("/api/events");
  events.addEventListener("state", (e) => { latest = heard(JSON.parse(e.data)); update(); });
  events.addEventListener("changes", (e) => { latest = applyChanges(latest, heard(JSON.parse(e.data))); update(); });
  setInterval(tick, 1000);
  events.onopen = () => { $("live").textContent = "live"; $("live").classList.add("on"); };
  events.onerror = () => { $("live").textContent = "reconnecting"; $("live").classList.remove("on"); };
}

async function start() {
  session = await api("/api/session");
  $("who").textContent = session.user ? `${session.user} (${session.role})` : "";
  if (session.login) {
    $("logout").hidden = false;
    $("logout").addEventListener("click", async () => { await act("/logout"); location.reload(); });
  }
  latest = await Promise.all([api("/api/renders"), api("/api/workers")]).then(([r, w]) => ({ renders: r.renders, workers: w.workers }));
  window.addEventListener("hashchange", route);
  await route();
  listen();
}

start();
