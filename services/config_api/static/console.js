// safemimic web console: live status over server-sent events, parameter forms, calibrate.
// Plain JavaScript, no build step. Talks only to the config API that serves this page.
"use strict";

const WINDOW_S = 10;            // plotted history (s)
const MODE_COLORS = { nominal: "#2e8540", active: "#c77c02", relaxed: "#c0392b", hold: "#6c3483" };
const SAFETY_NUMBERS = ["gamma", "phi", "self_margin", "human_margin", "human_predict_s", "human_standoff_m", "human_speed_mps", "intrusion_backout_mps", "k", "dt"];  // safety form's numbers (API names)
const samples = [];             // {t, hSelf, hHuman, solve, mode}
let loaded = null;              // the last GET /api/config response
let dirty = false;              // a form was edited since it was filled
let edits = 0;                  // form edits so far (a reload started before the newest one keeps it)

const $ = (id) => document.getElementById(id);
const fmt = (x, digits = 3) => (x === null || x === undefined ? "–" : Number(x).toFixed(digits));

// ---------------------------------------------------------------------------- HTTP
function headers(json) {
  const h = {};
  const token = $("token").value.trim();
  if (token) h["Authorization"] = "Bearer " + token;
  const operator = $("operator").value.trim();
  if (operator) h["X-Operator"] = operator;
  if (json) h["Content-Type"] = "application/json";
  return h;
}

async function call(method, url, body) {
  const response = await fetch(url, {
    method, headers: headers(body !== undefined), body: body === undefined ? undefined : JSON.stringify(body),
  });
  let data = null;
  try { data = await response.json(); } catch (e) { /* empty or not JSON */ }
  return { ok: response.ok, status: response.status, data };
}

function describeError(result) {
  if (result.status === 401) return "401: a valid API token is required (field 'API token')";
  const detail = result.data && result.data.detail;
  if (Array.isArray(detail)) {
    return result.status + ": " + detail.map((e) => e.loc.filter((p) => p !== "body").join(".") + ": " + e.msg).join("\n");
  }
  return result.status + ": " + (detail || "request failed");
}

function showResult(result, what) {
  const box = $("result");
  if (result.ok) {
    const d = result.data;
    box.className = "ok";
    box.textContent = what + ": " + d.detail + (d.changed.length ? "\nchanged: " + d.changed.join(", ") : "");
  } else {
    box.className = "error";
    box.textContent = what + " refused — " + describeError(result);
  }
}

// ---------------------------------------------------------------------------- forms
function vectorRow(table, name, label, values, placeholder) {
  const row = table.insertRow();
  const th = document.createElement("th");
  th.textContent = label;
  row.appendChild(th);
  for (let i = 0; i < loaded.joint_names.length; i++) {
    const input = document.createElement("input");
    input.type = "number"; input.step = "any"; input.name = name + "." + i;
    input.value = values === null ? "" : values[i];
    if (placeholder) input.placeholder = placeholder(i);
    row.insertCell().appendChild(input);
  }
}

function jointHeader(table) {
  const head = table.createTHead().insertRow();
  head.appendChild(document.createElement("th"));
  for (const name of loaded.joint_names) {
    const th = document.createElement("th");
    th.textContent = name.replace("_joint", "").replace("shoulder", "sh").replaceAll("_", " ");
    head.appendChild(th);
  }
}

function fillForms() {
  const s = loaded.safety, r = loaded.retarget;
  const sf = $("safety-form");
  for (const name of SAFETY_NUMBERS) sf.elements[name].value = s[name];
  sf.elements.human_velocity_term.checked = s.human_velocity_term;
  sf.elements.on_intrusion.value = s.on_intrusion;
  sf.elements.feedforward.checked = s.feedforward;
  sf.elements.target_path.value = s.target_path;

  const groups = $("pair-groups");
  groups.querySelectorAll("label").forEach((l) => l.remove());
  for (const group of ["self_arms", "self_torso", "self_legs", "human"]) {
    const label = document.createElement("label");
    const box = document.createElement("input");
    box.type = "checkbox"; box.name = "group." + group; box.checked = s.enabled_pair_groups.includes(group);
    label.append(box, " " + group);
    groups.appendChild(label);
  }

  const sv = $("safety-vectors");
  sv.replaceChildren(); jointHeader(sv);
  vectorRow(sv, "w", "w", s.w);
  vectorRow(sv, "u_min", "u_min", s.u_min, (i) => String(-s.u_max[i]));
  vectorRow(sv, "u_max", "u_max", s.u_max);
  vectorRow(sv, "accel_max", "accel_max", s.accel_max, () => "none");

  const radii = $("radii");
  radii.replaceChildren();
  const robotRow = radii.insertRow(), humanRow = radii.insertRow();
  robotRow.insertCell().textContent = "robot r (m)";
  for (const name of loaded.capsule_names) {
    const input = document.createElement("input");
    input.type = "number"; input.step = "any"; input.name = "robot." + name; input.title = name;
    input.placeholder = name.replace("_", " ");
    input.value = name in s.capsule_radii.robot ? s.capsule_radii.robot[name] : "";
    robotRow.insertCell().appendChild(input);
  }
  humanRow.insertCell().textContent = "human r (m)";
  for (const name of ["torso", "upper_arm", "forearm", "thigh"]) {
    const input = document.createElement("input");
    input.type = "number"; input.step = "any"; input.name = "human." + name; input.title = name;
    input.value = s.capsule_radii.human[name];
    humanRow.insertCell().appendChild(input);
  }

  const rv = $("retarget-vectors");
  rv.replaceChildren(); jointHeader(rv);
  vectorRow(rv, "S", "S", r.S);
  vectorRow(rv, "b", "b", r.b);
  vectorRow(rv, "q_home", "q_home", r.q_home);
  vectorRow(rv, "theta_home", "θ_home", r.theta_home);
  $("retarget-form").elements.mirror.checked = r.mirror;
  $("retarget-form").elements.method.value = r.method;
  dirty = false;
}

function readVector(form, name) {
  const values = loaded.joint_names.map((_, i) => form.elements[name + "." + i].value.trim());
  if (values.every((v) => v === "")) return null;
  return values.map(Number);
}

const same = (a, b) => JSON.stringify(a) === JSON.stringify(b);

function safetyPatch() {
  const f = $("safety-form"), s = loaded.safety, patch = {};
  for (const name of SAFETY_NUMBERS) {
    const value = Number(f.elements[name].value);
    if (value !== s[name]) patch[name] = value;
  }
  if (f.elements.human_velocity_term.checked !== s.human_velocity_term) patch.human_velocity_term = f.elements.human_velocity_term.checked;
  if (f.elements.on_intrusion.value !== s.on_intrusion) patch.on_intrusion = f.elements.on_intrusion.value;
  if (f.elements.feedforward.checked !== s.feedforward) patch.feedforward = f.elements.feedforward.checked;
  if (f.elements.target_path.value !== s.target_path) patch.target_path = f.elements.target_path.value;
  for (const name of ["w", "u_min", "u_max", "accel_max"]) {
    const value = readVector(f, name);
    if (!same(value, s[name])) patch[name] = value;
  }
  const groups = ["self_arms", "self_torso", "self_legs", "human"].filter((g) => f.elements["group." + g].checked);
  if (!same([...groups].sort(), [...s.enabled_pair_groups].sort())) patch.enabled_pair_groups = groups;
  const robot = {}, human = {};
  for (const name of loaded.capsule_names) {
    const text = f.elements["robot." + name].value.trim();
    const old = name in s.capsule_radii.robot ? s.capsule_radii.robot[name] : null;
    const value = text === "" ? null : Number(text);
    if (value !== old) robot[name] = value;
  }
  for (const name of ["torso", "upper_arm", "forearm", "thigh"]) {
    const value = Number(f.elements["human." + name].value);
    if (value !== s.capsule_radii.human[name]) human[name] = value;
  }
  const radii = {};
  if (Object.keys(robot).length) radii.robot = robot;
  if (Object.keys(human).length) radii.human = human;
  if (Object.keys(radii).length) patch.capsule_radii = radii;
  return patch;
}

function retargetPatch() {
  const f = $("retarget-form"), r = loaded.retarget, patch = {};
  for (const name of ["S", "b", "q_home", "theta_home"]) {
    const value = readVector(f, name);
    if (!same(value, r[name])) patch[name] = value;
  }
  if (f.elements.mirror.checked !== r.mirror) patch.mirror = f.elements.mirror.checked;
  if (f.elements.method.value !== r.method) patch.method = f.elements.method.value;
  return patch;
}

async function loadConfig() {
  const editsBefore = edits;
  const result = await call("GET", "/api/config");
  if (!result.ok) { showResult(result, "loading the configuration"); return; }
  loaded = result.data;
  $("robot-id").textContent = loaded.config.robot_id;
  $("config-version").textContent = "v" + loaded.version;
  // an edit typed while the request was in flight is the operator's newest intent: keep it (a
  // patch is the difference to `loaded`, so it still sends exactly what was edited)
  if (edits === editsBefore) fillForms();
  loadHistory();
}

async function loadHistory() {
  const result = await call("GET", "/api/config/history?limit=10");
  if (!result.ok) return;
  const body = $("history").tBodies[0];
  body.replaceChildren();
  for (const entry of result.data.entries) {
    const row = body.insertRow();
    const changes = entry.diff.map((c) => c.path + ": " + JSON.stringify(c.old) + " → " + JSON.stringify(c.new)).join("\n");
    for (const text of ["v" + entry.version, new Date(entry.time).toLocaleTimeString(), entry.who + "@" + entry.client, entry.action, changes]) {
      row.insertCell().textContent = text;
    }
  }
}

async function submit(event, url, patch, what) {
  event.preventDefault();
  $("result").className = ""; $("result").textContent = what + ": sending…";
  const result = await call("PATCH", url, patch);
  showResult(result, what);
  if (result.ok) await loadConfig();
}

// ---------------------------------------------------------------------------- live data
function onStatus(status) {
  const mode = $("mode");
  mode.textContent = status.available ? status.mode : "no status";
  mode.className = "mode " + (status.mode || "");
  $("h-self").textContent = fmt(status.h_min_self);
  $("h-human").textContent = fmt(status.h_min_human);
  $("solve-ms").textContent = fmt(status.solve_time_ms);
  $("step-ms").textContent = fmt(status.step_time_ms);
  $("active").textContent = status.available ? status.active_constraints + " / " + status.total_constraints : "–";
  $("human-age").textContent = fmt(status.human_age_s, 2);
  $("misses").textContent = status.deadline_misses ?? "–";
  $("backend").textContent = status.backend || "–";
  // tripped watchdogs now, e.g. "human_stale, executor_holding"; "ok" when none
  const tripped = Object.entries(status.watchdogs || {}).filter(([, on]) => on).map(([name]) => name);
  $("watchdogs").textContent = status.available ? (tripped.join(", ") || "ok") : "–";
  // robot–person pairs that gave way (relaxed), and a person inside a robot capsule's margin
  $("relaxed-pairs").textContent = status.available ? ((status.relaxed_pairs || []).join(", ") || "none") : "–";
  // what the robot does about it is the configured response (safety.on_intrusion)
  const response = loaded && loaded.safety.on_intrusion === "retreat" ? "the robot retreats" : "the robot stops";
  $("intrusion").textContent = status.available ? (status.person_intrusion ? "yes: " + response : "no") : "–";
  $("backing-out").textContent = status.available ? (status.backing_out ? "yes" : "no") : "–";
  $("lateness").textContent = fmt(status.human_lateness_ms, 0);
  $("applied-version").textContent = status.applied_config_version === null ? "–" : "v" + status.applied_config_version;
  if (!status.available) return;
  samples.push({ t: performance.now() / 1000, hSelf: status.h_min_self, hHuman: status.h_min_human, solve: status.solve_time_ms, mode: status.mode });
  const canvas = $("plot-h");
  canvas.dataset.samples = String(Number(canvas.dataset.samples) + 1);
}

function onConfig(event) {
  if (loaded && event.version !== loaded.version) {
    $("config-version").textContent = "v" + event.version;
    if (!dirty) loadConfig(); else loadHistory();
  }
}

function parseEvents(buffer, handle) {
  let end;
  while ((end = buffer.indexOf("\n\n")) >= 0) {
    const block = buffer.slice(0, end);
    buffer = buffer.slice(end + 2);
    let name = "message", data = "";
    for (const line of block.split("\n")) {
      if (line.startsWith("event:")) name = line.slice(6).trim();
      else if (line.startsWith("data:")) data += line.slice(5).trim();
    }
    if (data) handle(name, JSON.parse(data));
  }
  return buffer;
}

// fetch-based event stream (unlike EventSource it can send the Authorization header)
async function stream() {
  for (;;) {
    try {
      const response = await fetch("/api/status/stream", { headers: headers(false) });
      if (!response.ok) throw new Error("HTTP " + response.status);
      $("stream-state").textContent = "live";
      const reader = response.body.getReader();
      const decoder = new TextDecoder();
      let buffer = "";
      for (;;) {
        const { value, done } = await reader.read();
        if (done) break;
        buffer = parseEvents(buffer + decoder.decode(value, { stream: true }), (name, data) => {
          if (name === "status") onStatus(data); else if (name === "config") onConfig(data);
        });
      }
    } catch (e) {
      $("stream-state").textContent = "disconnected (" + e.message + "), retrying…";
    }
    $("stream-state").textContent = "reconnecting…";
    await new Promise((resolve) => setTimeout(resolve, 1000));
  }
}

// ---------------------------------------------------------------------------- plots
function drawSeries(ctx, w, h, now, keys, colors, lo, hi) {
  const x = (t) => w * (1 - (now - t) / WINDOW_S);
  const y = (v) => h - ((v - lo) / (hi - lo)) * h;
  keys.forEach((key, k) => {
    ctx.strokeStyle = colors[k]; ctx.lineWidth = 1.5; ctx.beginPath();
    let pen = false;
    for (const s of samples) {
      const v = s[key];
      if (v === null || v === undefined) { pen = false; continue; }
      if (pen) ctx.lineTo(x(s.t), y(v)); else ctx.moveTo(x(s.t), y(v));
      pen = true;
    }
    ctx.stroke();
  });
  return y;
}

function range(keys, floorLo, floorHi) {
  let lo = floorLo, hi = floorHi;
  for (const s of samples) for (const key of keys) {
    const v = s[key];
    if (v !== null && v !== undefined) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
  }
  const pad = 0.08 * (hi - lo || 1);
  return [lo - pad, hi + pad];
}

function draw() {
  const now = performance.now() / 1000;
  while (samples.length && now - samples[0].t > WINDOW_S) samples.shift();

  const ph = $("plot-h"), c = ph.getContext("2d");
  c.clearRect(0, 0, ph.width, ph.height);
  const [lo, hi] = range(["hSelf", "hHuman"], -0.02, 0.1);
  const y = drawSeries(c, ph.width, ph.height, now, ["hSelf", "hHuman"], ["#1f6feb", "#d9480f"], lo, hi);
  c.strokeStyle = "#999"; c.setLineDash([4, 4]); c.beginPath(); c.moveTo(0, y(0)); c.lineTo(ph.width, y(0)); c.stroke(); c.setLineDash([]);
  c.fillStyle = "#6b7580"; c.font = "12px sans-serif";
  c.fillText(hi.toFixed(3) + " m", 4, 12); c.fillText(lo.toFixed(3) + " m", 4, ph.height - 4);

  const ps = $("plot-solve"), d = ps.getContext("2d");
  d.clearRect(0, 0, ps.width, ps.height);
  const [slo, shi] = range(["solve"], 0, 0.05);
  drawSeries(d, ps.width, ps.height, now, ["solve"], ["#495057"], Math.max(0, slo), shi);
  d.fillStyle = "#6b7580"; d.font = "12px sans-serif"; d.fillText(shi.toFixed(3) + " ms", 4, 12);

  const pm = $("plot-mode"), m = pm.getContext("2d");
  m.clearRect(0, 0, pm.width, pm.height);
  for (let i = 0; i < samples.length; i++) {
    const x0 = pm.width * (1 - (now - samples[i].t) / WINDOW_S);
    const x1 = i + 1 < samples.length ? pm.width * (1 - (now - samples[i + 1].t) / WINDOW_S) : pm.width;
    m.fillStyle = MODE_COLORS[samples[i].mode] || "#888";
    m.fillRect(x0, 0, Math.max(1, x1 - x0), pm.height);
  }
  requestAnimationFrame(draw);
}

// ---------------------------------------------------------------------------- start
$("window-s").textContent = WINDOW_S;
$("token").value = sessionStorage.getItem("safemimic-token") || "";
$("token").addEventListener("change", () => sessionStorage.setItem("safemimic-token", $("token").value.trim()));
for (const id of ["safety-form", "retarget-form"]) $(id).addEventListener("input", () => { dirty = true; edits += 1; });
$("safety-form").addEventListener("submit", (e) => submit(e, "/api/config/safety", safetyPatch(), "safety"));
$("retarget-form").addEventListener("submit", (e) => submit(e, "/api/config/retarget", retargetPatch(), "retargeting"));
$("calibrate").addEventListener("click", async () => {
  $("result").className = ""; $("result").textContent = "calibrating…";
  const result = await call("POST", "/api/calibrate");
  showResult(result, "calibration");
  if (result.ok) await loadConfig();
});
loadConfig();
stream();
requestAnimationFrame(draw);
