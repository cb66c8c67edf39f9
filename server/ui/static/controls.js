// The REST controls of the selected session: parameters, features, materials, bone, snapshots,
// recording, exports. Each action says what the server answered; nothing is kept locally.
import { call, download } from "./api.js";

const $ = (id) => document.getElementById(id);
const NUMBER_FIELDS = [
  ["us_n_mm2", "Us (N/mm²)"], ["k", "K"], ["fd_N", "Fd (N)"], ["g", "g"], ["harmonic", "harmonic"],
  ["radius_mm", "burr radius (mm)"], ["min_cutting_rpm", "min cutting rpm"],
  ["shaft_radius_mm", "shaft radius (mm)"], ["shaft_length_mm", "shaft length (mm)"],
  ["shaft_stiffness_n_mm3", "shaft stiffness (N/mm³)"],
];
const FEATURES = ["model", "carving", "vibration", "shaft", "deltas"];

function el(tag, attrs = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") e.className = v;
    else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null && v !== false) e.setAttribute(k, v === true ? "" : v);
  }
  e.append(...children);
  return e;
}

export class Controls {
  constructor({ onError, onChanged }) {
    this.onError = onError;
    this.onChanged = onChanged;
    this.root = $("controls");
  }

  /** Runs one REST action, shows its outcome in the section's status line. */
  async act(statusId, label, fn, { refresh = true } = {}) {
    const status = $(statusId);
    status.className = "action-status";
    status.textContent = `${label}…`;
    try {
      const result = await fn();
      status.textContent = `${label}: done${typeof result === "string" ? ` (${result})` : ""}`;
      status.classList.add("ok");
      if (refresh) await this.onChanged();
    } catch (e) {
      status.textContent = `${label}: ${e.message}`;
      status.classList.add("bad");
      this.onError(`${label}: ${e.message}`);
    }
  }

  show(id, view, params, materials) {
    this.id = id;
    const open = new Set([...this.root.querySelectorAll("details[open]")].map((d) => d.dataset.part));
    if (!open.size) open.add("parameters");
    // An action's outcome outlives the rebuild its success triggers.
    const statuses = [...this.root.querySelectorAll(".action-status")].map((e) => [e.id, e.textContent, e.className]);
    this.root.replaceChildren(
      this.parameters(params), this.features(view.features), this.materials(materials),
      this.bone(view), this.snapshots(), this.recording(view), this.exports());
    for (const d of this.root.querySelectorAll("details")) d.open = open.has(d.dataset.part);
    for (const [id, text, className] of statuses) {
      const e = document.getElementById(id);
      if (e) { e.textContent = text; e.className = className; }
    }
    this.fillLists();
  }

  section(part, title, ...body) {
    const details = el("details", { "data-part": part }, el("summary", {}, title), ...body,
      el("div", { id: `${part}-status`, class: "action-status" }));
    // Lists (snapshots, recordings, bones) are read again whenever a section is opened.
    details.addEventListener("toggle", () => { if (details.open) this.fillLists(); });
    return details;
  }

  parameters(p) {
    const form = el("form", { class: "grid", id: "parameters-form" });
    for (const [key, label] of NUMBER_FIELDS) {
      form.append(el("label", { for: `p-${key}` }, label),
        el("input", { id: `p-${key}`, name: key, type: "number", step: "any", value: p[key] ?? "" }));
    }
    const spin = el("select", { id: "p-spin", name: "spin" },
      ...["forward", "reverse"].map((s) => el("option", { value: s, selected: p.spin === s }, s)));
    form.append(el("label", { for: "p-spin" }, "spin"), spin);
    const burr = el("textarea", { id: "p-burr", name: "burr", rows: 3, spellcheck: "false" });
    burr.value = JSON.stringify(p.burr);
    form.append(el("label", { for: "p-burr" }, "burr (JSON)"), burr);
    form.append(el("span", {}, ""), el("button", { type: "submit" }, "Apply"));
    form.addEventListener("submit", (event) => {
      event.preventDefault();
      const patch = {};
      for (const [key] of NUMBER_FIELDS) {
        const text = form.elements[key].value.trim();
        if (text === "" || Number(text) === p[key]) continue;
        patch[key] = Number(text);
      }
      if (spin.value !== p.spin) patch.spin = spin.value;
      if (burr.value.trim() !== JSON.stringify(p.burr)) {
        try { patch.burr = JSON.parse(burr.value); } catch (e) {
          $("parameters-status").textContent = `burr is not JSON: ${e.message}`;
          $("parameters-status").className = "action-status bad";
          return;
        }
      }
      if (!Object.keys(patch).length) {
        $("parameters-status").textContent = "nothing changed";
        return;
      }
      this.act("parameters-status", `PATCH ${Object.keys(patch).join(", ")}`,
        () => call("PATCH", `/sessions/${this.id}/parameters`, patch));
    });
    const info = el("p", { class: "hint" }, `frame ${p.frame}, device ${p.device ?? "none"}, primary material ${p.primary_material_name ?? "—"}`);
    return this.section("parameters", "Parameters", info, form);
  }

  features(f) {
    const form = el("form", { class: "row" });
    for (const name of FEATURES) {
      form.append(el("label", {}, el("input", { type: "checkbox", name, checked: f[name] }), ` ${name}`));
    }
    const coupling = el("select", { name: "coupling", title: "the coupled output: auto follows the device" },
      ...[["auto", null], ["on", true], ["off", false]].map(([text, value]) => el("option", { value: text, selected: f.coupling === value }, `coupling ${text}`)));
    form.append(coupling, el("button", { type: "submit" }, "Apply"));
    form.addEventListener("submit", (event) => {
      event.preventDefault();
      const body = Object.fromEntries(FEATURES.map((n) => [n, form.elements[n].checked]));
      body.coupling = { auto: null, on: true, off: false }[coupling.value];
      this.act("features-status", "PUT features", () => call("PUT", `/sessions/${this.id}/features`, body));
    });
    return this.section("features", "Features", form);
  }

  materials(list) {
    const table = el("table", { class: "materials" },
      el("tr", {}, ...["label", "name", "Us N/mm²", "K", "forbidden", ""].map((h) => el("th", {}, h))));
    for (const m of list) {
      const name = el("input", { value: m.name, size: 10 });
      const us = el("input", { type: "number", step: "any", value: m.us_n_mm2, size: 6 });
      const k = el("input", { type: "number", step: "any", value: m.k, size: 4 });
      const forbidden = el("input", { type: "checkbox", checked: m.forbidden });
      const save = el("button", {
        type: "button",
        onclick: () => {
          const patch = {};
          if (name.value !== m.name) patch.name = name.value;
          if (Number(us.value) !== m.us_n_mm2) patch.us_n_mm2 = Number(us.value);
          if (Number(k.value) !== m.k) patch.k = Number(k.value);
          if (forbidden.checked !== m.forbidden) patch.forbidden = forbidden.checked;
          if (!Object.keys(patch).length) { $("materials-status").textContent = "nothing changed"; return; }
          this.act("materials-status", `PATCH material ${m.label}`, () => call("PATCH", `/sessions/${this.id}/materials/${m.label}`, patch));
        },
      }, "Save");
      table.append(el("tr", { "data-label": m.label }, el("td", {}, `${m.label}`), el("td", {}, name),
        el("td", {}, us), el("td", {}, k), el("td", {}, forbidden), el("td", {}, save)));
    }
    return this.section("materials", "Materials", table);
  }

  bone(view) {
    const source = el("input", { id: "bone-source", list: "bone-sources", value: view.source || "", size: 28 });
    const sources = el("datalist", { id: "bone-sources" });
    const load = el("button", {
      type: "button",
      onclick: () => this.act("bone-status", `load ${source.value}`, () => call("PUT", `/sessions/${this.id}/bone`, { source: source.value })),
    }, "Load");
    const reset = el("button", {
      type: "button",
      onclick: () => this.act("bone-status", "reset the bone", () => call("POST", `/sessions/${this.id}/reset`)),
    }, "Reset to uncut");
    const restart = el("button", {
      type: "button", title: "the engine's next POSE starts a new stream",
      onclick: () => this.act("bone-status", "restart the stream", () => call("POST", `/sessions/${this.id}/restart-stream`)),
    }, "Restart stream");
    const b = view.bone;
    const info = el("p", { class: "hint" }, b ? `${b.name}: ${b.shape.join(" × ")} voxels of ${b.voxel_mm} mm, generation ${b.generation}` : "no bone");
    return this.section("bone", "Bone", info, el("div", { class: "row" }, source, sources, load, reset, restart));
  }

  snapshots() {
    const name = el("input", { placeholder: "name (optional)", pattern: "[A-Za-z0-9][A-Za-z0-9_-]{0,70}", size: 14 });
    const take = el("button", {
      type: "button",
      onclick: () => this.act("snapshots-status", "snapshot", async () => {
        const r = await call("POST", `/sessions/${this.id}/snapshot`, name.value ? { name: name.value } : {});
        return r.name || r.snapshot || "";
      }),
    }, "Take snapshot");
    const list = el("select", { id: "snapshot-list" });
    const restore = el("button", {
      type: "button",
      onclick: () => {
        if (!list.value) return;
        this.act("snapshots-status", `restore ${list.value}`, () => call("POST", `/sessions/${this.id}/restore`, { snapshot: list.value }));
      },
    }, "Restore");
    return this.section("snapshots", "Snapshots", el("div", { class: "row" }, name, take), el("div", { class: "row" }, list, restore));
  }

  recording(view) {
    const active = view.recording;
    const name = el("input", { placeholder: "name (optional)", size: 14 });
    const startStop = active
      ? el("button", { type: "button", onclick: () => this.act("recording-status", "stop recording", () => call("DELETE", `/sessions/${this.id}/recording`)) }, "Stop recording")
      : el("button", { type: "button", onclick: () => this.act("recording-status", "start recording", () => call("POST", `/sessions/${this.id}/recording`, name.value ? { name: name.value } : {})) }, "Start recording");
    const list = el("select", { id: "recording-list" });
    const report = el("button", {
      type: "button",
      onclick: () => list.value && this.act("recording-status", `report of ${list.value}`,
        () => download(`/recordings/${encodeURIComponent(list.value)}/report?format=html`, `${list.value}-report.html`, { open: true }), { refresh: false }),
    }, "Report");
    const state = el("p", { class: "hint" }, active ? `recording: ${typeof active === "object" ? (active.name || JSON.stringify(active)) : active}` : "not recording");
    return this.section("recording", "Recording", state, el("div", { class: "row" }, ...(active ? [] : [name]), startStop),
      el("div", { class: "row" }, list, report));
  }

  exports() {
    const dl = (label, path, filename, open = false) => el("button", {
      type: "button",
      onclick: () => this.act("exports-status", label, async () => {
        const bytes = await download(`/sessions/${this.id}${path}`, filename, { open });
        return `${(bytes / 1024).toFixed(0)} kB`;
      }, { refresh: false }),
    }, label);
    return this.section("exports", "Exports and report",
      el("div", { class: "row" },
        dl("Surface STL", "/export/mesh?format=stl", `session-${this.id}.stl`),
        dl("Volume NRRD", "/export/volume?format=nrrd", `session-${this.id}.nrrd`),
        dl("Report (HTML)", "/report?format=html", `session-${this.id}-report.html`, true),
        dl("Report (JSON)", "/report?format=json", `session-${this.id}-report.json`)));
  }

  async fillLists() {
    const id = this.id;
    const [snaps, recs, phantoms, library] = await Promise.allSettled([
      call("GET", "/snapshots"), call("GET", "/recordings"), call("GET", "/phantoms"), call("GET", "/library")]);
    if (this.id !== id) return;
    const names = (r) => (r.status === "fulfilled" ? r.value : []).map((x) => (typeof x === "string" ? x : x.name ?? x.source));
    const fill = (select, items) => select && select.replaceChildren(...items.map((n) => el("option", { value: n }, n)));
    fill($("snapshot-list"), names(snaps));
    fill($("recording-list"), names(recs));
    const sources = [...names(phantoms), ...(library.status === "fulfilled" ? library.value : []).map((x) => x.source ?? x.name)];
    fill($("bone-sources"), sources.filter(Boolean));
  }
}
