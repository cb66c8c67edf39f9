// The live view: sessions, live plots, the bone in 3D, the REST controls.
import { adoptTokenFromUrl, ApiError, call, fetchBinary, getToken, setToken, socket } from "./api.js";
import { ChunkCopy, parseMessage, parseStl } from "./mesh.js";
import { LivePlots } from "./plots.js";
import { BoneScene } from "./scene.js";
import { Controls } from "./controls.js";

const $ = (id) => document.getElementById(id);
const LIST_PERIOD_MS = 1000;
const TELEMETRY_HZ = 30;
const LIVE_FPS = 30;
const LIVE_FPS_SOFTWARE = 5;
const MESH_INTERVAL_MS = 100;
// A software renderer redraws the bone at most twice a second: no use meshing faster.
const MESH_INTERVAL_MS_SOFTWARE = 500;

const state = {
  selected: null,       // session id
  telemetryWs: null,
  meshWs: null,
  copy: null,
  lastSample: null,
  rates: new Map(),      // id → {accepted, at}
  listTimer: null,
  drawPending: false,
  lastLiveDraw: -Infinity,
  meshUpdates: 0,
};

let plots = null;
let scene = null;
let controls = null;

function showError(message) {
  const box = $("errors");
  const line = document.createElement("div");
  line.textContent = `${new Date().toLocaleTimeString()}  ${message}`;
  box.prepend(line);
  while (box.childElementCount > 6) box.lastElementChild.remove();
}

function showLogin(reason) {
  stopSession();
  if (state.listTimer) clearTimeout(state.listTimer);
  state.listTimer = null;
  $("main").hidden = true;
  $("login").hidden = false;
  $("login-reason").textContent = reason;
  $("token").focus();
}

async function start() {
  try {
    await call("GET", "/sessions");
  } catch (e) {
    if (e instanceof ApiError && e.status === 401) {
      // The server's own 401 says where its token is kept (its file, or --token).
      showLogin(getToken() ? `The server refused this token (401): ${e.detail}`
        : `This page needs the server's REST token: ${e.detail}`);
      return;
    }
    showLogin(`The server did not answer: ${e.message}`);
    return;
  }
  $("login").hidden = true;
  $("main").hidden = false;
  if (!plots) plots = new LivePlots($("plots"));
  if (!scene) scene = new BoneScene($("view"));
  if (!controls) controls = new Controls({ onError: showError, onChanged: refreshSelected });
  window.burrforceView = { scene, plots, state };
  refreshList();
}

async function refreshList() {
  if (state.listTimer) clearTimeout(state.listTimer);
  try {
    const [health, sessions] = await Promise.all([call("GET", "/health"), call("GET", "/sessions")]);
    renderHealth(health);
    const rows = await Promise.all(sessions.map(sessionRow));
    renderSessions(rows);
    if (state.selected === null || !sessions.some((s) => s.id === state.selected)) {
      const wanted = Number(new URLSearchParams(window.location.hash.slice(1)).get("session"));
      const pick = sessions.find((s) => s.id === wanted && s.state === "ready")
        || sessions.find((s) => s.state === "ready");
      if (pick) selectSession(pick.id);
      else if (state.selected !== null) stopSession();
    }
  } catch (e) {
    if (e instanceof ApiError && e.status === 401) { showLogin("The token stopped working (401)."); return; }
    showError(`sessions: ${e.message}`);
  }
  state.listTimer = setTimeout(refreshList, LIST_PERIOD_MS);
}

function renderHealth(h) {
  const loops = (h.workers || []).map((w) => `${w.state}`).join(", ");
  $("health").textContent = `server ${h.version} · ${h.status} · hot loop${(h.workers || []).length > 1 ? "s" : ""} ${loops || (h.hot_loop ? "running" : "down")} · up ${Math.round(h.uptime_s)} s`;
  $("health").className = h.status === "ok" ? "ok" : "bad";
}

async function sessionRow(s) {
  const row = {
    id: s.id, state: s.state, output: s.output, source: s.source,
    device: [s.device, s.device_attached ? "attached" : null].filter(Boolean).join(", ") || "—",
  };
  if (s.state !== "ready") return row;
  const [st, tel] = await Promise.allSettled([
    call("GET", `/sessions/${s.id}/state?max_events=0`),
    call("GET", `/sessions/${s.id}/telemetry`),
  ]);
  if (st.status === "fulfilled") {
    const prev = state.rates.get(s.id);
    // The hot loop's own clock (t_loop_s, when it read the counters), not the page's: two
    // requests that take different times to come back would skew the rate.
    const now = st.value.t_loop_s;
    row.forbidden = st.value.forbidden_events;
    row.removed = Object.values(st.value.removed_mm3 || {}).reduce((a, b) => a + b, 0);
    if (prev && now > prev.at) row.rate = Math.max(0, (st.value.accepted - prev.accepted) / (now - prev.at));
    state.rates.set(s.id, { accepted: st.value.accepted, at: now });
  }
  if (tel.status === "fulfilled") row.status = tel.value.status_names;
  return row;
}

function statusWord(row) {
  if (!row.status) return row.state;
  if (row.rate !== undefined && row.rate < 1) return "idle";
  if (row.status.includes("stale")) return "stale";
  if (row.status.includes("cutting")) return "cutting";
  if (row.status.includes("contact") || row.status.includes("shaft_contact")) return "contact";
  return "in air";
}

function renderSessions(rows) {
  const body = $("sessions-body");
  body.replaceChildren();
  for (const r of rows) {
    const tr = document.createElement("tr");
    tr.dataset.session = r.id;
    if (r.id === state.selected) tr.className = "selected";
    const word = statusWord(r);
    const cells = [
      `${r.id}`, r.source || "", r.rate === undefined ? "—" : `${Math.round(r.rate)} Hz`,
      word, r.output || "", r.device || "—", r.forbidden === undefined ? "—" : `${r.forbidden}`,
      r.removed === undefined ? "—" : r.removed.toFixed(2),
    ];
    cells.forEach((text, i) => {
      const td = document.createElement("td");
      td.textContent = text;
      if (i === 3) td.className = `status ${word.replace(" ", "-")}`;
      if (i === 6 && r.forbidden > 0) td.className = "forbidden";
      tr.appendChild(td);
    });
    tr.addEventListener("click", () => selectSession(r.id));
    body.appendChild(tr);
  }
  $("no-sessions").hidden = rows.length > 0;
}

function stopSession() {
  for (const ws of [state.telemetryWs, state.meshWs]) if (ws) { ws.onclose = null; ws.close(); }
  state.telemetryWs = state.meshWs = null;
  state.copy = null;
  state.lastSample = null;
  state.meshUpdates = 0;
  state.forbiddenKey = null;
  state.selected = null;
  if (scene) { scene.clearBone(); scene.hideTool(); scene.setForbidden(null); }
  if (plots) plots.clear();
}

async function selectSession(id) {
  if (state.selected === id) return;
  stopSession();
  state.selected = id;
  for (const tr of document.querySelectorAll("#sessions-body tr")) {
    tr.classList.toggle("selected", Number(tr.dataset.session) === id);
  }
  $("session-title").textContent = `Session ${id}`;
  await refreshSelected(true);
  if (state.selected !== id) return;  // another row was clicked meanwhile: its sockets open
  openTelemetry(id);
  openMesh(id);
}

/** Re-reads the selected session's view, parameters and materials (after a change). */
async function refreshSelected(reframe = false) {
  const id = state.selected;
  if (id === null) return;
  try {
    const [view, params, materials] = await Promise.all([
      call("GET", `/sessions/${id}`), call("GET", `/sessions/${id}/parameters`),
      call("GET", `/sessions/${id}/materials`)]);
    if (state.selected !== id) return;
    if (view.bone) {
      scene.setBoneBox(view.bone, reframe);
      applySection();  // across the new box
    }
    scene.setMaterials(materials);
    if (params.burr_profile_mm) scene.setTool(params.burr_profile_mm, params.shaft_radius_mm, params.shaft_length_mm);
    controls.show(id, view, params, materials);
    renderLegend(materials);
    loadForbidden(id, view, materials);
  } catch (e) {
    showError(`session ${id}: ${e.message}`);
  }
}

/** The forbidden structures' surface, from the mesh export of their labels; read again when
 * the bone or the material table changes (not while cutting: it is for finding them). */
async function loadForbidden(id, view, materials) {
  const labels = materials.filter((m) => m.forbidden).map((m) => m.label);
  const key = `${id}/${view.bone ? view.bone.generation : ""}/${labels.join(",")}`;
  if (state.forbiddenKey === key) return;
  state.forbiddenKey = key;
  if (!labels.length) { scene.setForbidden(null); return; }
  try {
    const query = labels.map((l) => `material=${l}`).join("&");
    const stl = await fetchBinary(`/sessions/${id}/export/mesh?format=stl&${query}`);
    if (state.selected === id && state.forbiddenKey === key) scene.setForbidden(parseStl(stl));
  } catch (e) {
    state.forbiddenKey = null;
    showError(`forbidden structures: ${e.message}`);
  }
}

function renderLegend(materials) {
  const box = $("legend");
  box.replaceChildren();
  for (const m of materials) {
    const item = document.createElement("span");
    const c = scene.labelColors.get(m.label);
    const swatch = document.createElement("i");
    swatch.style.background = c ? `#${c.getHexString()}` : "#888";
    item.append(swatch, `${m.label} ${m.name}${m.forbidden ? " (forbidden)" : ""}`);
    if (m.forbidden) item.className = "forbidden";
    box.appendChild(item);
  }
}

function openTelemetry(id) {
  const ws = socket(`/sessions/${id}/telemetry/ws`, { hz: TELEMETRY_HZ });
  state.telemetryWs = ws;
  ws.onmessage = (event) => {
    if (state.selected !== id) return;
    const sample = JSON.parse(event.data);
    if (state.lastSample && sample.installs !== state.lastSample.installs) plots.clear();
    state.lastSample = sample;
    plots.push(sample);  // every sample is plotted; redrawing is paced (drawLive)
    drawLive();
  };
  ws.onclose = (event) => {
    if (state.telemetryWs !== ws) return;
    if (event.code === 4401) { showLogin("The token was refused (4401)."); return; }
    // 4503: no telemetry on this server, or too many watchers: said once, retried slowly.
    const busy = event.code === 4503;
    if (busy) $("readout").textContent = `no live telemetry: ${event.reason}`;
    else if (event.code !== 1000) showError(`telemetry closed (${event.code}${event.reason ? `: ${event.reason}` : ""}); reconnecting`);
    setTimeout(() => { if (state.selected === id && state.telemetryWs === ws) openTelemetry(id); }, busy ? 5000 : 1000);
  };
}

/** Redraws what telemetry changes (plots, readout, burr) in one animation frame, at most
 * LIVE_FPS times a second: 30 on a GPU; 5 on a software renderer, where every visible change
 * costs a composite of the whole page in CPU time the hot loop on the same machine needs. */
function drawLive() {
  if (state.drawPending) return;
  state.drawPending = true;
  const fps = scene.software ? LIVE_FPS_SOFTWARE : LIVE_FPS;
  const wait = Math.max(0, state.lastLiveDraw + 1000 / fps - performance.now());
  setTimeout(() => requestAnimationFrame((now) => {
    state.drawPending = false;
    state.lastLiveDraw = now;
    const sample = state.lastSample;
    if (!sample) return;
    plots.draw();
    scene.setPose(sample.centre_mm, sample.axis, sample.force_server_N ?? sample.force_N);
    renderReadout(sample);
  }), wait);
}

function renderReadout(s) {
  const f = (x, d = 3) => (x === null || x === undefined ? "—" : x.toFixed(d));
  const words = s.status_names.length ? s.status_names.join(", ") : "in air";
  const line1 = [`|F| ${f(s.hand_force_magnitude_N)} N`,
    s.resistive_N ? `feed ${f(s.resistive_N[0])}  lateral ${f(s.resistive_N[1])}  normal ${f(s.resistive_N[2])} N` : ""];
  const line2 = [`${Math.round(s.rpm)} rpm`, words, `burr at ${s.centre_mm.map((x) => x.toFixed(1)).join(", ")} mm`,
    s.bone_version === null ? "" : `bone v${s.bone_version}`,
    s.age_s !== undefined && s.age_s !== null && s.age_s > 1 ? `last packet ${s.age_s.toFixed(0)} s ago` : "",
    s.loop && s.loop !== "running" ? `hot loop ${s.loop}` : ""];
  $("readout").textContent = `${line1.filter(Boolean).join("   ")}\n${line2.filter(Boolean).join("   ")}`;
}

function openMesh(id, resume = false) {
  if (!resume || !state.copy) {
    state.copy = new ChunkCopy({
      onChange: (key, chunk) => scene.setChunk(key, chunk),
      onClear: () => scene.clearBone(),
    });
  }
  const copy = state.copy;
  copy.low = null;  // an update cut short by the dropped connection starts over
  const query = { format_version: 2, frame: "server", winding: "ccw", chunk_bricks: 2,
    interval_ms: scene.software ? MESH_INTERVAL_MS_SOFTWARE : MESH_INTERVAL_MS };
  // Reopened from the copy's version: only what changed meanwhile comes again.
  if (copy.have !== null) Object.assign(query, { since: copy.have, generation: copy.generation });
  const ws = socket(`/sessions/${id}/mesh/ws`, query);
  ws.binaryType = "arraybuffer";
  state.meshWs = ws;
  ws.onmessage = (event) => {
    if (state.meshWs !== ws) return;
    try {
      copy.apply(parseMessage(event.data));
      state.meshUpdates += 1;
      $("mesh-status").textContent = `surface: ${copy.chunks.size} chunks at bone v${copy.have ?? "…"} (${state.meshUpdates} updates)`;
    } catch (e) {
      showError(`mesh: ${e.message}`);
    }
  };
  ws.onclose = (event) => {
    if (state.meshWs !== ws) return;
    if (event.code === 4401) { showLogin("The token was refused (4401)."); return; }
    if (event.code === 4409) {
      $("mesh-status").textContent = `no surface: ${event.reason}`;
      return;
    }
    const busy = event.code === 4503;
    if (busy) $("mesh-status").textContent = `no surface: ${event.reason}`;
    else if (event.code !== 1000) showError(`mesh closed (${event.code}${event.reason ? `: ${event.reason}` : ""}); reconnecting`);
    setTimeout(() => { if (state.selected === id && state.meshWs === ws) openMesh(id, true); }, busy ? 5000 : 1000);
  };
}

function applySection() {
  scene.setSection($("section-axis").value, Number($("section-at").value) / 100, $("section-flip").checked);
}

function wireStatic() {
  $("login-form").addEventListener("submit", (event) => {
    event.preventDefault();
    setToken($("token").value.trim());
    $("token").value = "";
    start();
  });
  $("logout").addEventListener("click", () => { setToken(""); showLogin("Token forgotten for this tab."); });
  for (const name of ["iso", "top", "front", "side"]) {
    $(`view-${name}`).addEventListener("click", () => scene.view(name));
  }
  for (const id of ["section-axis", "section-at", "section-flip"]) $(id).addEventListener("input", applySection);
  $("show-burr").addEventListener("input", () => scene.setToolShown($("show-burr").checked));
  $("show-forbidden").addEventListener("input", () => scene.setForbiddenShown($("show-forbidden").checked));
}

adoptTokenFromUrl();
wireStatic();
start();
