// semservo dashboard: watch and steer a positioning run. Plain JS on the gateway's REST
// API and its WS /events stream; plots with the vendored uPlot. No build step, no CDN.
"use strict";

const $ = (id) => document.getElementById(id);
const FINISHED = ["converged", "failed", "stopped"];
const state = { runId: null, referenceId: null, latestSeq: null, pixelSizeNm: null, mask: [], plots: {}, series: null };

// -- the API --------------------------------------------------------------------------
$("token").value = localStorage.getItem("semservo-token") || "";
$("token").addEventListener("change", () => localStorage.setItem("semservo-token", $("token").value.trim()));

async function api(method, path, body) {
  const headers = {};
  const token = $("token").value.trim();
  if (token) headers["Authorization"] = `Bearer ${token}`;
  let payload = body;
  if (body !== undefined && !(body instanceof FormData)) {
    headers["Content-Type"] = "application/json";
    payload = JSON.stringify(body);
  }
  let response;
  try {
    response = await fetch(path, { method, headers, body: payload });
  } catch (error) {
    throw new Error(`the gateway does not answer (${error.message})`);
  }
  const text = await response.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch { data = null; }
  if (!response.ok) {
    const error = (data && data.error) || {};
    const field = error.field ? ` (field ${error.field})` : "";
    throw new Error(`${error.message || response.statusText}${field}`);
  }
  return data;
}

function say(text) {
  $("message-text").textContent = text;
  $("message").hidden = false;
}
$("message-close").addEventListener("click", () => { $("message").hidden = true; });

// Every control reports its failure in words, never swallowed.
function action(element, event, work) {
  element.addEventListener(event, async (e) => {
    try { await work(e); } catch (error) { say(error.message); }
  });
}

// -- images ---------------------------------------------------------------------------
function refreshImage(img, path) {
  const next = new Image();
  next.onload = () => { img.src = next.src; img.dataset.loaded = path; };
  next.src = `${path}?t=${Date.now()}`;
}

function refreshImages() {
  if (document.hidden) return;
  refreshImage($("live"), "/frames/latest.png");
  if (state.referenceId) refreshImage($("difference"), "/difference.png");
}

// -- plots ----------------------------------------------------------------------------
function makePlot(element, title, series, log) {
  const width = Math.max(element.clientWidth, 240);
  const options = {
    width, height: 190,
    scales: { x: { time: false }, y: log ? { distr: 3 } : {} },
    axes: [{ stroke: "#8c96a3", grid: { stroke: "#2d343e" } }, { stroke: "#8c96a3", grid: { stroke: "#2d343e" } }],
    series: [{ label: "iteration" }, ...series],
    legend: { show: true },
  };
  return new uPlot(options, [[], ...series.map(() => [])], element);
}

function resetPlots() {
  state.series = { iteration: [], ex: [], ey: [], er: [], ea: [], eb: [], cost: [], vx: [], vy: [] };
  drawPlots();
}

function drawPlots() {
  const s = state.series;
  state.plots.error.setData([s.iteration, s.ex, s.ey, s.er, s.ea, s.eb]);
  state.plots.cost.setData([s.iteration, s.cost]);
  state.plots.voltage.setData([s.iteration, s.vx, s.vy]);
  $("error-points").textContent = `${s.iteration.length} points`;
  $("cost-points").textContent = `${s.cost.length} points`;
  $("voltage-points").textContent = `${s.vx.filter((v) => v !== null).length} points`;
}

function addIteration(record) {
  if (!record.error || record.action !== "moved") return;
  const s = state.series;
  s.iteration.push(record.iteration);
  s.ex.push(record.error[0] ?? null);
  s.ey.push(record.error.length > 1 ? record.error[1] : null);
  s.er.push(record.error.length > 2 ? record.error[2] : null);
  s.ea.push(record.alpha_deg ?? null);  // the last focus sweep's tilts, degrees
  s.eb.push(record.beta_deg ?? null);
  s.cost.push(Math.max(record.cost, 1e-9));
  s.vx.push(record.voltages ? record.voltages.x ?? null : null);
  s.vy.push(record.voltages ? record.voltages.y ?? null : null);
  drawPlots();
}

async function loadRunIntoPlots(runId) {
  const run = await api("GET", `/runs/${runId}`);
  resetPlots();
  for (const record of run.trajectory) addIteration(record);
}

// -- status ---------------------------------------------------------------------------
const fmt = (value, digits) => (value === null || value === undefined ? "–" : Number(value).toFixed(digits));

// What the live frame says of its acquisition; what it does not know is not shown.
function acquisitionText(acquisition) {
  const parts = [];
  parts.push(acquisition.pixel_size_nm ? `${fmt(acquisition.pixel_size_nm, 2)} nm/px` : "pixel size unknown");
  if (acquisition.magnification) parts.push(`×${fmt(acquisition.magnification, 0)}`);
  if (acquisition.dwell_ns) parts.push(`${fmt(acquisition.dwell_ns, 0)} ns/px`);
  if (acquisition.working_distance_mm) parts.push(`WD ${fmt(acquisition.working_distance_mm, 2)} mm`);
  if (acquisition.high_voltage_kv) parts.push(`${fmt(acquisition.high_voltage_kv, 1)} kV`);
  if (acquisition.detector) parts.push(acquisition.detector);
  return parts.join(" · ");
}

// The last focus sweep: its tilts and a small depth map (one cell per kernel).
function showTilt(tilt) {
  if (!tilt) return;
  $("tilt-summary").textContent = `α ${fmt(tilt.alpha_deg, 3)}° β ${fmt(tilt.beta_deg, 3)}° · ${tilt.frames} frames · ` +
    `${tilt.kernels_used}/${tilt.kernels_total} kernels`;
  const grid = tilt.depth_map_um || [];
  const canvas = $("depth-map"), context = canvas.getContext("2d");
  const rows = grid.length, cols = rows ? grid[0].length : 0;
  if (!rows || !cols) return;
  const values = grid.flat().filter((v) => v !== null);
  const span = Math.max(1e-6, ...values.map(Math.abs));
  const w = canvas.width / cols, h = canvas.height / rows;
  grid.forEach((row, r) => row.forEach((value, c) => {
    if (value === null) { context.fillStyle = "#888"; } else {
      const t = value / span;  // -1 nearer (blue) .. +1 farther (red)
      context.fillStyle = `rgb(${Math.round(128 + 127 * Math.max(t, 0))}, ${Math.round(128 - 100 * Math.abs(t))}, ` +
        `${Math.round(128 + 127 * Math.max(-t, 0))})`;
    }
    context.fillRect(c * w, r * h, Math.ceil(w), Math.ceil(h));
  }));
}

function showStatus(status) {
  const badge = $("state");
  badge.textContent = status.state;
  badge.className = `state state-${status.state}`;
  $("run-id").textContent = status.run_id || "–";
  $("iteration").textContent = status.iteration;
  // The error the controller judges (mean of its last fresh frames), else the last frame's.
  const errorPx = status.mean_error_px ?? status.error_px;
  const umPerPx = status.error_px ? status.error_um / status.error_px : null;
  $("error-px").textContent = fmt(errorPx, 3);
  $("error-um").textContent = umPerPx === null || errorPx === null ? "–" : fmt(errorPx * umPerPx, 4);
  $("gamma").textContent = fmt(status.rotation_deg, 3);
  $("alpha").textContent = fmt(status.alpha_deg, 3);
  $("beta").textContent = fmt(status.beta_deg, 3);
  showTilt(status.tilt);
  $("frame-rate").textContent = fmt(status.frame_rate, 1);
  $("snr").textContent = fmt(status.snr_db, 1);
  $("latency").textContent = fmt(status.last_latency_ms, 1);
  $("live-seq").textContent = status.latest_frame_seq === null ? "(no frames)" : `#${status.latest_frame_seq}`;
  $("live-acquisition").textContent = acquisitionText(status.frame_acquisition || {});
  const stage = status.stage || {};
  const positions = stage.positions_um || {}, voltages = stage.voltages || {};
  $("stage-x").textContent = fmt(positions.x, 3);
  $("stage-y").textContent = fmt(positions.y, 3);
  $("volt-x").textContent = fmt(voltages.x, 2);
  $("volt-y").textContent = fmt(voltages.y, 2);
  $("link").textContent = stage.link || "–";
  $("stage-state").textContent = stage.state ? `${stage.state}${stage.reason ? ": " + stage.reason : ""}` : "–";
  $("resume").hidden = !["stopped", "held"].includes(stage.state);

  const services = $("services");
  services.replaceChildren(...Object.entries(status.services).map(([name, health]) => {
    const item = document.createElement("li");
    item.dataset.service = name;
    item.innerHTML = `<span>${name}</span><span class="${health.up ? "up" : "down"}">${health.up ? health.state : "DOWN"}</span>`;
    if (health.last_error) item.title = health.last_error;
    return item;
  }));
  const problems = status.down.map((name) => `${name} is down`);
  for (const name of status.degraded || []) {
    problems.push(`${name} is degraded${status.services[name].last_error ? `: ${status.services[name].last_error}` : ""}`);
  }
  if (stage.link && stage.link !== "connected") problems.push(`the stage's serial link is ${stage.link}`);
  $("banner").hidden = problems.length === 0;
  $("banner").textContent = problems.length ? `⚠ ${problems.join("; ")}` : "";

  const reference = status.reference;
  const referenceId = reference ? reference.id : null;
  if (referenceId !== state.referenceId) {
    state.referenceId = referenceId;
    $("reference-id").textContent = reference ? `${reference.kind} ${reference.id}` : "none taught";
    if (referenceId) refreshImage($("reference"), "/reference.png");
  }
  if (status.run_id && status.run_id !== state.runId) {
    state.runId = status.run_id;
    loadRunIntoPlots(status.run_id).catch(() => resetPlots());
  }
  state.latestSeq = status.latest_frame_seq;
}

async function pollStatus() {
  try {
    showStatus(await api("GET", "/status"));
  } catch (error) {
    $("banner").hidden = false;
    $("banner").textContent = `⚠ ${error.message}`;
  }
}

// -- live events ----------------------------------------------------------------------
function connectEvents() {
  // Browsers cannot set headers on a WebSocket: the token (when one is set) rides in the query.
  const token = $("token").value.trim();
  const query = token ? `?token=${encodeURIComponent(token)}` : "";
  const socket = new WebSocket(`${location.protocol === "https:" ? "wss" : "ws"}://${location.host}/events${query}`);
  socket.onmessage = (message) => {
    const event = JSON.parse(message.data);
    if (event.kind === "iteration") {
      if (event.run_id !== state.runId) { state.runId = event.run_id; resetPlots(); }
      addIteration(event.data);
      if (event.data.snr_db !== undefined) $("snr").textContent = fmt(event.data.snr_db, 1);
    } else if (event.kind === "status") {
      if (event.data.state) {
        $("state").textContent = event.data.state;
        $("state").className = `state state-${event.data.state}`;
        if (FINISHED.includes(event.data.state)) { pollStatus(); setTimeout(loadRuns, 500); }
      }
    } else if (event.kind === "reference") {
      state.referenceId = null;  // the next status refreshes the reference image
      pollStatus();
    }
  };
  socket.onclose = () => setTimeout(connectEvents, 1000);
}

// -- controls -------------------------------------------------------------------------
action($("stop"), "click", async () => {
  const stopped = await api("POST", "/stop", { reason: "stop pressed on the dashboard" });
  if (!stopped.stage_stopped) say(`the stage did not confirm the stop: ${stopped.stage_error}`);
  pollStatus();
});

for (const button of document.querySelectorAll(".jog button")) {
  action(button, "click", async () => {
    const step = Number($("jog-step").value) * Number(button.dataset.sign);
    await api("POST", "/stage/move", { [`${button.dataset.axis}_um`]: step, relative: true });
    pollStatus();
  });
}

action($("resume"), "click", async () => {
  await api("POST", "/stage/resume");
  pollStatus();
});

action($("teach-live"), "click", async () => {
  const tilts = $("teach-tilts").checked ? "&tilts=true" : "";
  await api("POST", `/teach?frames=${Number($("teach-frames").value) || 1}${tilts}`);
  pollStatus();
});

action($("teach-file"), "change", async (e) => {
  const file = e.target.files[0];
  if (!file) return;
  const form = new FormData();
  form.append("image", file);
  form.append("label", file.name);
  try { await api("POST", "/teach", form); } finally { e.target.value = ""; }
  pollStatus();
});

function imagePoint(event) {
  const img = $("live");
  const box = img.getBoundingClientRect();
  const width = img.naturalWidth || 512, height = img.naturalHeight || 512;
  return [(event.clientX - box.left) * width / box.width, (event.clientY - box.top) * height / box.height];
}

function drawMask() {
  const img = $("live");
  $("overlay").setAttribute("viewBox", `0 0 ${img.naturalWidth || 512} ${img.naturalHeight || 512}`);
  $("mask-polygon").setAttribute("points", state.mask.map((p) => p.join(",")).join(" "));
  $("mask-count").textContent = state.mask.length;
  $("teach-mask").disabled = state.mask.length < 3;
}

action($("live-box"), "click", async (event) => {
  const [x, y] = imagePoint(event);
  if (document.querySelector("input[name=click-mode]:checked").value === "mask") {
    state.mask.push([Math.round(x * 10) / 10, Math.round(y * 10) / 10]);
    drawMask();
    return;
  }
  await api("POST", "/stage/center", { x_px: x, y_px: y });  // the clicked point comes to the centre
  pollStatus();
});

action($("clear-mask"), "click", async () => { state.mask = []; drawMask(); });

action($("teach-mask"), "click", async () => {
  await api("POST", "/teach/polygon", { polygon: state.mask });
  state.mask = [];
  drawMask();
  pollStatus();
});

action($("start"), "click", async () => {
  const dofs = [...document.querySelectorAll("input[name=dof]:checked")].map((box) => box.value);
  const started = await api("POST", "/start", {
    tolerance_px: Number($("tolerance").value), max_iterations: Number($("max-iterations").value),
    dofs, hold: $("hold").checked,
  });
  state.runId = started.run_id;
  resetPlots();
  pollStatus();
});

// -- history --------------------------------------------------------------------------
async function loadRuns() {
  const runs = await api("GET", "/runs?limit=50");
  $("runs").replaceChildren(...runs.map((run) => {
    const row = document.createElement("tr");
    row.dataset.runId = run.id;
    const started = new Date(run.started_at_ns / 1e6).toLocaleTimeString();
    const truth = run.truth ? fmt(run.truth.error_norm_px, 3) : "–";
    row.innerHTML = `<td>${run.id}</td><td>${started}</td><td class="outcome-${run.state}">${run.state}</td>` +
      `<td>${run.iterations}</td><td>${fmt(run.final_error_px, 3)}</td><td>${truth}</td>`;
    row.addEventListener("click", () => showRun(run.id).catch((error) => say(error.message)));
    return row;
  }));
}

async function showRun(runId) {
  const run = await api("GET", `/runs/${runId}`);
  $("run-detail").hidden = false;
  $("detail-id").textContent = run.id;
  $("detail-state").textContent = run.state;
  const truth = run.truth ? `; true final error ${fmt(run.truth.error_norm_px, 3)} px` : "";
  $("detail-summary").textContent = `${run.iterations} iterations, ${run.reason || "no reason given"}; ` +
    `final error ${fmt(run.final_error_px, 3)} px${truth}; ${run.stage_commands.length} stage commands; ` +
    `tolerance ${run.settings.tolerance_px} px`;
  $("detail-csv").href = `/runs/${run.id}.csv`;
  $("detail-json").href = `/runs/${run.id}`;
  $("detail-report").src = `/runs/${run.id}/report.png`;
  await loadRunIntoPlots(run.id);
}
action($("refresh-runs"), "click", loadRuns);

// -- start ----------------------------------------------------------------------------
state.plots.error = makePlot($("plot-error"), "error", [
  { label: "e_x", stroke: "#58a6ff" }, { label: "e_y", stroke: "#f0883e" }, { label: "e_rot", stroke: "#a371f7" },
  { label: "α (deg)", stroke: "#3fb950" }, { label: "β (deg)", stroke: "#d29922" }]);
state.plots.cost = makePlot($("plot-cost"), "cost", [{ label: "cost", stroke: "#dfe5ec" }], true);
state.plots.voltage = makePlot($("plot-voltage"), "voltages", [
  { label: "V_x", stroke: "#58a6ff" }, { label: "V_y", stroke: "#f0883e" }]);
resetPlots();
$("live").addEventListener("load", drawMask);
pollStatus();
loadRuns().catch((error) => say(error.message));
connectEvents();
setInterval(pollStatus, 1000);
setInterval(refreshImages, 700);
refreshImages();
window.semservo = state;  // for the curious (and the browser tests)
