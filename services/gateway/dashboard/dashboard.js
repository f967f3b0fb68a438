// semservo dashboard: watch and steer a positioning run. Plain JS on the gateway's REST
// API and its WS /events stream; plots with the vendored uPlot. No build step, no CDN.
"use strict";

const $ = (id) => document.getElementById(id);
const FINISHED = ["converged", "failed", "stopped"];
const ANGULAR = ["rotation", "alpha", "beta"];
const DOF_SYMBOL = { x: "x", y: "y", rotation: "γ", alpha: "α", beta: "β" };
const state = {
  runId: null,           // the controller's run (active or last), from GET /status
  runDofs: [],           // its degrees of freedom
  settingsShownFor: null, // the servoing run whose settings the Position panel shows
  status: null,
  mask: [],
  plots: {},
  plot: { runId: null, dofs: null, records: new Map() },  // the run the plots show: its records by frame seq
  series: null,
  images: {},            // per image: what is shown (key) and its object URL
};

// Another name for the same degree of freedom.
const canonicalDof = (dof) => (dof === "gamma" ? "rotation" : dof);

// -- the API --------------------------------------------------------------------------
$("token").value = localStorage.getItem("semservo-token") || "";
$("token").addEventListener("change", () => localStorage.setItem("semservo-token", $("token").value.trim()));

function authHeaders() {
  const token = $("token").value.trim();
  return token ? { Authorization: `Bearer ${token}` } : {};
}

// The API's error body, {"error": {"code", "message", "field"}}, as an Error in words.
async function errorOf(response) {
  const text = await response.text();
  let body = null;
  try { body = text ? JSON.parse(text) : null; } catch { body = null; }
  const detail = (body && body.error) || {};
  const field = detail.field ? ` (field ${detail.field})` : "";
  const error = new Error(`${detail.message || response.statusText || `HTTP ${response.status}`}${field}`);
  error.code = detail.code;
  error.status = response.status;
  error.field = detail.field;
  return error;
}

async function api(method, path, body) {
  const headers = authHeaders();
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
  if (!response.ok) throw await errorOf(response);
  const text = await response.text();
  try { return text ? JSON.parse(text) : null; } catch { return null; }
}

function say(text) {
  $("message-text").textContent = text;
  $("message").hidden = false;
}
$("message-close").addEventListener("click", () => { $("message").hidden = true; });

// Every control reports its failure in words, never swallowed; a new action's outcome
// replaces the last one's (a refusal stayed over the run a later click started).
function action(element, event, work) {
  element.addEventListener(event, async (e) => {
    $("message").hidden = true;
    try { await work(e); } catch (error) { say(error.message); }
  });
}

// A number field's value, or an error naming the field and its range (an empty jog step
// sent 0, a step of 50 over the field's 20 went out, an average of 0 taught 1 frame).
function fieldNumber(id, label, { whole = false } = {}) {
  const input = $(id), value = Number(input.value), low = Number(input.min), high = Number(input.max);
  if (input.value.trim() === "" || !Number.isFinite(value) || value < low || value > high
      || (whole && !Number.isInteger(value))) {
    throw new Error(`${label}: ${whole ? "a whole number" : "a number"} from ${low} to ${high}, not "${input.value}"`);
  }
  return value;
}

// A button whose request is still out takes no second click (a double click on Teach or
// Start would send two, and the gateway refuses the second: 409 teach_in_progress). Not
// for Stop, which must always be pressable.
function once(button, work) {
  return async (e) => {
    if (button.getAttribute("aria-busy") === "true") return;
    button.setAttribute("aria-busy", "true");
    try { await work(e); } finally { button.removeAttribute("aria-busy"); }
  };
}

const fmt = (value, digits) => (value === null || value === undefined ? "–" : Number(value).toFixed(digits));

function fmtDuration(seconds) {
  if (seconds === null || seconds === undefined) return "–";
  if (seconds < 60) return `${seconds.toFixed(1)} s`;
  const minutes = Math.floor(seconds / 60);
  return `${minutes}:${String(Math.round(seconds - 60 * minutes)).padStart(2, "0")} min`;
}

const dofText = (dofs) => (dofs || []).map((dof) => DOF_SYMBOL[canonicalDof(dof)] || dof).join(" ");

// -- images ---------------------------------------------------------------------------
// Each image is fetched, not pointed at: a refusal (no reference, the scan changed size)
// is shown in words in the panel instead of a broken image.
async function showImage(name, path, placeholder, key = path) {
  const img = $(name), text = $(`${name}-placeholder`);
  const shown = state.images[name] || (state.images[name] = {});
  if (!path) {
    shown.key = null;
    img.hidden = true;
    img.removeAttribute("src");
    if (shown.url) URL.revokeObjectURL(shown.url);
    shown.url = null;
    text.textContent = placeholder;
    text.hidden = false;
    return;
  }
  if (shown.loading) return;  // one request at a time per image
  shown.loading = true;
  try {
    const response = await fetch(`${path}${path.includes("?") ? "&" : "?"}t=${Date.now()}`, { cache: "no-store" });
    if (!response.ok) throw await errorOf(response);
    const url = URL.createObjectURL(await response.blob());
    await new Promise((resolve, reject) => {
      const probe = new Image();
      probe.onload = resolve;
      probe.onerror = () => reject(new Error("the image does not decode"));
      probe.src = url;
    });
    img.src = url;
    if (shown.url) URL.revokeObjectURL(shown.url);
    shown.url = url;
    shown.key = key;
    img.hidden = false;
    text.hidden = true;
  } catch (error) {
    if (shown.key !== key) {  // nothing of this image shown yet: say why
      img.hidden = true;
      text.textContent = `${placeholder}: ${error.message}`;
      text.hidden = false;
    }
  } finally {
    shown.loading = false;
  }
}

function refreshImages() {
  if (document.hidden) return;
  const status = state.status;
  if (status && status.latest_frame_seq === null) {
    showImage("live", null, "no frames yet: is the image server running?");
  } else {
    showImage("live", "/frames/latest.png", "no frame");
  }
  if (status && status.reference) showImage("difference", "/difference.png", "no difference", "difference");
  else showImage("difference", null, "no reference: nothing to compare");
}

// A scale bar from the frame's pixel size: a round length near a fifth of the field.
function showScaleBar(element, pixelSizeNm, columns) {
  if (!pixelSizeNm || !columns) { element.hidden = true; return; }
  const fieldNm = pixelSizeNm * columns;
  const target = fieldNm / 5, power = 10 ** Math.floor(Math.log10(target));
  const length = [5, 2, 1].map((m) => m * power).find((value) => value <= target) || power;
  const label = length >= 1e6 ? `${length / 1e6} mm` : length >= 1e3 ? `${length / 1e3} µm` : `${length} nm`;
  element.querySelector(".bar").style.width = `${(100 * length) / fieldNm}%`;
  element.querySelector(".label").textContent = label;
  element.hidden = false;
}

// The box takes the frame's aspect ratio, so the image fills it and the bar is true.
function fitBox(box, shape) {
  if (shape && shape.length >= 2 && shape[0] > 0 && shape[1] > 0) box.style.aspectRatio = `${shape[1]} / ${shape[0]}`;
}

// -- plots ----------------------------------------------------------------------------
const AXIS_FONT = "12px system-ui, -apple-system, 'Segoe UI', sans-serif";
const measure = document.createElement("canvas").getContext("2d");
measure.font = AXIS_FONT;

// A y axis as wide as its widest label (none clipped), however large the numbers.
function axisSize(self, values) {
  if (!values) return 40;
  const widest = Math.max(0, ...values.map((value) => (value ? measure.measureText(String(value)).width : 0)));
  const size = Math.ceil(widest) + 18;
  if (self) self.yAxisSize = size;  // what the plot's layout must leave it (layOutAgainIfCut)
  return size;
}

// uPlot (1.6.32) lays a plot out before its y axis is sized for new data, and does not lay
// it out again when the new labels need more room: "37.5" drawn where "35" fitted lost its
// first digit. After a draw, lay it out again when they do: once that draw is done (a
// resize within it is not drawn), and there and back by a pixel (uPlot skips a resize to
// the same size). At most once per setData (never a loop: a hidden axis, no data, or a
// zoom whose rounding keeps the two a pixel apart once drew 200 times a second).
function layOutAgainIfCut(plot) {
  const yAxis = plot.axes[1];
  if (plot.laidOutAgain || !yAxis._show || !plot.yAxisSize) return;
  if (plot.bbox.left / (window.devicePixelRatio || 1) + 1 >= plot.yAxisSize) return;
  plot.laidOutAgain = true;
  setTimeout(() => {
    const { width, height } = plot;
    plot.setSize({ width: width - 1, height });
    plot.setSize({ width, height });
  }, 0);
}

// Log axis labels a person reads: 1e-3, 0.01, 0.1, 1, 10, 100, 1000, 1e4.
function logLabel(value) {
  if (!(value > 0)) return "";
  const exponent = Math.floor(Math.log10(value) + 1e-9);
  const mantissa = Math.round(value / 10 ** exponent);
  if (exponent >= -2 && exponent <= 3) return String(Number(value.toPrecision(2)));
  return `${mantissa === 1 ? "" : `${mantissa}×`}1e${exponent}`;
}

// Decades only (and 2, 5 between them when the range spans few): no barcode of minor lines.
function logSplits(self, axisIndex, min, max) {
  if (!(min > 0) || !(max > min)) return [];
  const low = Math.floor(Math.log10(min) + 1e-9), high = Math.ceil(Math.log10(max) - 1e-9);
  const splits = [];
  for (let exponent = low; exponent <= high; exponent++) {
    const multiples = high - low <= 2 ? [1, 2, 5] : [1];
    for (const m of multiples) {
      const value = m * 10 ** exponent;
      if (value >= min * (1 - 1e-9) && value <= max * (1 + 1e-9)) splits.push(value);
    }
  }
  return splits;
}

function logValues(self, splits) {
  // At most one label per 22 px of height; the other decades keep their grid line.
  const room = Math.max(2, Math.floor((self.bbox.height / devicePixelRatio) / 22));
  const every = Math.ceil(splits.length / room);
  return splits.map((value, index) => ((splits.length - 1 - index) % every === 0 ? logLabel(value) : ""));
}

function plotHeight(width) {
  return Math.round(Math.min(260, Math.max(170, width * 0.55)));
}

function makePlot(box, series, { log = false } = {}) {
  const width = box.clientWidth > 0 ? box.clientWidth : 300;
  const axis = { stroke: "#8c96a3", font: AXIS_FONT, grid: { stroke: "#2d343e", width: 1 }, ticks: { stroke: "#2d343e" } };
  const yAxis = { ...axis, size: axisSize };
  // Every split drawn as logValues says (uPlot's own log filter would drop labels again).
  if (log) Object.assign(yAxis, { splits: logSplits, values: logValues, filter: (self, splits) => splits });
  const plot = new uPlot({
    width, height: plotHeight(width),
    scales: { x: { time: false }, y: log ? { distr: 3, log: 10 } : {} },
    axes: [{ ...axis }, yAxis],
    series: [{ label: "iteration" }, ...series],
    legend: { show: true },
    hooks: { draw: [layOutAgainIfCut], setData: [(self) => { self.laidOutAgain = false; }] },
  }, [[], ...series.map(() => [])], box);
  plot.box = box;
  return plot;
}

// Plots follow their panel's width (window resize, the grid reflowing, a panel shown).
const resizer = new ResizeObserver((entries) => {
  for (const entry of entries) {
    const plot = Object.values(state.plots).find((p) => p && p.box === entry.target);
    const width = Math.floor(entry.contentRect.width);
    if (plot && width > 0 && Math.abs(width - plot.width) >= 1) plot.setSize({ width, height: plotHeight(width) });
  }
});

function buildPlots(dofs) {
  for (const name of ["error", "angles"]) {
    if (state.plots[name]) { state.plots[name].destroy(); state.plots[name] = null; }
  }
  const colours = { x: "#58a6ff", y: "#f0883e", rotation: "#a371f7", alpha: "#3fb950", beta: "#d29922" };
  const translations = dofs.filter((dof) => dof === "x" || dof === "y");
  const angles = dofs.filter((dof) => ANGULAR.includes(dof));
  state.plots.error = makePlot($("plot-error"),
    translations.map((dof) => ({ label: `e_${dof} (px)`, stroke: colours[dof] })));
  state.plots.angles = makePlot($("plot-angles"),
    angles.map((dof) => ({ label: `${DOF_SYMBOL[dof]} (°)`, stroke: colours[dof] })));
  $("angles-panel").hidden = angles.length === 0;
  state.plots.dofs = dofs.join(",");
}

// The plotted run's series from its records: every move, in order.
function seriesOf(records, dofs) {
  const planar = dofs.filter((dof) => ["x", "y", "rotation"].includes(dof));
  const moved = [...records.values()].filter((r) => r.error && r.action === "moved")
    .sort((a, b) => a.iteration - b.iteration || a.seq - b.seq);
  const s = { iteration: [], translation: {}, angle: {}, cost: [], vx: [], vy: [] };
  for (const dof of dofs) (ANGULAR.includes(dof) ? s.angle : s.translation)[dof] = [];
  for (const r of moved) {
    s.iteration.push(r.iteration);
    for (const dof of ["x", "y"]) {
      if (s.translation[dof]) s.translation[dof].push(r.error[planar.indexOf(dof)] ?? null);
    }
    if (s.angle.rotation) {  // the error vector's rotation is in radians (eq. 34): shown in degrees
      const radians = r.error[planar.indexOf("rotation")];
      s.angle.rotation.push(radians === undefined || radians === null ? null : (radians * 180) / Math.PI);
    }
    if (s.angle.alpha) s.angle.alpha.push(r.alpha_deg ?? null);  // the last focus sweep's tilts
    if (s.angle.beta) s.angle.beta.push(r.beta_deg ?? null);
    s.cost.push(r.cost > 0 ? r.cost : null);
    s.vx.push(r.voltages ? r.voltages.x ?? null : null);
    s.vy.push(r.voltages ? r.voltages.y ?? null : null);
  }
  return s;
}

function drawPlots() {
  const dofs = (state.plot.dofs || ["x", "y"]).map(canonicalDof);
  if (state.plots.dofs !== dofs.join(",")) buildPlots(dofs);
  const s = seriesOf(state.plot.records, dofs);
  state.series = s;
  const translations = dofs.filter((dof) => dof === "x" || dof === "y");
  const angles = dofs.filter((dof) => ANGULAR.includes(dof));
  state.plots.error.setData([s.iteration, ...translations.map((dof) => s.translation[dof])]);
  state.plots.angles.setData([s.iteration, ...angles.map((dof) => s.angle[dof])]);
  state.plots.cost.setData([s.iteration, s.cost]);
  state.plots.voltage.setData([s.iteration, s.vx, s.vy]);
  $("error-points").textContent = `${s.iteration.length} points`;
  $("angle-points").textContent = `${s.iteration.length} points`;
  $("cost-points").textContent = `${s.cost.filter((v) => v !== null).length} points`;
  $("voltage-points").textContent = `${s.vx.filter((v) => v !== null).length} points`;
}

let drawPending = false;
function scheduleDraw() {  // iterations may come faster than a plot should redraw
  if (drawPending) return;
  drawPending = true;
  setTimeout(() => { drawPending = false; drawPlots(); }, 100);
}

// Show a run in the plots: its whole record now, then its iterations as they come.
async function plotRun(runId) {
  if (state.plot.runId !== runId) {
    state.plot = { runId, dofs: runId === state.runId && state.runDofs.length ? state.runDofs : null,
                   records: new Map(), loaded: false, loading: 0 };
    scheduleDraw();
  }
  const plot = state.plot;
  plot.loading += 1;
  try {
    const run = await api("GET", `/runs/${encodeURIComponent(runId)}`);
    if (state.plot !== plot) return run;  // another run was chosen meanwhile
    plot.dofs = (run.dofs && run.dofs.length ? run.dofs : (run.settings || {}).dofs || ["x", "y"]).map(canonicalDof);
    for (const record of run.trajectory) plot.records.set(record.seq ?? `i${record.iteration}`, record);
    plot.loaded = true;
    scheduleDraw();
    return run;
  } finally {
    plot.loading -= 1;
  }
}

function addIteration(runId, record) {
  // Another run than the one plotted: a new run is plotted when the status names it.
  if (state.plot.runId !== runId) return;
  state.plot.records.set(record.seq ?? `i${record.iteration}`, record);
  scheduleDraw();
}

// -- status ---------------------------------------------------------------------------
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

// Depth map colours: blue nearer, white at the centre's focus, red farther (diverging).
const NEAR = [33, 102, 172], ZERO = [247, 247, 247], FAR = [178, 24, 43], UNCLEAR = "#555";
function depthColour(t) {
  const end = t < 0 ? NEAR : FAR, a = Math.min(1, Math.abs(t));
  return `rgb(${ZERO.map((z, i) => Math.round(z + (end[i] - z) * a)).join(", ")})`;
}

// The last focus sweep: its tilts, a small depth map (one cell per kernel), its scale.
// Before a run's first sweep, what the taught pose's sweep said (the estimator keeps no
// depth map of it).
function showTilt(tilt, tiltTeach, taught) {
  if (!tilt) {
    $("depth").hidden = true;
    if (tiltTeach && tiltTeach.state === "sweeping") $("tilt-summary").textContent = "sweeping the focus…";
    else if (taught) {
      $("tilt-summary").textContent = `taught plane α ${fmt(taught.alpha_deg, 3)}° β ${fmt(taught.beta_deg, 3)}° · ` +
        `${taughtSweeps(taught, taught.frames)} · ${taught.kernels_used} kernels; the depth map comes with a tilt ` +
        "run's sweeps";
    } else $("tilt-summary").textContent = "no focus sweep yet: teach with tilts";
    return;
  }
  $("tilt-summary").textContent = `α ${fmt(tilt.alpha_deg, 3)}° β ${fmt(tilt.beta_deg, 3)}° · ${tilt.frames} frames · ` +
    `${tilt.kernels_used}/${tilt.kernels_total} kernels`;
  const grid = tilt.depth_map_um || [];
  const rows = grid.length, cols = rows ? grid[0].length : 0;
  $("depth").hidden = !rows || !cols;
  if (!rows || !cols) return;
  const canvas = $("depth-map"), context = canvas.getContext("2d");
  const values = grid.flat().filter((v) => v !== null);
  const span = Math.max(1e-6, ...values.map(Math.abs));
  const w = canvas.width / cols, h = canvas.height / rows;
  context.clearRect(0, 0, canvas.width, canvas.height);
  grid.forEach((row, r) => row.forEach((value, c) => {
    context.fillStyle = value === null ? UNCLEAR : depthColour(value / span);
    context.fillRect(c * w, r * h, Math.ceil(w), Math.ceil(h));
  }));
  const digits = span < 1 ? 2 : 1;
  $("depth-max").textContent = `+${span.toFixed(digits)}`;
  $("depth-min").textContent = `−${span.toFixed(digits)}`;
}

// "1 wide one", "3 wide ones".
const counted = (number, noun) => `${number} ${noun}${number === 1 ? "" : "s"}`;

// What a reference's tilts were taught from, as the CLI says it: "7 fine sweeps of 19
// frames, pooled, after 1 wide one".
function taughtSweeps(tilt, frames) {
  if (!tilt) return `${frames} frames`;
  const sweeps = tilt.sweeps || 1;
  let text = `${counted(sweeps, tilt.fine ? "fine sweep" : "sweep")} of ${tilt.frames || frames} frames`;
  if (sweeps > 1) text += ", pooled";
  if (tilt.fine && tilt.wide_sweeps) text += `, after ${counted(tilt.wide_sweeps.sweeps, "wide one")}`;
  return text;
}

// A teach with tilts answers at once; its focus sweep goes on: how far it is.
function showTiltTeach(tiltTeach, tilt) {
  const box = $("tilt-teach");
  box.hidden = !tiltTeach;
  if (!tiltTeach) return;
  const progress = $("tilt-teach-progress");
  box.classList.toggle("failed", tiltTeach.state === "failed");
  if (tiltTeach.state === "sweeping") {
    progress.hidden = false;
    if (tiltTeach.frames > 0) {
      progress.max = tiltTeach.frames;
      progress.value = tiltTeach.scanned;
      // The fine sweeps are counted on their own, after the wide ones (as the CLI does).
      const wide = tiltTeach.fine ? tiltTeach.wide_sweeps || 0 : 0;
      const most = (tiltTeach.max_sweeps || 1) - wide;
      const after = wide ? `, after ${counted(wide, "wide one")}` : "";
      const which = most > 1 || wide ? ` ${(tiltTeach.sweep || 1) - wide} (of at most ${most}${after})` : "";
      const pinned = tiltTeach.pinned_deg
        ? `; so far the tilts are pinned to ±${fmt(tiltTeach.pinned_deg[0], 3)}° and ±${fmt(tiltTeach.pinned_deg[1], 3)}°`
        : "";
      const fine = tiltTeach.fine ? "fine " : "";
      $("tilt-teach-text").textContent =
        `${fine}focus sweep${which}: ${tiltTeach.scanned} of ${tiltTeach.frames} frames scanned${pinned}`;
    } else {
      progress.removeAttribute("value");
      $("tilt-teach-text").textContent = "focus sweep: starting";
    }
  } else if (tiltTeach.state === "done") {
    progress.hidden = true;
    const plane = tilt ? `: α ${fmt(tilt.alpha_deg, 2)}° β ${fmt(tilt.beta_deg, 2)}°` : "";
    $("tilt-teach-text").textContent = `focus sweep done (${taughtSweeps(tilt, tiltTeach.frames)})${plane}; ` +
      "tilts can be servoed";
  } else {
    progress.hidden = true;
    $("tilt-teach-text").textContent = `focus sweep ${tiltTeach.state}: ${tiltTeach.error || "no reason given"}`;
  }
}

// Fields of a degree of freedom the run does not servo are not shown.
function showDofFields(dofs) {
  for (const element of document.querySelectorAll("header [data-dofs]")) {
    element.hidden = !element.dataset.dofs.split(" ").some((dof) => dofs.includes(dof));
  }
}

// While a run servoes, the Position panel shows its settings (not the form's last values).
function showRunSettings(run) {
  const settings = run.settings || {};
  const dofs = (settings.dofs || run.dofs || []).map(canonicalDof);
  if (settings.tolerance_px !== undefined) $("tolerance").value = settings.tolerance_px;
  if (settings.max_iterations !== undefined) $("max-iterations").value = settings.max_iterations;
  if (settings.hold !== undefined) $("hold").checked = settings.hold;
  if (settings.law !== undefined) $("law").value = settings.law;
  for (const box of document.querySelectorAll("input[name=dof]")) box.checked = dofs.includes(box.value);
}

function showStatus(status) {
  state.status = status;
  const badge = $("state");
  // A stage an operator stopped holds across runs and restarts: the header says so, not
  // only "idle" or "converged" (the next start or jog would be refused).
  const stageStopped = status.stage && status.stage.state === "stopped"
    && !["servoing", "stopped"].includes(status.state);
  badge.textContent = stageStopped ? `${status.state} · stage stopped` : status.state;
  badge.className = `state state-${stageStopped ? "stopped" : status.state}`;
  badge.title = stageStopped ? `the stage holds until resumed: ${status.stage.reason || ""}` : "";
  $("run-id").textContent = status.run_id || "–";
  $("iteration").textContent = status.iteration;
  // The error the controller judges (mean of its last fresh frames), else the last frame's.
  const errorPx = status.mean_error_px ?? status.error_px;
  const umPerPx = status.error_px ? status.error_um / status.error_px : null;
  $("error-px").textContent = fmt(errorPx, 3);
  $("error-um").textContent = umPerPx === null || errorPx === null ? "–" : fmt(errorPx * umPerPx, 4);
  state.runDofs = (status.dofs || []).map(canonicalDof);
  showDofFields(state.runDofs);
  $("gamma").textContent = fmt(status.rotation_deg, 3);
  $("alpha").textContent = fmt(status.alpha_deg, 3);
  $("beta").textContent = fmt(status.beta_deg, 3);
  const reference = status.reference;
  showTilt(status.tilt, reference && reference.tilt_teach, reference && reference.tilt);
  showTiltTeach(reference && reference.tilt_teach, reference && reference.tilt);
  $("frame-rate").textContent = fmt(status.frame_rate, 1);
  $("snr").textContent = fmt(status.snr_db, 1);
  $("latency").textContent = fmt(status.last_latency_ms, 1);
  $("live-seq").textContent = status.latest_frame_seq === null ? "(no frames)" : `#${status.latest_frame_seq}`;
  const acquisition = status.frame_acquisition || {};
  $("live-acquisition").textContent = acquisitionText(acquisition);
  fitBox($("live-box"), status.frame_shape);
  fitBox($("difference-box"), status.frame_shape);
  const columns = status.frame_shape ? status.frame_shape[1] : null;
  showScaleBar($("live-scale"), acquisition.pixel_size_nm, columns);
  showScaleBar($("difference-scale"), reference ? acquisition.pixel_size_nm : null, columns);
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
    const label = document.createElement("span"), value = document.createElement("span");
    label.textContent = name;
    value.className = health.up ? "up" : "down";
    value.textContent = health.up ? health.state : "DOWN";
    item.append(label, value);
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

  // The reference: the estimator's (whoever taught it); none after its restart.
  if (reference) {
    const from = reference.target ? ` (target ${reference.target})` : "";
    $("reference-id").textContent = `${reference.kind} ${reference.id}${from}`;
    fitBox($("reference-box"), reference.shape);
    showScaleBar($("reference-scale"), reference.pixel_size_nm, reference.shape ? reference.shape[1] : null);
    if (state.images.reference?.key !== reference.id) showImage("reference", "/reference.png", "no reference image", reference.id);
  } else {
    $("reference-id").textContent = "none taught";
    $("reference-scale").hidden = true;
    showImage("reference", null, "no reference taught");
  }

  // A new run is plotted; a run whose record was not there yet (just started) is asked again.
  const newRun = status.run_id && status.run_id !== state.runId;
  state.runId = status.run_id;
  const plot = state.plot;
  if (newRun || (status.run_id && (plot.runId === null || (plot.runId === status.run_id && !plot.loaded
      && !plot.loading)))) {
    plotRun(status.run_id).catch(() => {});
  }
  const servoing = status.state === "servoing";
  $("position-note").textContent = servoing && status.run_id ? `run ${status.run_id}'s settings` : "";
  if (servoing && state.settingsShownFor !== status.run_id && state.settingsLoading !== status.run_id) {
    const runId = status.run_id;
    state.settingsLoading = runId;
    api("GET", `/runs/${encodeURIComponent(runId)}`).then((run) => {
      showRunSettings(run);
      state.settingsShownFor = runId;
    }).catch(() => {}).finally(() => { if (state.settingsLoading === runId) state.settingsLoading = null; });
  }
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
      addIteration(event.run_id, event.data);
      if (event.data.snr_db !== undefined) $("snr").textContent = fmt(event.data.snr_db, 1);
    } else if (event.kind === "status") {
      if (event.data.state) {
        $("state").textContent = event.data.state;
        $("state").className = `state state-${event.data.state}`;
        if (FINISHED.includes(event.data.state)) { pollStatus(); setTimeout(loadRuns, 500); }
      }
    } else if (event.kind === "reference") {
      pollStatus();
    }
  };
  socket.onclose = (closed) => {
    // 1008: the gateway wants the API token. The status still refreshes, so the page
    // would look alive with no plots: say it once.
    if (closed.code === 1008 && !state.eventsRefusedSaid) {
      state.eventsRefusedSaid = true;
      say("live updates (plots, iterations) need the API token: enter it in the token field");
    }
    if (closed.code !== 1008) state.eventsRefusedSaid = false;
    setTimeout(connectEvents, 1000);
  };
}

// -- controls -------------------------------------------------------------------------
action($("stop"), "click", async () => {
  const stopped = await api("POST", "/stop", { reason: "stop pressed on the dashboard" });
  if (!stopped.stage_stopped) say(`the stage did not confirm the stop: ${stopped.stage_error}`);
  pollStatus();
});

for (const button of document.querySelectorAll(".jog button")) {
  action(button, "click", async () => {
    const step = fieldNumber("jog-step", "jog step (µm)") * Number(button.dataset.sign);
    await api("POST", "/stage/move", { [`${button.dataset.axis}_um`]: step, relative: true });
    pollStatus();
  });
}

action($("resume"), "click", async () => {
  await api("POST", "/stage/resume");
  pollStatus();
});

action($("teach-live"), "click", once($("teach-live"), async () => {
  const tilts = $("teach-tilts").checked ? "&tilts=true" : "";
  await api("POST", `/teach?frames=${fieldNumber("teach-frames", "average (frames)", { whole: true })}${tilts}`);
  pollStatus();
}));

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
  if ($("live").hidden) return;
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

action($("teach-mask"), "click", once($("teach-mask"), async () => {
  await api("POST", "/teach/polygon", { polygon: state.mask });
  state.mask = [];
  drawMask();
  pollStatus();
}));

function positionSettings() {
  return {
    tolerance_px: Number($("tolerance").value), max_iterations: Number($("max-iterations").value), law: $("law").value,
    dofs: [...document.querySelectorAll("input[name=dof]:checked")].map((box) => box.value), hold: $("hold").checked,
  };
}

// A run that servoes the tilts acts on every fresh frame while it waits for each focus
// sweep, so it takes more iterations (600, as the demo's; 150 for the rest): until someone
// edits the field, it follows the tilt boxes.
const MAX_ITERATIONS = { withTilts: 600, without: 150 };
$("max-iterations").addEventListener("input", () => { $("max-iterations").dataset.edited = "true"; });
for (const box of document.querySelectorAll("input[name=dof]")) {
  box.addEventListener("change", () => {
    if ($("max-iterations").dataset.edited) return;
    const tilts = [...document.querySelectorAll("input[name=dof]:checked")]
      .some((checked) => checked.value === "alpha" || checked.value === "beta");
    $("max-iterations").value = tilts ? MAX_ITERATIONS.withTilts : MAX_ITERATIONS.without;
  });
}

async function started(run) {
  state.settingsShownFor = run.run_id;  // the form already shows what was started
  await pollStatus();
  plotRun(run.run_id).catch(() => {});
}

action($("start"), "click", once($("start"), async () => {
  started(await api("POST", "/start", positionSettings()));
}));

// -- stored targets -------------------------------------------------------------------
function targetItem(target) {
  const item = document.createElement("li");
  item.dataset.target = target.name;
  const path = `/targets/${encodeURIComponent(target.name)}`;
  const thumbnail = document.createElement("img");
  thumbnail.alt = `target ${target.name}`;
  thumbnail.src = `${target.thumbnail_url || `${path}/thumbnail.png`}?t=${target.created_at_ns}`;
  thumbnail.addEventListener("error", () => { thumbnail.hidden = true; });  // never a broken image
  const what = document.createElement("div");
  what.className = "what";
  const name = document.createElement("b"), note = document.createElement("small"), when = document.createElement("small");
  name.textContent = target.name;
  note.textContent = target.note || "";
  note.hidden = !target.note;
  const reference = target.reference || {};
  const size = reference.shape ? ` · ${reference.shape[1]}×${reference.shape[0]}` : "";
  const pixel = reference.pixel_size_nm ? ` · ${fmt(reference.pixel_size_nm, 1)} nm/px` : "";
  when.textContent = `${new Date(target.created_at_ns / 1e6).toLocaleString()}${size}${pixel}`;
  what.append(name, note, when);
  const actions = document.createElement("div");
  actions.className = "actions";
  const go = document.createElement("button");
  go.className = "small go";
  go.textContent = "Go";
  go.title = "Move to its stored pose, teach its reference, then position on the image (the Position panel's settings)";
  action(go, "click", once(go, async () => started(await api("POST", `${path}/go`, { settings: positionSettings() }))));
  const exported = document.createElement("a");
  exported.className = "export";
  exported.href = target.export_url || `${path}/export`;
  exported.textContent = "Export";
  exported.download = `${target.name}.semservo-target.tif`;
  const remove = document.createElement("button");
  remove.className = "small delete";
  remove.textContent = "Delete";
  action(remove, "click", async () => {
    if (!confirm(`Delete the stored target ${target.name}?`)) return;
    await api("DELETE", path);
    await loadTargets();
  });
  actions.append(go, exported, remove);
  item.append(thumbnail, what, actions);
  return item;
}

async function loadTargets() {
  const targets = await api("GET", "/targets");
  $("targets").replaceChildren(...targets.map(targetItem));
  $("targets-count").textContent = targets.length ? `${targets.length} stored` : "none stored";
}

// Saving under a name in use asks before replacing it.
async function withReplace(work) {
  try {
    return await work(false);
  } catch (error) {
    if (error.code !== "target_exists" || !confirm(`${error.message}. Replace it?`)) throw error;
    return work(true);
  }
}

action($("target-save"), "submit", async (event) => {
  event.preventDefault();
  const name = $("target-name").value.trim(), note = $("target-note").value;
  await withReplace((replace) => api("POST", "/targets", { name, note, replace }));
  $("target-name").value = "";
  $("target-note").value = "";
  await loadTargets();
});

action($("target-import"), "change", async (e) => {
  const file = e.target.files[0];
  if (!file) return;
  try {
    await withReplace((replace) => {
      const form = new FormData();
      form.append("file", file);
      if (replace) form.append("replace", "true");
      return api("POST", "/targets/import", form);
    });
  } finally {
    e.target.value = "";
  }
  await loadTargets();
});

// -- history --------------------------------------------------------------------------
async function loadRuns() {
  const runs = await api("GET", "/runs?limit=50");
  $("runs").replaceChildren(...runs.map((run) => {
    const row = document.createElement("tr");
    row.dataset.runId = run.id;
    const started = new Date(run.started_at_ns / 1e6).toLocaleTimeString();
    const truth = run.truth && run.truth.error_norm_px !== undefined
      ? fmt(run.truth.view_error_norm_px ?? run.truth.error_norm_px, 3) : "–";
    const cells = [run.id, started, dofText(run.dofs), run.state, run.iterations, fmtDuration(run.duration_s),
      fmt(run.final_error_px, 3), truth];
    row.replaceChildren(...cells.map((value, index) => {
      const cell = document.createElement("td");
      cell.textContent = value;
      if (index === 3) cell.className = `outcome-${run.state}`;
      if (index === 2) cell.className = "dofs-cell";
      return cell;
    }));
    if (run.time_to_target_s) row.title = `at the target after ${fmtDuration(run.time_to_target_s)}; ${run.fresh_frames} fresh frames`;
    row.addEventListener("click", () => showRun(run.id).catch((error) => say(error.message)));
    return row;
  }));
}

async function showRun(runId) {
  const run = await plotRun(runId);
  for (const row of document.querySelectorAll("#runs tr")) row.classList.toggle("selected", row.dataset.runId === runId);
  $("run-detail").hidden = false;
  $("detail-id").textContent = run.id;
  $("detail-state").textContent = run.state;
  const truth = run.truth && run.truth.error_norm_px !== undefined
    ? `; true final error ${fmt(run.truth.view_error_norm_px ?? run.truth.error_norm_px, 3)} px` : "";
  const toTarget = run.time_to_target_s ? `, at the target after ${fmtDuration(run.time_to_target_s)}` : "";
  $("detail-summary").textContent = `DOFs ${dofText(run.dofs)}; ${run.iterations} iterations in ` +
    `${fmtDuration(run.duration_s)}${toTarget} (${run.fresh_frames ?? "–"} fresh frames); ` +
    `${run.reason || "no reason given"}; final error ${fmt(run.final_error_px, 3)} px${truth}; ` +
    `${run.stage_commands.length} stage commands; tolerance ${run.settings ? run.settings.tolerance_px : "–"} px`;
  const path = `/runs/${encodeURIComponent(run.id)}`;
  $("detail-csv").href = `${path}.csv`;
  $("detail-json").href = path;
  $("detail-report-link").href = `${path}/report.png`;
  const report = $("detail-report");
  report.hidden = true;
  report.onload = () => { report.hidden = false; };
  report.onerror = () => { report.hidden = true; };
  report.src = `${path}/report.png`;
}
action($("refresh-runs"), "click", loadRuns);

// -- start ----------------------------------------------------------------------------
state.plots.cost = makePlot($("plot-cost"), [{ label: "cost", stroke: "#dfe5ec" }], { log: true });
state.plots.voltage = makePlot($("plot-voltage"), [{ label: "V_x", stroke: "#58a6ff" }, { label: "V_y", stroke: "#f0883e" }]);
buildPlots(["x", "y"]);
for (const id of ["plot-error", "plot-angles", "plot-cost", "plot-voltage"]) resizer.observe($(id));
drawPlots();
$("live").addEventListener("load", drawMask);
pollStatus().then(refreshImages);
loadRuns().catch((error) => say(error.message));
loadTargets().catch((error) => say(error.message));
connectEvents();
setInterval(pollStatus, 1000);
setInterval(refreshImages, 700);
window.semservo = state;  // for the curious (and the browser tests)
