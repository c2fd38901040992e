// rovergate's mission-control page: it draws the ground station's state (GET /api/state,
// polled) and queues commands (POST /api/commands). It keeps no state of its own that matters:
// a reload, or another browser, draws the same.
"use strict";

const POLL_MS = 500;
const SPAN_BEFORE = 40;  // link steps of the plan drawn before now
const SPAN_AFTER = 120;  // and after
const $ = (id) => document.getElementById(id);
let state = null;
let dictionaryKey = "";
let mapStep = null;
let mapData = { points: [], path: [] };

function fmt(x, digits = 0) {
  return x === null || x === undefined ? "–" : Number(x).toFixed(digits);
}

function duration(s) {
  if (s === null || s === undefined) return "–";
  if (s < 120) return `${s.toFixed(0)} s`;
  if (s < 7200) return `${(s / 60).toFixed(1)} min`;
  return `${(s / 3600).toFixed(1)} h`;
}

// --- the allowlist: the same checks as mission/link/commands.py -------------------------------

const NUMBER = /^-?\d{1,12}(\.\d{1,12})?([eE][-+]?\d{1,3})?$/;

function plain(x) {
  return Number.isInteger(x) ? String(x) : String(x);
}

// The reason a setting's value is refused, or null: the rover's words (setting_value).
function refusal(setting, raw) {
  raw = raw.trim();
  const isNumber = NUMBER.test(raw);
  const value = isNumber ? Number(raw) : NaN;
  const integral = isNumber && /^-?\d+$/.test(raw);
  if (!isNumber || (setting.kind === "integer" && !integral)) {
    const kind = setting.kind === "integer" ? "an integer" : "a number";
    return `${setting.key} takes ${kind}, got '${raw.slice(0, 40)}'`;
  }
  if (!(setting.least <= value && value <= setting.most)) {
    return `${setting.key} must be between ${plain(setting.least)} and ${plain(setting.most)}, got '${raw}'`;
  }
  return null;
}

function fillSelect(select, values) {
  const keep = select.value;
  select.replaceChildren(...values.map((v) => new Option(v, v)));
  if (values.includes(keep)) select.value = keep;
}

function buildComposer(dictionary) {
  const key = JSON.stringify(dictionary);
  if (key === dictionaryKey) return;
  dictionaryKey = key;
  fillSelect($("verb"), ["pause", "resume", "abort", "set", "condition", "planner"]);
  fillSelect($("set-field"), dictionary.settings.map((s) => s.key));
  fillSelect($("condition-name"), dictionary.conditions);
  fillSelect($("planner-name"), dictionary.planners);
  $("dictionary-source").textContent = dictionary.source === "rover"
    ? "(the rover's allowlist, downlinked)" : "(this station's allowlist until the rover's comes down)";
  showVerb();
}

function currentSetting() {
  return state.dictionary.settings.find((s) => s.key === $("set-field").value);
}

function showVerb() {
  const verb = $("verb").value;
  $("set-fields").hidden = verb !== "set";
  $("condition-name").hidden = verb !== "condition";
  $("planner-name").hidden = verb !== "planner";
  if (verb === "set" && state) {
    const s = currentSetting();
    const input = $("set-value");
    input.min = s.least;
    input.max = s.most;
    input.step = s.kind === "integer" ? "1" : "any";
    $("set-range").textContent = `${s.kind}, ${plain(s.least)} to ${plain(s.most)}`;
  }
}

function composed() {
  const verb = $("verb").value;
  if (verb === "set") {
    const s = currentSetting();
    const raw = $("set-value").value === "" ? $("set-value").validity.badInput ? "?" : "" : $("set-value").value;
    const why = refusal(s, raw);
    return why ? { refused: why } : { line: `set ${s.key}=${raw.trim()}` };
  }
  if (verb === "condition") return { line: `condition ${$("condition-name").value}` };
  if (verb === "planner") return { line: `planner ${$("planner-name").value}` };
  return { line: verb };
}

function say(text, kind) {
  const out = $("compose-result");
  out.textContent = text;
  out.className = kind;
}

async function queue(line) {
  const response = await fetch("/api/commands", {
    method: "POST", headers: { "Content-Type": "application/json" },
    body: JSON.stringify({ line }),
  });
  const answer = await response.json();
  if (response.ok) say(`command ${answer.id} queued: ${line}`, "queued");
  else say(`refused: ${answer.error}`, "refused");
  poll();
}

// --- drawing -------------------------------------------------------------------------------

function canvas(id) {
  const c = $(id);
  const ctx = c.getContext("2d");
  ctx.clearRect(0, 0, c.width, c.height);
  return [c, ctx];
}

function drawTimeline(plan) {
  const [c, ctx] = canvas("timeline");
  if (!plan) return;
  // A span of the plan around now: the windows just past and the next ones.
  const now = plan.now_link_step || 0;
  const end = Math.max(1, ...plan.windows.map((w) => w[1]), now);
  const first = Math.max(0, now - SPAN_BEFORE);
  const last = Math.min(end, first + SPAN_BEFORE + SPAN_AFTER);
  const x = (t) => 10 + (c.width - 20) * (Math.min(Math.max(t, first), last) - first) / Math.max(1, last - first);
  ctx.fillStyle = "#2a3646";
  ctx.fillRect(10, 30, c.width - 20, 14);
  for (const [a, b] of plan.windows) {
    if (b < first || a > last) continue;
    ctx.fillStyle = plan.now_link_step !== null && b <= plan.now_link_step ? "#2f6d52" : "#3ecf8e";
    ctx.fillRect(x(a), 26, Math.max(2, x(b) - x(a)), 22);
  }
  ctx.fillStyle = "#8796a8";
  ctx.font = "11px system-ui";
  ctx.fillText(`link step ${first}`, 10, 64);
  ctx.fillText(`${last}`, c.width - 40, 64);
  if (plan.now_link_step !== null) {
    ctx.strokeStyle = "#f5b94a";
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(x(plan.now_link_step), 18);
    ctx.lineTo(x(plan.now_link_step), 54);
    ctx.stroke();
    ctx.fillStyle = "#f5b94a";
    ctx.fillText(`now ~${plan.now_link_step}`, Math.min(x(plan.now_link_step) + 4, c.width - 60), 14);
  }
}

function drawCoverage(points) {
  const [c, ctx] = canvas("coverage");
  // Up to a quarter past the last step seen (a long mission's start would be a sliver).
  const seen = Math.max(20, ...points.map((p) => p[0]));
  const total = Math.min(state.rover.steps_total || Infinity, Math.ceil(seen * 1.25));
  const x = (t) => 30 + (c.width - 40) * t / total;
  const y = (v) => c.height - 20 - (c.height - 30) * v;
  ctx.strokeStyle = "#2a3646";
  ctx.strokeRect(30, 10, c.width - 40, c.height - 30);
  ctx.fillStyle = "#8796a8";
  ctx.font = "11px system-ui";
  ctx.fillText("1", 16, 16);
  ctx.fillText("0", 16, c.height - 20);
  ctx.fillText(`step ${total}`, c.width - 60, c.height - 5);
  ctx.strokeStyle = "#4fb3ff";
  ctx.lineWidth = 2;
  ctx.beginPath();
  points.forEach(([t, v], i) => (i ? ctx.lineTo(x(t), y(v)) : ctx.moveTo(x(t), y(v))));
  ctx.stroke();
}

function drawMap() {
  const [c, ctx] = canvas("map");
  const pts = mapData.points;
  const path = mapData.path;
  const all = pts.concat(path.map(([px, py]) => [px, py, 0]));
  if (!all.length) return;
  let [x0, x1, y0, y1, z0, z1] = [Infinity, -Infinity, Infinity, -Infinity, Infinity, -Infinity];
  for (const [px, py, pz] of all) {
    x0 = Math.min(x0, px); x1 = Math.max(x1, px); y0 = Math.min(y0, py); y1 = Math.max(y1, py);
  }
  for (const p of pts) { z0 = Math.min(z0, p[2]); z1 = Math.max(z1, p[2]); }
  const span = Math.max(x1 - x0, y1 - y0, 1e-3);
  const sx = (px) => 10 + (c.width - 20) * (px - x0) / span;
  const sy = (py) => c.height - 10 - (c.height - 20) * (py - y0) / span;
  for (const [px, py, pz] of pts) {
    const h = z1 > z0 ? (pz - z0) / (z1 - z0) : 0.5;
    ctx.fillStyle = `hsl(${240 - 200 * h}, 70%, 55%)`;
    ctx.fillRect(sx(px), sy(py), 2, 2);
  }
  if (path.length) {
    ctx.strokeStyle = "#ffffff";
    ctx.lineWidth = 2;
    ctx.beginPath();
    path.forEach(([px, py], i) => (i ? ctx.lineTo(sx(px), sy(py)) : ctx.moveTo(sx(px), sy(py))));
    ctx.stroke();
    const [ex, ey] = path[path.length - 1];
    ctx.fillStyle = "#f5b94a";
    ctx.beginPath();
    ctx.arc(sx(ex), sy(ey), 5, 0, 2 * Math.PI);
    ctx.fill();
  }
}

function commandRow(c) {
  const tr = document.createElement("tr");
  tr.dataset.id = c.id;
  const radiated = c.radiated
    ? `link step ${c.radiated.step}` + (c.radiated.arrives_s !== undefined ? `, reaches the rover at t=${fmt(c.radiated.arrives_s)} s` : "")
    : "–";
  const ack = c.ack ? `${c.ack.state} at step ${c.ack.step}${c.ack.detail ? ": " + c.ack.detail : ""}` : "–";
  const cells = [String(c.id), c.line, c.stage || "–", radiated, ack];
  cells.forEach((text, i) => {
    const td = document.createElement("td");
    td.textContent = text;
    if (i === 2) { td.className = "stage"; td.dataset.stage = c.stage || ""; }
    tr.appendChild(td);
  });
  return tr;
}

function render() {
  const r = state.rover;
  $("rover-state").textContent = r.state;
  $("rover-state").dataset.state = r.state;
  $("last-step").textContent = r.last_step ?? "–";
  $("steps-total").textContent = r.steps_total ?? "–";
  $("age").textContent = duration(r.age_s);
  $("predicted-step").textContent = r.predicted_step ?? "–";
  $("condition").textContent = r.condition ?? "–";
  const plan = state.plan;
  if (plan) {
    const next = plan.next_window;
    $("link-state").textContent = plan.in_window ? "in a window (estimated)"
      : next ? `blackout; next window at link step ${next[0]}` : "no window left";
    $("plan-text").textContent = `light time ${fmt(plan.light_time_s)} s (${plan.light_steps} steps of ${fmt(plan.step_s)} s), `
      + `downlink ${plan.downlink_kbps} kbit/s, ${plan.windows.length} windows; `
      + `now ~ t=${fmt(plan.now_s)} s (link step ${plan.now_link_step ?? "–"})`;
  }
  drawTimeline(plan);
  const q = state.onboard_queue;
  $("onboard-queue").textContent = q
    ? `${q.items} items, ${(q.bytes / 1024).toFixed(1)} KiB, ${q.unacked} unacknowledged (at link step ${q.link_step})` : "–";
  const waiting = state.ground_queue;
  $("ground-queue").textContent = waiting.length ? waiting.map((c) => `#${c.id} ${c.line}`).join(", ") : "none";
  const t = state.telemetry;
  const cov = t.coverage;
  $("coverage-now").textContent = cov.length ? fmt(cov[cov.length - 1][1], 3) : "–";
  $("metres").textContent = `${fmt(t.metres_driven, 1)} m`;
  $("collisions").textContent = t.collisions;
  $("stuck").textContent = `${t.stuck_steps} (of ${t.poses} poses)`;
  $("received").textContent = t.received;
  drawCoverage(cov);
  $("events").replaceChildren(...t.events.slice().reverse().map((e) => {
    const li = document.createElement("li");
    li.textContent = `step ${e.step}: ${e.kind}${e.detail ? " — " + e.detail : ""}`;
    return li;
  }));
  $("commands").tBodies[0].replaceChildren(...state.commands.slice().reverse().map(commandRow));
  buildComposer(state.dictionary);
  if (t.map_step !== mapStep) {
    mapStep = t.map_step;
    fetch("/api/map").then((res) => res.json()).then((m) => {
      mapData = m;
      $("map-step").textContent = m.step === null ? "" : `(snapshot of step ${m.step}, ${m.points.length} points)`;
      drawMap();
    });
  } else {
    mapData.path = t.path;
    drawMap();
  }
}

async function poll() {
  try {
    const response = await fetch("/api/state", { cache: "no-store" });
    if (!response.ok) {
      $("link-state").textContent = `the station answered ${response.status}`;
      return;
    }
    state = await response.json();
    render();
    document.body.dataset.ready = "true";
  } catch (err) {
    $("link-state").textContent = "the ground station is not answering";
  }
}

document.addEventListener("DOMContentLoaded", () => {
  $("verb").addEventListener("change", showVerb);
  $("set-field").addEventListener("change", showVerb);
  $("composer").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const c = composed();
    if (c.refused) say(`refused: ${c.refused}`, "refused");
    else queue(c.line);
  });
  $("raw").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const line = $("raw-line").value.trim();
    if (line) queue(line);
  });
  $("composer").noValidate = true;
  poll();
  setInterval(poll, POLL_MS);
});
