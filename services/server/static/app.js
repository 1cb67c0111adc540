// neuvolex browser UI: plain JavaScript, no build step.
"use strict";
const $ = (id) => document.getElementById(id);
// Text from files and other users (volume and class names) goes into HTML escaped.
const esc = (t) => String(t).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));
const api = async (method, url, body) => {
  const r = await fetch(url, { method, headers: body ? { "Content-Type": "application/json" } : {}, body: body ? JSON.stringify(body) : undefined });
  if (!r.ok) { let m = r.statusText; try { m = (await r.json()).error; } catch (_) {} throw new Error(m); }
  return r.status === 204 ? null : r.json();
};
const S = { id: null, info: null, tf: null, strokes: [], redo: [], cls: 1, radius: 3, hover: "z", idx: { x: 0, y: 0, z: 0 }, events: null, renderPending: false, ovlPending: false };
// The page's own settings that the session keeps for a reload (slice positions, zoom and pan,
// window/level, overlay, brush, 3-D camera) live in S.ui; call uiChanged() after changing them
// (it saves them, debounced, with PUT /api/sessions/{id}/ui).
S.ui = {};
const AX = { z: { u: 0, v: 1, flip: false }, y: { u: 0, v: 2, flip: true }, x: { u: 1, v: 2, flip: true } };
const status = (t) => { $("status").textContent = t; };
const hex = (c) => "#" + c.map((v) => v.toString(16).padStart(2, "0")).join("");
const rgb = (h) => [1, 3, 5].map((i) => parseInt(h.slice(i, i + 2), 16));

async function loadVolumes() {
  const v = await api("GET", "/api/volumes");
  $("volume").innerHTML = v.map((p) => `<option>${esc(p)}</option>`).join("");
}

async function loadBackend() {
  try {
    const b = await api("GET", "/api/backend");
    const gpu = b.train === "gpu" || b.render === "gpu" || b.classify === "gpu";
    const e = $("engines");
    e.textContent = gpu ? `GPU${b.software ? " (software)" : ""}: ${b.adapter}` : "CPU";
    e.title = `INR training: ${b.train}, rendering: ${b.render}, classification: ${b.classify} (requested: ${b.requested}${b.gpu_build ? "" : "; this build has no GPU engines"})`;
    e.style.background = gpu ? "#1f4d2b" : "#333";
    e.style.color = gpu ? "#9e9" : "#aaa";
  } catch (_) { $("engines").textContent = "engines unknown"; }
}

// Sessions. The page's URL names its session (?session=ID): a reload, or the same URL in
// another tab, re-attaches to it (POST /api/sessions {"resume": ID} reopens it from its save file
// when the server has closed it), with its strokes, redo stack, classes, transfer function,
// features and the page's settings (S.ui). Only the Open button starts a new session.
async function open() {
  status("opening " + $("volume").value + " ...");
  let info;
  try { info = await api("POST", "/api/sessions", { volume: $("volume").value }); }
  catch (e) { status("error: " + e.message); return; }
  S.ui = {};
  await attach(info, true);
}
// Re-attaches to session `id`; false when the server does not know it.
async function resumeSession(id) {
  status("resuming session " + id + " ...");
  let info;
  try { info = await api("POST", "/api/sessions", { resume: id }); }
  catch (e) { status(`session ${id}: ${e.message}`); return false; }
  await attach(info, false);
  return true;
}
async function attach(info, fresh) {
  S.info = info; S.id = info.id; S.strokes = []; S.redo = []; progress(0, 1);
  // The readout of another session's volume no longer applies.
  if ($("readout")) { $("readout").textContent = ""; delete $("readout").dataset.voxel; }
  if ([...$("volume").options].some((o) => o.value === info.volume)) $("volume").value = info.volume;
  history.replaceState(null, "", `${location.pathname}?session=${encodeURIComponent(S.id)}`);
  // Strokes, redo stack and the page's settings from the session's state.
  let st = null;
  try { st = await api("GET", `/api/sessions/${S.id}/state`); } catch (_) {}
  if (st && Array.isArray(st.strokes)) S.strokes = st.strokes;
  else if (info.strokes > 0) { try { S.strokes = await api("GET", `/api/sessions/${S.id}/strokes`); } catch (_) {} }
  if (st && Array.isArray(st.redo)) S.redo = st.redo;
  S.ui = !fresh && st && st.ui && typeof st.ui === "object" && !Array.isArray(st.ui) ? st.ui : {};
  const d = S.info.dims;
  for (const a of ["x", "y", "z"]) {
    const n = d[{ x: 0, y: 1, z: 2 }[a]];
    $("i" + a).max = n - 1; $("i" + a).value = S.idx[a] = Math.floor(n / 2);
  }
  $("export").href = `/api/sessions/${S.id}/export/labels.nii.gz`;
  $("exports").href = `/api/sessions/${S.id}/export/scribbles.nii.gz`;
  $("thumbs").innerHTML = ""; S.views = []; $("vpinfo").textContent = "";
  applyMyUi();
  if (typeof applyUi === "function") applyUi();
  layoutViews(); renderClasses(); await loadTf(); refreshAll();
  $("trinfo").textContent = S.info.trained ? `INR trained (model ${S.info.model_version})` : "not trained"; $("preview").removeAttribute("src");
  await loadFeatures();
  $("prior").checked = !S.info.prior || S.info.prior.enabled; priorInfo(S.info.prior); $("suggestinfo").textContent = "";
  status(`${S.info.volume}: ${d.join(" x ")}${fresh ? "" : ` (session ${S.id}, ${S.strokes.length} strokes)`}`);
  if (fresh) { saveMyUi(); uiChanged(); }
}
// This part of the page's settings in S.ui: the 3-D camera and mode, orientation convention,
// selected class, overlay, brush, view recommendation and training budget.
const MY_UI = { az: "az", el: "el", zoom: "zoom", mode: "mode", ovl: "ovl", brush: "brush", vpcount: "vpcount", vpangle: "vpangle", epochs: "epochs" };
function saveMyUi() {
  for (const [k, id] of Object.entries(MY_UI)) S.ui[k] = $(id).type === "range" || $(id).type === "number" ? +$(id).value : $(id).value;
  S.ui.neuro = $("neuro").checked; S.ui.cls = S.cls; S.ui.tftarget = TF.target;
}
function applyMyUi() {
  const u = S.ui || {};
  for (const [k, id] of Object.entries(MY_UI)) {
    const el = $(id), v = u[k];
    if (v === undefined || v === null || (el.tagName === "SELECT" && ![...el.options].some((o) => o.value === String(v)))) continue;
    el.value = v;
  }
  S.radius = +$("brush").value; $("brushv").textContent = S.radius;
  if (typeof u.neuro === "boolean") $("neuro").checked = u.neuro;
  if (typeof u.cls === "number") S.cls = u.cls;
  if (typeof u.tftarget === "string") TF.target = u.tftarget;
  if (S.id) $("exportp").href = `/api/sessions/${S.id}/export/probability/${S.cls || 255}.nii.gz`;
}
// Saves S.ui with the session, 300 ms after the last change.
let uiTimer = null;
function uiChanged() {
  if (!S.id) return;
  saveMyUi();
  clearTimeout(uiTimer);
  const id = S.id;
  uiTimer = setTimeout(() => { uiTimer = null; if (id === S.id) api("PUT", `/api/sessions/${id}/ui`, S.ui).catch(() => {}); }, 300);
}
// The Sessions menu: every session the server keeps, newest first; a click goes back to one.
$("sessmenu").addEventListener("toggle", async (e) => {
  if (!e.target.open) return;
  const box = $("sesslist"); box.textContent = "loading ...";
  let r; try { r = await api("GET", "/api/sessions"); } catch (err) { box.textContent = "error: " + err.message; return; }
  const list = Array.isArray(r) ? r : r.sessions || [];
  box.innerHTML = "";
  if (!list.length) box.textContent = "no sessions";
  for (const s of list) {
    const b = document.createElement("button");
    const when = s.updated_ms ? new Date(s.updated_ms).toLocaleString() : "";
    b.style.textAlign = "left"; b.dataset.id = s.id;
    b.textContent = `${s.id === S.id ? "\u25b8 " : ""}${s.volume} \u2014 ${s.strokes ?? 0} strokes, ${s.open === false ? "saved" : "open"}${when ? ", " + when : ""}`;
    b.title = s.id;
    b.onclick = async () => { $("sessmenu").open = false; if (s.id !== S.id) { if (!(await resumeSession(s.id))) status(`could not resume ${s.id}`); } };
    box.appendChild(b);
  }
});
// Menus close after a choice and on a click elsewhere.
for (const m of document.querySelectorAll("details.menu")) {
  m.addEventListener("click", (e) => { if (e.target.closest("a, button")) setTimeout(() => { m.open = false; }, 0); });
}
document.addEventListener("click", (e) => { for (const m of document.querySelectorAll("details.menu[open]")) if (!m.contains(e.target)) m.open = false; });

function renderClasses() {
  const box = $("classes"); box.innerHTML = "";
  S.info.classes.forEach((c, i) => {
    const row = document.createElement("div");
    row.className = "cls" + (S.cls === c.id ? " sel" : ""); row.dataset.id = c.id;
    row.innerHTML = `<input type="color" value="${hex(c.color)}"> <input type="text" value="${esc(c.name)}"> <small>${i + 1}</small>`;
    row.onclick = (e) => { if (e.target.tagName !== "INPUT") pick(c.id); };
    row.querySelector("input[type=color]").onchange = (e) => { c.color = rgb(e.target.value); pushClasses(); };
    row.querySelector("input[type=text]").onchange = (e) => { c.name = e.target.value; pushClasses(); };
    box.appendChild(row);
  });
  for (const el of [$("bgcls"), $("erase")]) el.classList.toggle("sel", +el.dataset.id === S.cls);
}
async function pushClasses() {
  try { S.info = await api("PUT", `/api/sessions/${S.id}/classes`, S.info.classes); renderClasses(); fillTfTargets(); drawTf(); refreshAll(); refreshThumbs(); }
  catch (e) { status("error: " + e.message); }
}
function pick(id) {
  S.cls = id; renderClasses(); uiChanged();
  if (S.id) $("exportp").href = `/api/sessions/${S.id}/export/probability/${id || 255}.nii.gz`;
  if ($("ovl").value.startsWith("cls-")) for (const a of ["x", "y", "z"]) drawSlice(a);
}
$("addcls").onclick = () => {
  if (!S.info) return;
  const id = Math.max(0, ...S.info.classes.map((c) => c.id)) + 1;
  const hue = (id * 0.618) % 1, c = [0, 1, 2].map((k) => Math.round(127 + 120 * Math.cos(6.283 * (hue + k / 3))));
  S.info.classes.push({ id, name: "class " + id, color: c }); pushClasses().then(fillTfTargets); pick(id);
};
$("bgcls").onclick = () => pick(255);
$("erase").onclick = () => pick(0);
$("brush").oninput = (e) => { S.radius = +e.target.value; $("brushv").textContent = S.radius; uiChanged(); };

// Window and level in the source's units (S.ui.window, S.ui.level; HU for CT). The slice
// endpoint maps values through them. CT or not comes from the server (`info.unit`, decided from
// the data: values down to air, -500 HU and below, mean CT); CT gets the radiology presets,
// anything gets 1-99 % of the histogram (the default for non-CT) and the full range.
const sig = (v) => +(+v).toPrecision(4);
function histValue(q) {
  const h = S.info.histogram || [], [lo, hi] = S.info.range, tot = h.reduce((s, v) => s + v, 0);
  if (!tot || !(hi > lo)) return q < 0.5 ? lo : hi;
  let acc = 0; const bw = (hi - lo) / h.length;
  for (let i = 0; i < h.length; i++) { if (acc + h[i] >= q * tot) return lo + bw * (i + (q * tot - acc) / Math.max(1, h[i])); acc += h[i]; }
  return hi;
}
function wlPresets() {
  const p = [];
  if (S.info.unit === "HU") p.push(["CT soft tissue", 400, 40], ["CT lung", 1500, -600], ["CT bone", 1800, 400], ["CT brain", 80, 40]);
  const a = histValue(0.01), b = histValue(0.99), [lo, hi] = S.info.range;
  p.push(["1–99 %", Math.max(b - a, 1e-6), (a + b) / 2], ["full range", Math.max(hi - lo, 1e-6), (lo + hi) / 2]);
  return p.map(([n, w, l]) => [n, sig(w), sig(l)]);
}
function wl() { return `window=${S.ui.window}&level=${S.ui.level}`; }
function showWl() {
  $("win").value = sig(S.ui.window); $("lev").value = sig(S.ui.level);
  const u = S.info && S.info.unit ? " " + S.info.unit : "";
  $("wlunit").textContent = u;
  const k = wlPresets().findIndex(([, w, l]) => Math.abs(w - S.ui.window) < 1e-9 * Math.max(1, Math.abs(w)) + 1e-9 && Math.abs(l - S.ui.level) < 1e-9 * Math.max(1, Math.abs(l)) + 1e-9);
  $("wlpreset").value = k >= 0 ? String(k) : "";
}
let wlTimer = null;
function setWl(w, l, now) {
  if (!(w > 0) || !Number.isFinite(l)) return;
  S.ui.window = sig(w); S.ui.level = sig(l); showWl(); uiChanged();
  const go = () => { wlTimer = null; for (const a of ["x", "y", "z"]) drawSlice(a); };
  if (now) { clearTimeout(wlTimer); go(); } else if (!wlTimer) wlTimer = setTimeout(go, 60);
}
// A typed value applies on Enter or leaving the field; Enter hands the keys back to the views.
$("win").onchange = () => setWl(+$("win").value, S.ui.level, true);
$("lev").onchange = () => setWl(S.ui.window, +$("lev").value, true);
for (const id of ["win", "lev"]) $(id).addEventListener("keydown", (e) => { if (e.key === "Enter") e.target.blur(); });
$("wlpreset").onchange = (e) => { const p = wlPresets()[+e.target.value]; if (e.target.value !== "" && p) setWl(p[1], p[2], true); e.target.blur(); };
function loadImg(url) { return new Promise((res) => { const i = new Image(); i.onload = () => res(i); i.onerror = () => res(null); i.src = url; }); }

// Slice orientation. The server sends a slice with its first in-plane voxel axis across and
// the second down (flipped for y and x); the page lays it out in the radiological convention
// from the voxel axes' anatomical directions (`info.directions`, from the affine): axial with
// anterior up and the patient's right on the screen's left, coronal and sagittal with superior
// up (sagittal: anterior on the left). Neurological puts the patient's left on the left.
// Pixels are scaled by voxel spacing.
const OPP = { R: "L", L: "R", A: "P", P: "A", S: "I", I: "S" };
const AXK = { x: 0, y: 1, z: 2 };
function viewOf(a) {
  const f = S.info.directions[AXK[a]];
  return "SI".includes(f) ? "axial" : "AP".includes(f) ? "coronal" : "sagittal";
}
function frame(a) {
  const d = S.info.dims, sp = S.info.spacing, dir = S.info.directions, ax = AX[a], view = viewOf(a);
  const right = view === "sagittal" ? "P" : $("neuro").checked ? "R" : "L", up = view === "axial" ? "A" : "S";
  const pairs = (k, c) => dir[k] === c || dir[k] === OPP[c];
  const h = pairs(ax.u, right) ? ax.u : ax.v, w = h === ax.u ? ax.v : ax.u;
  const min = Math.min(...sp), kh = sp[h] / min, kw = sp[w] / min;
  const sx = dir[h] === right ? 1 : -1, sy = dir[w] === up ? -1 : 1;
  // Continuous voxel coordinates (along u, along v) → frame pixels, and back.
  const toScreen = (U, V) => { const vh = h === ax.u ? U : V, vw = h === ax.u ? V : U;
    return [sx > 0 ? vh * kh : (d[h] - vh) * kh, sy > 0 ? vw * kw : (d[w] - vw) * kw]; };
  const toVoxel = (X, Y) => { const vh = sx > 0 ? X / kh : d[h] - X / kh, vw = sy > 0 ? Y / kw : d[w] - Y / kw;
    return h === ax.u ? [vh, vw] : [vw, vh]; };
  const affine = (f) => { const o = f(0, 0), x = f(1, 0), y = f(0, 1); return [x[0] - o[0], x[1] - o[1], y[0] - o[0], y[1] - o[1], o[0], o[1]]; };
  return {
    view, W: Math.max(1, d[h] * kh), H: Math.max(1, d[w] * kw),
    letters: { left: OPP[right], right, top: up, bottom: OPP[up] },
    voxel: affine(toScreen), // voxel (u, v) → frame
    image: affine((i, j) => toScreen(i, ax.flip ? d[ax.v] - j : j)), // server image → frame
    toVoxel,
  };
}
// Names, order and edge letters of the three views.
function layoutViews() {
  const order = { axial: 0, coronal: 1, sagittal: 2 };
  for (const a of ["x", "y", "z"]) {
    const f = frame(a), v = $("c" + a).closest(".view");
    v.style.order = order[f.view]; $("n" + a).textContent = `${f.view} (${a})`;
    for (const [k, t] of Object.entries(f.letters)) v.querySelector(".m" + k[0]).textContent = t;
    sliceLabel(a);
  }
}

// Each slice view is a frame (the slice in spacing-scaled pixels, `frame`) fitted into its
// pane, then zoomed about and panned by the view's own state (S.ui.views[a]: zoom, and the
// frame point at the pane's centre as fractions of the frame). The slice images are streamed
// from the server and kept per view, so zoom, pan, resizing and the crosshair repaint without
// fetching. Canvases are sized in device pixels.
const VIEW_BG = "rgb(24,27,34)"; // the pane outside the slice (not grey, so tests can find the slice)
function vstate(a) {
  S.ui.views = S.ui.views && typeof S.ui.views === "object" ? S.ui.views : {};
  const v = S.ui.views[a] && typeof S.ui.views[a] === "object" ? S.ui.views[a] : (S.ui.views[a] = {});
  if (!(v.zoom >= 0.5 && v.zoom <= 40)) v.zoom = 1;
  if (!Number.isFinite(v.cx)) v.cx = 0.5;
  if (!Number.isFinite(v.cy)) v.cy = 0.5;
  return v;
}
// The 2-D affine (canvas order a b c d e f) of `n` followed by `m`.
const mul = (m, n) => [m[0] * n[0] + m[2] * n[1], m[1] * n[0] + m[3] * n[1], m[0] * n[2] + m[2] * n[3], m[1] * n[2] + m[3] * n[3], m[0] * n[4] + m[2] * n[5] + m[4], m[1] * n[4] + m[3] * n[5] + m[5]];
function fitCanvas(a) {
  const c = $("c" + a), t = $("t" + a), p = c.parentElement, dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(p.clientWidth * dpr)), h = Math.max(1, Math.round(p.clientHeight * dpr));
  if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
  if (t.width !== w || t.height !== h) { t.width = w; t.height = h; }
}
// Frame → canvas: scale k (canvas pixels per frame pixel) and offset (e, g).
function viewXf(a) {
  const c = $("c" + a), f = frame(a), v = vstate(a);
  const k = Math.min(c.width / f.W, c.height / f.H) * v.zoom;
  const m = [k, 0, 0, k, c.width / 2 - v.cx * f.W * k, c.height / 2 - v.cy * f.H * k];
  return { f, k, m, voxel: mul(m, f.voxel), image: mul(m, f.image) };
}
// The slice's rectangle in CSS pixels relative to its canvas (for tests and tools).
function viewRect(a) {
  const c = $("c" + a), t = viewXf(a), s = c.clientWidth / c.width;
  return { x: t.m[4] * s, y: t.m[5] * s, w: t.f.W * t.k * s, h: t.f.H * t.k * s };
}
// Continuous voxel coordinates (u, v) in view `a` under a mouse event.
function eventVoxel(a, e) {
  const c = $("c" + a), r = c.getBoundingClientRect(), t = viewXf(a);
  const X = (e.clientX - r.left) * c.width / r.width, Y = (e.clientY - r.top) * c.height / r.height;
  return t.f.toVoxel((X - t.m[4]) / t.k, (Y - t.m[5]) / t.k);
}
// One paint per update: both images are fetched, then base, overlay and strokes are drawn at
// once, and only by the latest request for that view.
const paintSeq = { x: 0, y: 0, z: 0 }, PIX = {};
async function drawSlice(a) {
  if (!S.id) return;
  sliceLabel(a);
  const seq = ++paintSeq[a], idx = S.idx[a], id = S.id;
  let kind = $("ovl").value, cls = "";
  if (kind.startsWith("cls-")) { kind = kind.slice(4); cls = `&class=${S.cls || 255}`; }
  const [base, o] = await Promise.all([
    loadImg(`/api/sessions/${id}/slice/${a}/${idx}?${wl()}`),
    kind ? loadImg(`/api/sessions/${id}/overlay/${a}/${idx}?kind=${kind}${cls}&t=${Date.now()}`) : null,
  ]);
  if (!base || seq !== paintSeq[a] || id !== S.id) return;
  PIX[a] = { base, o, id };
  paint(a);
}
// Draws view `a` from its last images (no fetch).
function paint(a) {
  const p = PIX[a], c = $("c" + a);
  if (!p || !S.info || p.id !== S.id) return;
  fitCanvas(a);
  const t = viewXf(a), g = c.getContext("2d");
  g.setTransform(1, 0, 0, 1, 0, 0); g.clearRect(0, 0, c.width, c.height);
  g.fillStyle = VIEW_BG; g.fillRect(0, 0, c.width, c.height);
  g.imageSmoothingEnabled = false;
  g.setTransform(...t.image); g.drawImage(p.base, 0, 0);
  if (p.o) g.drawImage(p.o, 0, 0);
  drawStrokes(a, g);
  drawTop(a);
}
function drawStrokes(a, g, extra) {
  const d = S.info.dims, ax = AX[a];
  g.save(); g.setTransform(...viewXf(a).voxel);
  g.beginPath(); g.rect(0, 0, d[ax.u], d[ax.v]); g.clip(); // strokes stay on the slice
  for (const s of extra ? [...S.strokes, extra] : S.strokes) {
    if (s.axis !== a || s.slice !== S.idx[a]) continue;
    const c = s.class === 255 ? [120, 120, 120] : s.class === 0 ? [0, 0, 0] : (S.info.classes.find((k) => k.id === s.class) || { color: [255, 255, 255] }).color;
    g.lineCap = g.lineJoin = "round";
    g.beginPath();
    s.points.forEach((p, i) => { const x = p[0] + 0.5, y = p[1] + 0.5; i ? g.lineTo(x, y) : g.moveTo(x, y); });
    // A light rim first, so a stroke stays visible over an overlay of its own class's colour.
    const w = Math.max(1, s.radius * 2);
    g.strokeStyle = "rgba(255,255,255,0.85)"; g.lineWidth = w + 1.2; g.stroke();
    g.strokeStyle = s.class === 0 ? "#000" : hex(c); g.lineWidth = w; g.stroke();
  }
  g.restore();
}
// The layer over each slice: the crosshair through S.idx (the 3-D point all views share) and
// the brush outline at its true radius (voxels, so an ellipse where the voxels are not square).
const HOV = { a: null, uv: null, e: null };
function drawTop(a) {
  const c = $("t" + a);
  if (!S.info) return;
  const g = c.getContext("2d"), dpr = window.devicePixelRatio || 1;
  g.setTransform(1, 0, 0, 1, 0, 0); g.clearRect(0, 0, c.width, c.height);
  const t = viewXf(a), M = t.voxel, ax = AX[a], d = S.info.dims;
  const P = (U, V) => [M[0] * U + M[2] * V + M[4], M[1] * U + M[3] * V + M[5]];
  if (S.ui.crosshair !== false) {
    const U = S.idx["xyz"[ax.u]] + 0.5, V = S.idx["xyz"[ax.v]] + 0.5;
    g.strokeStyle = "rgba(90,220,255,0.75)"; g.lineWidth = dpr; g.beginPath();
    for (const [p, q] of [[P(U, 0), P(U, d[ax.v])], [P(0, V), P(d[ax.u], V)]]) { g.moveTo(p[0], p[1]); g.lineTo(q[0], q[1]); }
    g.stroke();
  }
  if (HOV.a === a && HOV.uv && !DRAG) {
    g.save(); g.setTransform(...M); g.beginPath();
    g.ellipse(HOV.uv[0] + 0.5, HOV.uv[1] + 0.5, Math.max(0.5, S.radius), Math.max(0.5, S.radius), 0, 0, 2 * Math.PI);
    g.restore(); g.strokeStyle = "rgba(255,255,255,0.9)"; g.lineWidth = dpr; g.stroke();
  }
}
// "i / n" and the slice's world position (mm, along the world axis the voxel axis follows most,
// at the crosshair point: Slicer's "S 12.5 mm").
const mm = (v) => (Math.abs(v) < 0.05 ? 0 : v).toFixed(1);
function worldOf(p) { const A = S.info.affine; return A ? [0, 1, 2].map((r) => A[r][0] * p[0] + A[r][1] * p[1] + A[r][2] * p[2] + A[r][3]) : p.map((v, k) => v * S.info.spacing[k]); }
function sliceLabel(a) {
  if (!S.info) return;
  const k = AXK[a], n = S.info.dims[k], A = S.info.affine || [[1, 0, 0], [0, 1, 0], [0, 0, 1]];
  let r = 0; for (let i = 1; i < 3; i++) if (Math.abs(A[i][k]) > Math.abs(A[r][k])) r = i;
  const w = worldOf([S.idx.x, S.idx.y, S.idx.z])[r];
  $("s" + a).textContent = `${S.idx[a]} / ${n} · ${"RAS"[r]} ${mm(w)} mm`;
  $("i" + a).max = n - 1; $("i" + a).value = S.idx[a];
}
function refreshAll() { for (const a of ["x", "y", "z"]) drawSlice(a); render(); fractions(); }
// The 3-D view. One render at a time, always current: a request while one is in flight
// marks it stale, and exactly one more render follows with the latest state (labels, prior,
// transfer function, colours, camera, mode).
function camera() { return { az: +$("az").value, el: +$("el").value, zoom: +$("zoom").value, mode: $("mode").value }; }
function renderQuery(cam, size) {
  const q = new URLSearchParams({ az: cam.az, el: cam.el, size, zoom: cam.zoom });
  if (cam.mode) q.set("mode", cam.mode);
  return q;
}
async function render() {
  if (!S.id) return;
  if (S.renderPending) { S.renderAgain = true; return; }
  S.renderPending = true;
  try {
    do {
      S.renderAgain = false;
      const id = S.id, cam = camera();
      const i = await loadImg(`/api/sessions/${id}/render?${renderQuery(cam, 400)}&t=${Date.now()}`);
      if (i && id === S.id) {
        const r = $("render"); r.src = i.src; await r.decode().catch(() => {});
        S.shownCam = cam; drawOrientation($("orient"), cam.az, cam.el);
      }
    } while (S.renderAgain && S.id);
  } finally { S.renderPending = false; }
  S.renders = (S.renders || 0) + 1;
}
// Orientation marker: the voxel axes as the server's camera sees them (services/render
// camera.rs: world = voxel index x spacing; the eye at (sin az cos el, -cos az cos el, sin el),
// up +z), each end labelled with its anatomical direction from `info.directions`.
function cameraBasis(az, el) {
  const a = az * Math.PI / 180, e = el * Math.PI / 180;
  const d = [Math.sin(a) * Math.cos(e), -Math.cos(a) * Math.cos(e), Math.sin(e)], f = d.map((v) => -v);
  const wu = Math.abs(f[2]) > 0.999 ? [0, 1, 0] : [0, 0, 1];
  const cross = (p, q) => [p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0]];
  const r0 = cross(f, wu), n = Math.hypot(...r0), right = r0.map((v) => v / n);
  return { forward: f, right, up: cross(right, f) };
}
// Screen direction (x right, y down) and depth (towards the viewer > 0) of each anatomical
// direction letter for the camera at az, el.
function orientationAxes(az, el) {
  const b = cameraBasis(az, el), dir = (S.info && S.info.directions) || ["R", "A", "S"], out = {};
  for (let k = 0; k < 3; k++) {
    for (const sgn of [1, -1]) {
      const v = [0, 0, 0]; v[k] = sgn;
      const letter = sgn > 0 ? dir[k] : OPP[dir[k]];
      out[letter] = { x: v[0] * b.right[0] + v[1] * b.right[1] + v[2] * b.right[2], y: -(v[0] * b.up[0] + v[1] * b.up[1] + v[2] * b.up[2]), depth: -(v[0] * b.forward[0] + v[1] * b.forward[1] + v[2] * b.forward[2]) };
    }
  }
  return out;
}
const AXCOL = { R: "#f66", L: "#f66", A: "#6d6", P: "#6d6", S: "#69f", I: "#69f" };
function drawOrientation(c, az, el) {
  if (!c || !S.info) return;
  const g = c.getContext("2d"), W = c.width, r = W * 0.3, cx = W / 2, cy = W / 2;
  g.clearRect(0, 0, W, W);
  const ax = Object.entries(orientationAxes(az, el)).sort((p, q) => p[1].depth - q[1].depth);
  g.font = `bold ${Math.round(W * 0.15)}px sans-serif`; g.textAlign = "center"; g.textBaseline = "middle";
  const drawn = [];
  for (const [t, v] of ax) {
    const x = cx + v.x * r, y = cy + v.y * r, front = v.depth >= 0;
    // An axis seen nearly end-on: only its near end's letter (the far one would sit under it).
    if (!front && Math.hypot(v.x, v.y) < 0.35) continue;
    drawn.push(t);
    g.globalAlpha = front ? 1 : 0.45;
    g.strokeStyle = AXCOL[t]; g.lineWidth = Math.max(1.5, W / 40);
    g.beginPath(); g.moveTo(cx, cy); g.lineTo(x, y); g.stroke();
    const lx = cx + v.x * r * 1.38, ly = cy + v.y * r * 1.38;
    g.lineWidth = 3; g.strokeStyle = "#000"; g.strokeText(t, lx, ly);
    g.fillStyle = AXCOL[t]; g.fillText(t, lx, ly);
  }
  g.globalAlpha = 1;
  c.dataset.letters = drawn.join("");
}
// Drag rotates the 3-D view (the sliders follow), the wheel zooms.
{
  const box = $("render3d");
  let drag = null;
  box.addEventListener("mousedown", (e) => { if (e.button !== 0) return; e.preventDefault(); drag = { x: e.clientX, y: e.clientY, az: +$("az").value, el: +$("el").value }; box.style.cursor = "grabbing"; });
  window.addEventListener("mousemove", (e) => {
    if (!drag) return;
    let az = drag.az - (e.clientX - drag.x) * 0.5;
    az = ((az + 180) % 360 + 360) % 360 - 180;
    const el = Math.max(-89, Math.min(89, drag.el + (e.clientY - drag.y) * 0.5));
    if (Math.round(az) !== +$("az").value || Math.round(el) !== +$("el").value) { $("az").value = Math.round(az); $("el").value = Math.round(el); render(); }
  });
  window.addEventListener("mouseup", () => { if (drag) { drag = null; box.style.cursor = "grab"; uiChanged(); } });
  box.addEventListener("wheel", (e) => {
    e.preventDefault();
    const z = $("zoom"), v = Math.max(+z.min, Math.min(+z.max, +z.value * Math.exp(-e.deltaY * 0.0015)));
    if (v.toFixed(1) !== (+z.value).toFixed(1)) { z.value = v.toFixed(1); render(); refreshThumbs(); uiChanged(); }
  }, { passive: false });
}
async function fractions() {
  if (!S.id) return;
  let f; try { f = await api("GET", `/api/sessions/${S.id}/fractions`); } catch (e) { status("fractions: " + e.message); return; }
  $("fractions").innerHTML = f.classes.map((c) => {
    const k = S.info.classes.find((x) => x.id === c.id); const name = c.id === 255 ? "background" : c.id === 0 ? "unlabelled" : k ? k.name : c.id;
    return `<tr><td>${name}</td><td>${(100 * c.fraction).toFixed(2)}%</td></tr>`;
  }).join("");
}
// Transfer-function editor: opacity control points of the intensity map or of one class's
// maps (over its probability, or over intensity for the probability-intensity mode), drawn over
// the volume's histogram. Every edit goes to the session and re-renders the 3-D view.
const TF = { target: "intensity", drag: null };
async function loadTf() { S.tf = await api("GET", `/api/sessions/${S.id}/tf`); fillTfTargets(); drawTf(); }
// The editor offers only the maps the current 3-D mode draws with: intensity, the intensity
// map; class probabilities, each class's opacity over its probability; probability-intensity,
// each class's opacity over intensity (the intensity map for classes without one); labels,
// each class's opacity inside its label over intensity, and the intensity map as the faint
// context around them.
function fillTfTargets() {
  const mode = $("mode").value, opts = [];
  if (mode !== "prob") opts.push(["intensity", mode === "labels" ? "intensity (the faint context)" : mode === "prob-intensity" ? "intensity (classes without their own)" : "intensity"]);
  for (const c of S.info.classes) {
    if (mode === "prob") opts.push([`p:${c.id}`, `${c.name}: opacity over probability`]);
    else if (mode === "labels") opts.push([`i:${c.id}`, `${c.name}: opacity in its label, over intensity`]);
    else if (mode === "prob-intensity") opts.push([`i:${c.id}`, `${c.name}: opacity over intensity`]);
  }
  $("tftarget").innerHTML = opts.map(([v, t]) => `<option value="${v}">${t}</option>`).join("");
  if (!opts.some((o) => o[0] === TF.target)) {
    // The same class's map in this mode, else the first offered.
    const same = opts.find((o) => o[0].slice(2) === TF.target.slice(2) && o[0].length > 2 && TF.target.length > 2);
    TF.target = (same || opts[0] || ["intensity"])[0];
  }
  $("tftarget").value = TF.target;
}
// Intensity axis: the histogram spans the raw [min, max]; maps are in raw or normalised units.
const ispace = () => S.tf.space === "normalised";
const rawToMap = (v) => { const [lo, hi] = S.info.percentiles; return ispace() ? (v - lo) / Math.max(1e-12, hi - lo) : v; };
const mapToRaw = (x) => { const [lo, hi] = S.info.percentiles; return ispace() ? lo + x * (hi - lo) : x; };
// The edited map: { pts (opacity points), prob (x is a probability), color }; `create` adds
// a class entry with the renderer's defaults when the TF has none yet.
function tfMap(create) {
  const t = TF.target, [lo, hi] = S.info.range;
  // A class without its own intensity map: solid (0.6, the server's LABEL_OPACITY) in the
  // label view, the intensity map's opacity elsewhere.
  const defInt = () => ({ opacity: $("mode").value === "labels" ? [[rawToMap(lo), 0.6], [rawToMap(hi), 0.6]] : S.tf.intensity ? JSON.parse(JSON.stringify(S.tf.intensity.opacity)) : [[rawToMap(lo), 0.35]] });
  if (t === "intensity") {
    if (!S.tf.intensity && create) S.tf.intensity = { opacity: [[rawToMap(lo), 0], [rawToMap(hi), 0.5]] };
    const m = S.tf.intensity || { opacity: [[rawToMap(lo), 0], [rawToMap(hi), 0.5]] };
    return { pts: m.opacity, prob: false, color: "#ddd" };
  }
  const id = +t.slice(2), prob = t[0] === "p", key = prob ? "probability" : "intensity";
  const k = S.info.classes.find((c) => c.id === id), color = k ? hex(k.color) : "#fff";
  let c = (S.tf.classes || []).find((e) => e.id === id);
  if (!c && create) { S.tf.classes = S.tf.classes || []; c = { id }; S.tf.classes.push(c); }
  if (c && !c[key] && create) c[key] = prob ? { opacity: [[0, 0], [0.2, 0], [1, 0.6]] } : defInt();
  const m = c && c[key] ? c[key] : prob ? { opacity: [[0, 0], [0.2, 0], [1, 0.6]] } : defInt();
  return { pts: m.opacity, prob, color };
}
const TW = 512, TH = 200, PAD = 8;
function tfX(x, prob) { const [lo, hi] = S.info.range; const u = prob ? x : (mapToRaw(x) - lo) / Math.max(1e-12, hi - lo); return PAD + u * (TW - 2 * PAD); }
function tfFromX(px, prob) { const [lo, hi] = S.info.range; const u = Math.max(0, Math.min(1, (px - PAD) / (TW - 2 * PAD))); return prob ? u : rawToMap(lo + u * (hi - lo)); }
const tfY = (a) => TH - PAD - a * (TH - 2 * PAD), tfFromY = (py) => Math.max(0, Math.min(1, (TH - PAD - py) / (TH - 2 * PAD)));
function drawTf() {
  if (!S.tf) return;
  const c = $("tfc"), g = c.getContext("2d"), m = tfMap(false);
  g.fillStyle = "#000"; g.fillRect(0, 0, TW, TH);
  if (!m.prob) {
    const h = S.info.histogram || [], mx = Math.max(1, ...h.map((v) => Math.log(1 + v)));
    g.fillStyle = "#345"; h.forEach((v, i) => { const y = (TH - 2 * PAD) * Math.log(1 + v) / mx; g.fillRect(PAD + i * (TW - 2 * PAD) / h.length, TH - PAD - y, Math.max(1, (TW - 2 * PAD) / h.length), y); });
    if (S.tf.intensity && S.tf.intensity.color && TF.target === "intensity") {
      for (let px = PAD; px < TW - PAD; px++) { const x = tfFromX(px, false), cs = S.tf.intensity.color; let k = cs.findIndex((p) => p[0] >= x); if (k < 0) k = cs.length - 1; const p = cs[Math.max(0, k)]; g.fillStyle = `rgb(${p[1] * 255},${p[2] * 255},${p[3] * 255})`; g.fillRect(px, TH - PAD + 2, 1, PAD - 2); }
    }
  } else { g.fillStyle = "#888"; g.font = "11px sans-serif"; g.fillText("probability 0", PAD, TH - 2); g.fillText("1", TW - PAD - 6, TH - 2); }
  g.strokeStyle = m.color; g.lineWidth = 2; g.beginPath();
  m.pts.forEach((p, i) => { const x = tfX(p[0], m.prob), y = tfY(p[1]); i ? g.lineTo(x, y) : g.moveTo(x, y); });
  g.stroke();
  g.fillStyle = m.color; for (const p of m.pts) { g.beginPath(); g.arc(tfX(p[0], m.prob), tfY(p[1]), 5, 0, 7); g.fill(); }
}
async function pushTf() {
  try { S.info = await api("PUT", `/api/sessions/${S.id}/tf`, S.tf); render(); refreshThumbs(); }
  catch (e) { status("error: " + e.message); await loadTf(); }
}
{
  const c = $("tfc");
  const pos = (e) => { const r = c.getBoundingClientRect(); return [(e.clientX - r.left) * TW / r.width, (e.clientY - r.top) * TH / r.height]; };
  const near = (m, px, py) => m.pts.findIndex((p) => Math.hypot(tfX(p[0], m.prob) - px, tfY(p[1]) - py) < 8);
  c.oncontextmenu = (e) => e.preventDefault();
  c.onmousedown = (e) => {
    if (!S.tf) return;
    const [px, py] = pos(e), m = tfMap(true); let k = near(m, px, py);
    if (e.button === 2) { if (k >= 0 && m.pts.length > 1) { m.pts.splice(k, 1); drawTf(); pushTf(); } return; }
    if (k < 0) { const p = [+tfFromX(px, m.prob).toPrecision(6), +tfFromY(py).toFixed(3)]; m.pts.push(p); m.pts.sort((a, b) => a[0] - b[0]); k = m.pts.indexOf(p); }
    TF.drag = { m, k }; drawTf();
  };
  c.onmousemove = (e) => {
    if (!TF.drag) return;
    const [px, py] = pos(e), { m, k } = TF.drag, pts = m.pts;
    let x = +tfFromX(px, m.prob).toPrecision(6);
    if (k > 0) x = Math.max(x, pts[k - 1][0]); if (k < pts.length - 1) x = Math.min(x, pts[k + 1][0]);
    pts[k] = [x, +tfFromY(py).toFixed(3)]; drawTf();
  };
  c.onmouseup = c.onmouseleave = () => { if (TF.drag) { TF.drag = null; pushTf(); } };
}
$("tftarget").onchange = (e) => { TF.target = e.target.value; drawTf(); uiChanged(); };
$("tf").onchange = async (e) => {
  if (!e.target.value || !S.id) return;
  S.tf = await api("GET", `/api/presets/${e.target.value}`); e.target.value = ""; drawTf(); pushTf();
};
$("tfreset").onclick = async () => { if (!S.id) return; S.info = await api("PUT", `/api/sessions/${S.id}/tf`, null); await loadTf(); render(); refreshThumbs(); };

// Slice-view mouse: left draws (Shift+left sets the crosshair point, Space+left pans), the
// middle button pans, the right button sets window (across) and level (down), the wheel steps
// the slice and Ctrl+wheel (a pinch) zooms about the cursor.
let drawing = null, DRAG = null, SPACE = false;
// The voxel a point lands on, clamped into the slice, in the view's (u, v).
function clampUv(a, uv) { const d = S.info.dims, ax = AX[a]; return [Math.max(0, Math.min(d[ax.u] - 1, Math.floor(uv[0]))), Math.max(0, Math.min(d[ax.v] - 1, Math.floor(uv[1])))]; }
function point3(a, uv) { const p = [0, 0, 0], ax = AX[a]; p[AXK[a]] = S.idx[a]; p[ax.u] = uv[0]; p[ax.v] = uv[1]; return p; }
function setSlice(a, i) {
  if (!S.info) return;
  i = Math.max(0, Math.min(S.info.dims[AXK[a]] - 1, Math.round(i)));
  if (i === S.idx[a]) return;
  S.idx[a] = i; drawSlice(a);
  for (const b of ["x", "y", "z"]) { sliceLabel(b); if (b !== a) drawTop(b); }
  if (HOV.a === a && HOV.e) hover(a, HOV.e);
  uiChanged();
}
// The crosshair point: the other two views go to its slices.
function setCross(a, uv) {
  const ax = AX[a], [u, v] = clampUv(a, uv), ku = "xyz"[ax.u], kv = "xyz"[ax.v];
  const moved = [ku, kv].filter((k, i) => S.idx[k] !== [u, v][i]);
  S.idx[ku] = u; S.idx[kv] = v;
  for (const b of moved) drawSlice(b);
  for (const b of ["x", "y", "z"]) { sliceLabel(b); drawTop(b); }
  if (moved.length) uiChanged();
}
function resetView(a) { S.ui.views = S.ui.views || {}; S.ui.views[a] = { zoom: 1, cx: 0.5, cy: 0.5 }; paint(a); uiChanged(); }
function hover(a, e) {
  HOV.a = a; HOV.e = e;
  const uv = eventVoxel(a, e), d = S.info.dims, ax = AX[a];
  const inside = uv[0] >= 0 && uv[1] >= 0 && uv[0] < d[ax.u] && uv[1] < d[ax.v];
  HOV.uv = inside ? clampUv(a, uv) : null;
  drawTop(a); brushInfo(a);
  if (inside) readout(point3(a, HOV.uv)); else $("readout").textContent = "outside the volume";
}
function brushInfo(a) {
  if (!S.info) return;
  const sp = S.info.spacing, ax = AX[a || S.hover], mu = S.radius * sp[ax.u], mv = S.radius * sp[ax.v];
  $("brushmm").textContent = `vox = ${Math.abs(mu - mv) < 1e-6 ? mu.toFixed(1) : mu.toFixed(1) + " × " + mv.toFixed(1)} mm`;
}
for (const a of ["x", "y", "z"]) {
  const c = $("c" + a);
  const pos = (e) => clampUv(a, eventVoxel(a, e));
  c.onmouseenter = () => { S.hover = a; };
  c.oncontextmenu = (e) => e.preventDefault();
  c.onmousedown = (e) => {
    if (!S.id) return;
    S.hover = a;
    // The keys go to the views after a click on one (not to the control last used).
    if (document.activeElement && document.activeElement !== document.body) document.activeElement.blur();
    const v = vstate(a);
    if (e.button === 1 || (e.button === 0 && SPACE)) { e.preventDefault(); DRAG = { mode: "pan", a, x: e.clientX, y: e.clientY, cx: v.cx, cy: v.cy }; drawTop(a); return; }
    if (e.button === 2) { e.preventDefault(); DRAG = { mode: "wl", a, x: e.clientX, y: e.clientY, w: S.ui.window, l: S.ui.level }; drawTop(a); return; }
    if (e.button !== 0) return;
    if (e.shiftKey) { DRAG = { mode: "cross", a }; setCross(a, eventVoxel(a, e)); return; }
    drawing = { class: S.cls, axis: a, slice: S.idx[a], points: [pos(e)], radius: S.radius };
  };
  c.onmousemove = (e) => {
    if (!S.info) return;
    if (!DRAG) hover(a, e);
    if (!drawing || drawing.axis !== a) return;
    const p = pos(e), q = drawing.points[drawing.points.length - 1];
    if (p[0] !== q[0] || p[1] !== q[1]) drawing.points.push(p);
    drawStrokes(a, c.getContext("2d"), drawing);
  };
  c.onmouseup = (e) => { if (!drawing || drawing.axis !== a || e.button !== 0) return; S.strokes.push(drawing); S.redo = []; drawing = null; sendStrokes(); };
  c.onmouseleave = () => {
    HOV.a = null; drawTop(a);
    if (!drawing || drawing.axis !== a) return; S.strokes.push(drawing); S.redo = []; drawing = null; sendStrokes();
  };
  c.addEventListener("wheel", (e) => {
    if (!S.info) return;
    e.preventDefault();
    if (e.ctrlKey || e.metaKey) {
      // Zoom about the cursor: the frame point under it stays put.
      const v = vstate(a), t = viewXf(a), r = c.getBoundingClientRect();
      const X = (e.clientX - r.left) * c.width / r.width, Y = (e.clientY - r.top) * c.height / r.height;
      const fx = (X - t.m[4]) / t.k, fy = (Y - t.m[5]) / t.k;
      const z = Math.max(0.5, Math.min(40, v.zoom * Math.max(0.5, Math.min(2, Math.exp(-e.deltaY * 0.0025)))));
      const k = t.k * z / v.zoom;
      v.zoom = z; v.cx = (c.width / 2 - X + fx * k) / (t.f.W * k); v.cy = (c.height / 2 - Y + fy * k) / (t.f.H * k);
      paint(a); hover(a, e); uiChanged();
      return;
    }
    // One slice per wheel notch (a trackpad's small steps add up); up is the next slice.
    S.wheel = (S.wheel || 0) + e.deltaY;
    if (Math.abs(e.deltaY) >= 40 || Math.abs(S.wheel) >= 40) { const s = S.wheel < 0 ? 1 : -1; S.wheel = 0; setSlice(a, S.idx[a] + s); }
  }, { passive: false });
  $("i" + a).oninput = (e) => setSlice(a, +e.target.value);
  new ResizeObserver(() => { if (S.info) paint(a); }).observe(c.parentElement);
}
window.addEventListener("mousemove", (e) => {
  if (!DRAG || !S.info) return;
  const { a } = DRAG, c = $("c" + a);
  if (DRAG.mode === "pan") {
    const t = viewXf(a), s = c.width / c.clientWidth, v = vstate(a);
    v.cx = DRAG.cx - (e.clientX - DRAG.x) * s / (t.k * t.f.W); v.cy = DRAG.cy - (e.clientY - DRAG.y) * s / (t.k * t.f.H);
    paint(a);
  } else if (DRAG.mode === "wl") {
    setWl(DRAG.w * Math.exp((e.clientX - DRAG.x) / 150), DRAG.l + (e.clientY - DRAG.y) * DRAG.w / 300, false);
  } else if (DRAG.mode === "cross") setCross(a, eventVoxel(a, e));
});
window.addEventListener("mouseup", () => { if (!DRAG) return; const a = DRAG.a, m = DRAG.mode; DRAG = null; drawTop(a); if (m === "pan") uiChanged(); });
$("cross").onchange = (e) => { S.ui.crosshair = e.target.checked; for (const a of ["x", "y", "z"]) drawTop(a); uiChanged(); };
$("resetview").onclick = () => { for (const a of ["x", "y", "z"]) resetView(a); };
// The cursor readout: one request in flight, the latest position wins.
const RO = { busy: false, next: null, last: "" };
function readout(p) {
  const key = `${S.id}/${p.join("/")}`;
  if (key === RO.last && !RO.busy) return;
  RO.next = p; RO.last = key;
  if (!RO.busy) pumpReadout();
}
async function pumpReadout() {
  RO.busy = true;
  while (RO.next && S.id) {
    const p = RO.next; RO.next = null;
    try { showReadout(await api("GET", `/api/sessions/${S.id}/voxel/${p.join("/")}`)); }
    catch (e) { $("readout").textContent = "readout: " + e.message; }
  }
  RO.busy = false;
}
function showReadout(r) {
  const num = (v) => Number.isInteger(v) ? String(v) : (+v.toPrecision(5)).toString();
  let cls = "not classified yet";
  if (r.label !== null && r.label !== undefined) {
    const p = r.probabilities || {}, best = Object.entries(p).sort((x, y) => y[1] - x[1])[0];
    cls = r.label ? `${esc(r.label_name)} (p ${(+(p[r.label] || 0)).toFixed(2)})` : `unlabelled${best ? ` (most probable: ${best[0] === String(S.info.background) ? "background" : esc((S.info.classes.find((k) => String(k.id) === best[0]) || { name: best[0] }).name)} ${best[1].toFixed(2)})` : ""}`;
  }
  $("readout").innerHTML = `voxel <b>(${r.index.join(", ")})</b> · <b>(${r.world.map(mm).join(", ")})</b> mm · <b>${num(r.value)}${r.unit ? " " + esc(r.unit) : ""}</b> · ${cls}`;
  $("readout").dataset.voxel = JSON.stringify(r);
}
// Applies the slice views' part of S.ui (slice point, zoom and pan, window/level, crosshair),
// tolerating missing or bad fields (defaults: the middle slices, fitted views, the data's
// default window), and redraws.
function applyUi() {
  if (!S.info) return;
  const u = S.ui && typeof S.ui === "object" ? S.ui : (S.ui = {}), d = S.info.dims;
  const idx = u.idx && typeof u.idx === "object" ? u.idx : {};
  for (const a of ["x", "y", "z"]) {
    const n = d[AXK[a]], v = Number(idx[a]);
    S.idx[a] = Number.isFinite(v) ? Math.max(0, Math.min(n - 1, Math.round(v))) : Math.floor(n / 2);
    vstate(a);
  }
  u.idx = S.idx;
  $("wlpreset").innerHTML = `<option value="">preset ...</option>` + wlPresets().map(([n, w, l], i) => `<option value="${i}">${esc(n)}: W ${w} L ${l}</option>`).join("");
  if (!(Number(u.window) > 0) || !Number.isFinite(Number(u.level))) { const p = wlPresets()[0]; u.window = p[1]; u.level = p[2]; }
  u.window = Number(u.window); u.level = Number(u.level);
  u.crosshair = u.crosshair !== false; $("cross").checked = u.crosshair;
  showWl(); brushInfo("z");
  for (const a of ["x", "y", "z"]) { sliceLabel(a); drawSlice(a); }
}
// Slice-view keys (besides the slice steps in the handler below): C crosshair on/off, R reset
// the zoom and pan of the view under the mouse, Space held: the left button pans.
document.addEventListener("keydown", (e) => {
  if (e.target.tagName === "INPUT" && (e.target.type === "text" || e.target.type === "number")) return;
  if (e.ctrlKey || e.metaKey || e.altKey) return;
  const k = e.key;
  if (k === " ") { e.preventDefault(); SPACE = true; }
  else if ((k === "c" || k === "C") && S.info) { $("cross").checked = !$("cross").checked; $("cross").onchange({ target: $("cross") }); }
  else if ((k === "r" || k === "R") && S.info) resetView(S.hover);
  else if (k === "[" || k === "]") setTimeout(() => { if (S.info) { brushInfo(S.hover); drawTop(S.hover); } }, 0);
});
document.addEventListener("keyup", (e) => { if (e.key === " ") SPACE = false; });
$("brush").addEventListener("input", () => { if (S.info) { brushInfo(S.hover); drawTop(S.hover); } });
async function sendStrokes() {
  const url = `/api/sessions/${S.id}/strokes?focus=${S.idx.x},${S.idx.y},${S.idx.z}`;
  S.strokesAt = Date.now();
  try {
    if (S.plainStrokes) await api("PUT", url, S.strokes);
    else {
      try { await api("PUT", url, { strokes: S.strokes, redo: S.redo }); S.redoKept = true; }
      catch (e) { if (S.redoKept) throw e; await api("PUT", url, S.strokes); S.plainStrokes = true; }
    }
    status("classifying the slices on screen first ..."); progress(0, 1); S.firstPaint = true;
  }
  catch (e) { status("error: " + e.message); }
  for (const a of ["x", "y", "z"]) drawSlice(a);
}
$("undo").onclick = () => { if (S.strokes.length) { S.redo.push(S.strokes.pop()); sendStrokes(); } };
$("redo").onclick = () => { if (S.redo.length) { S.strokes.push(S.redo.pop()); sendStrokes(); } };
$("ovl").oninput = () => { for (const a of ["x", "y", "z"]) drawSlice(a); };
$("neuro").checked = localStorage.getItem("neuvolex.neurological") === "1";
$("neuro").onchange = (e) => {
  localStorage.setItem("neuvolex.neurological", e.target.checked ? "1" : "0");
  if (S.info) { layoutViews(); for (const a of ["x", "y", "z"]) drawSlice(a); showPreview(); }
  uiChanged();
};
for (const id of ["az", "el"]) $(id).oninput = () => { render(); uiChanged(); };
$("zoom").oninput = () => { render(); refreshThumbs(); uiChanged(); };
$("mode").oninput = () => { render(); refreshThumbs(); fillTfTargets(); drawTf(); uiChanged(); };
for (const id of ["vpcount", "vpangle", "epochs"]) $(id).onchange = uiChanged;
$("open").onclick = open;
const train = async (action) => { try { await api("POST", `/api/sessions/${S.id}/train`, { action, epochs: +$("epochs").value || 1 }); status("starting INR training ..."); } catch (e) { status("error: " + e.message); } };
$("train").onclick = () => train("start");
$("resume").onclick = () => train("resume");
$("exportz").onclick = async () => {
  if (!S.id) return;
  try { const r = await api("POST", `/api/sessions/${S.id}/export/zarr`, { name: "neuvolex" }); status(`wrote ${r.labels} and ${r.probabilities} into ${r.store}`); }
  catch (e) { status("error: " + e.message); }
};
$("stop").onclick = async () => { try { await api("POST", `/api/sessions/${S.id}/train`, { action: "stop" }); } catch (e) { status("error: " + e.message); } };
// Session files: the server writes and validates them (classes, strokes, transfer function);
// the view is the page's.
$("save").onclick = async () => {
  if (!S.id) return;
  try {
    const st = await api("GET", `/api/sessions/${S.id}/state`);
    st.view = { az: +$("az").value, el: +$("el").value, mode: $("mode").value };
    const blob = new Blob([JSON.stringify(st, null, 1)], { type: "application/json" });
    const a = document.createElement("a"); a.href = URL.createObjectURL(blob); a.download = "neuvolex-session.json"; a.click();
  } catch (e) { status("error: " + e.message); }
};
$("load").onchange = async (e) => {
  const f = e.target.files[0]; if (!f) return;
  const text = await f.text();
  let j; try { j = JSON.parse(text); } catch (err) { status(`error: ${f.name} is not JSON (${err.message})`); return; }
  if (!S.id || S.info.volume !== j.volume) { $("volume").value = j.volume; await open(); }
  try {
    const r = await fetch(`/api/sessions/${S.id}/state`, { method: "PUT", headers: { "Content-Type": "application/json" }, body: text });
    if (!r.ok) { let m = r.statusText; try { m = (await r.json()).error; } catch (_) {} throw new Error(m); }
    S.info = await r.json();
  } catch (err) { status(`error: ${f.name}: ${err.message}`); return; }
  S.strokes = j.strokes || []; S.redo = [];
  renderClasses(); await loadTf();
  if (j.view) { $("az").value = j.view.az; $("el").value = j.view.el; $("mode").value = j.view.mode || "labels"; fillTfTargets(); drawTf(); uiChanged(); }
  await loadFeatures();
  refreshAll();
  status(`loaded ${f.name}: ${S.strokes.length} strokes`);
};

// Features: the choices with their measured trade; what training feeds follows from the choice.
async function loadFeatures() {
  if (!S.id) return;
  let r; try { r = await api("GET", `/api/sessions/${S.id}/features`); } catch (_) { return; }
  const sel = $("features"); sel.innerHTML = "";
  const choices = r.choices.some((c) => c.set === r.set) ? r.choices : [...r.choices, { set: r.set, label: r.set, help: "", available: true }];
  for (const c of choices) {
    const o = document.createElement("option");
    o.value = c.set; o.textContent = c.label + (c.available ? "" : " (train the INR first)"); o.disabled = !c.available; o.title = c.help;
    sel.appendChild(o);
  }
  sel.value = r.set;
  $("featinfo").textContent = (choices.find((c) => c.set === r.set) || {}).help || "";
  $("featprep").textContent = r.stored === "complete" ? "features ready (kept in the store)" : r.stored === "pending" ? "preparing features ..." : "";
  $("trfeeds").textContent = r.uses_inr
    ? "The classification reads the INR: every model snapshot re-classifies. Training also feeds the recommended views."
    : "The classification does not read the INR: training feeds the recommended views and the preview (choose features with the INR to classify with it).";
}
$("features").onchange = async (e) => {
  if (!S.id) return;
  try {
    await api("PUT", `/api/sessions/${S.id}/features`, { set: e.target.value });
    if (S.strokes.length) { status("re-classifying with the new features ..."); progress(0, 1); S.firstPaint = true; }
  } catch (err) { status("error: " + err.message); }
  loadFeatures();
};
function trainingWords(d) {
  const m = d.model_version ? ` (model ${d.model_version})` : "";
  switch (d.state) {
    case "running": return `training the INR: epoch ${(d.epoch || 0).toFixed(2)}, PSNR ${(d.psnr || 0).toFixed(1)} dB`;
    case "snapshot": return `INR snapshot at step ${d.step}${m}${d.classifies ? ": re-classifying" : ""}`;
    case "finished": return `INR training finished (${d.stopped_by || "budget"}), PSNR ${(d.psnr || 0).toFixed(1)} dB`;
    case "model_saved": return `INR trained and saved, PSNR ${(d.psnr || 0).toFixed(1)} dB${m}${d.classifies ? ": re-classifying" : ""}`;
    case "stopped": return `INR training stopped${d.checkpoint ? "; Resume continues from the checkpoint" : ""}`;
    case "failed": return `INR training failed: ${d.error}`;
    default: return `INR training: ${d.state}${d.error ? ": " + d.error : ""}`;
  }
}

// Assistance: the spatial prior (a toggle) and the next-slice suggestion.
function priorInfo(r) {
  $("priorinfo").textContent = r && r.enabled && r.generation ? `${r.kept} of ${r.components} parts kept, ${r.voxels_cleared} voxels cleared, ${r.voxels_grown} grown` : "";
}
async function refreshPrior() { if (S.id) try { priorInfo(await api("GET", `/api/sessions/${S.id}/prior`)); } catch (_) {} }
$("prior").onchange = async (e) => {
  if (!S.id) return;
  try { priorInfo(await api("PUT", `/api/sessions/${S.id}/prior`, { enabled: e.target.checked })); }
  catch (err) { status("error: " + err.message); }
  // The overlays, the 3-D labels and the fractions all follow the prior.
  refreshAll(); refreshThumbs();
};
async function suggestSlice(axis) {
  if (!S.id) return;
  try {
    const r = await api("GET", `/api/sessions/${S.id}/suggest`);
    const sug = r.suggestions.find((s) => "xyz"[s.axis] === axis) || r.axial;
    if (!sug) { $("suggestinfo").textContent = "no uncertain voxel"; return; }
    const a = "xyz"[sug.axis];
    setSlice(a, sug.slice);
    $("suggestinfo").textContent = `${a} = ${sug.slice}: ${(100 * sug.share).toFixed(1)} % of the uncertainty${r.bricks < r.total_bricks ? " (so far)" : ""}`;
  } catch (e) { $("suggestinfo").textContent = "error: " + e.message; }
}
$("suggest").onclick = () => suggestSlice("z");

// Viewpoint recommendation: distinct views, each captioned with the reason it was picked; a
// click moves the 3-D view there. The thumbnails draw what the 3-D view draws (its mode, the
// current transfer function and labels).
$("recommend").onclick = async () => {
  if (!S.id) return;
  const count = Math.round(+$("vpcount").value) || 4, minAngle = +$("vpangle").value;
  $("vpinfo").textContent = "computing ...";
  try {
    const r = await api("POST", `/api/sessions/${S.id}/viewpoints`, { k: 50, views: 1800, count, min_angle: minAngle });
    const n = r.views.length, few = n < r.count ? ` (no more lie ${r.min_angle}\u00b0 apart)` : "";
    $("vpinfo").textContent = `${n} view${n === 1 ? "" : "s"}${few}, \u2265 ${r.min_angle}\u00b0 apart (${r.features} features, ${r.seconds.toFixed(1)} s)`;
    $("thumbs").innerHTML = "";
    S.views = r.views;
    r.views.forEach((v, i) => {
      const fig = document.createElement("figure"), img = document.createElement("img"), cap = document.createElement("figcaption");
      const pane = document.createElement("div"), mk = document.createElement("canvas");
      pane.style.position = "relative";
      mk.width = mk.height = 48; mk.className = "orient";
      mk.style.cssText = "position:absolute;left:1px;bottom:1px;width:48px;height:48px;pointer-events:none";
      img.alt = `view ${i + 1}`;
      cap.textContent = `${i + 1}. ${v.reason}`;
      fig.title = `${v.reason}\nazimuth ${v.azimuth.toFixed(0)}\u00b0, elevation ${v.elevation.toFixed(0)}\u00b0; ${v.in_view} of ${r.clusters} feature clusters in view, entropy ${v.entropy.toFixed(2)}`;
      fig.onclick = () => { $("az").value = Math.round(v.azimuth); $("el").value = Math.round(v.elevation); render(); uiChanged(); };
      pane.append(img, mk); fig.append(pane, cap);
      $("thumbs").appendChild(fig);
      drawOrientation(mk, v.azimuth, v.elevation);
    });
    refreshThumbs();
  } catch (e) { $("vpinfo").textContent = "error: " + e.message; }
};
// The thumbnails draw what the 3-D view draws (its mode, zoom, transfer function, colours and
// labels): re-rendered, coalesced like the 3-D view, after any of them changes.
async function refreshThumbs() {
  if (!S.id || !S.views || !S.views.length) return;
  if (S.thumbsPending) { S.thumbsAgain = true; return; }
  S.thumbsPending = true;
  try {
    do {
      S.thumbsAgain = false;
      const id = S.id, cam = camera(), t = Date.now(), imgs = [...document.querySelectorAll("#thumbs img")];
      const got = await Promise.all(S.views.map((v) => loadImg(`/api/sessions/${id}/render?${renderQuery({ ...cam, az: v.azimuth.toFixed(1), el: v.elevation.toFixed(1) }, 128)}&t=${t}`)));
      if (id !== S.id) break;
      await Promise.all(got.map((g, k) => { if (!g || !imgs[k]) return null; imgs[k].src = g.src; return imgs[k].decode().catch(() => {}); }));
    } while (S.thumbsAgain && S.id);
  } finally { S.thumbsPending = false; }
  S.thumbRenders = (S.thumbRenders || 0) + 1;
}

// Live updates over one event stream: ingest progress, classification brick by brick, training
// (with reconstruction previews and model snapshots), viewpoint aggregation, and failures.
let tick = null;
function subscribe() {
  const ev = new EventSource("/api/events");
  const on = (kind, f) => ev.addEventListener(kind, (e) => { const m = JSON.parse(e.data); if (m.session && m.session !== S.id) return; f(m.data); });
  on("ingest", (d) => status(d.stage === "done" ? `ingested ${d.volume}` : `ingesting ${d.volume}: ${d.stage} ${d.done}/${d.total}`));
  on("classified", (d) => {
    status(`classifying: ${d.done} of ${d.total} bricks`); progress(d.done, d.total);
    // The first brick of a new classification shows at once; later ones at most every 0.4 s.
    if (S.firstPaint) { S.firstPaint = false; for (const a of ["x", "y", "z"]) drawSlice(a); return; }
    if (!tick) tick = setTimeout(() => { tick = null; refreshAll(); }, 400);
  });
  on("classification", (d) => {
    status(d.error ? "classification failed: " + d.error : classificationWords(d.status));
    if (d.status && d.status.state === "done") { progress(1, 1); refreshThumbs(); syncStrokes(); }
    refreshAll(); refreshPrior();
  });
  on("training", (d) => {
    const t = trainingWords(d);
    status(t); $("trinfo").textContent = t;
    // A first model makes the sets with the INR available.
    if (d.state === "snapshot" || d.state === "model_saved") { loadFeatures(); if (d.classifies) { progress(0, 1); S.firstPaint = true; } }
  });
  // The background feature pass after an open: bricks whose features are ready (kept in the
  // volume's store, so the next open starts warm).
  on("features", (d) => { $("featprep").textContent = d.done === d.total ? "features ready (kept in the store)" : `preparing features: ${d.done} of ${d.total} bricks`; });
  on("preview", async (d) => {
    const id = S.id, i = await loadImg(`/api/sessions/${id}/preview.png?t=${Date.now()}`);
    if (!i || id !== S.id) return;
    S.previewImg = i; showPreview();
    $("preview").title = `reconstruction (left) beside the input (right), PSNR ${d.psnr.toFixed(1)} dB`;
  });
  on("viewpoints_progress", (d) => { $("vpinfo").textContent = `aggregating ${d.bricks}/${d.total} bricks; best so far azimuth ${d.best.azimuth.toFixed(0)}, elevation ${d.best.elevation.toFixed(0)}`; });
  on("actor_failed", (d) => { status("a worker failed and was restarted: " + d.error); });
  // A lost server shows at once; the stream reconnects by itself, and the session is checked
  // again (a restarted server may have closed it).
  ev.onerror = () => { document.querySelector("header").classList.add("offline"); };
  ev.onopen = async () => {
    const h = document.querySelector("header"), was = h.classList.contains("offline");
    h.classList.remove("offline");
    if (was && S.id) { try { await api("GET", `/api/sessions/${S.id}`); } catch (_) { status("the server restarted: resuming ..."); if (!(await resumeSession(S.id))) open(); } }
  };
  S.events = ev;
}
// The training preview (the middle z slice, reconstruction beside the input, each x across and
// y down, possibly subsampled) oriented like the page's view of z slices: each half is drawn
// through that view's frame (radiological or neurological, spacing-scaled).
function showPreview() {
  const i = S.previewImg;
  if (!i || !S.info) return;
  const f = frame("z"), d = S.info.dims, w = i.naturalWidth / 2, h = i.naturalHeight;
  // At least 256 pixels across each half (the image is shown pixelated).
  const k0 = Math.max(1, Math.ceil(256 / f.W)), W = Math.round(f.W * k0), H = Math.round(f.H * k0);
  const c = document.createElement("canvas"); c.width = 2 * W; c.height = H;
  const g = c.getContext("2d"); g.imageSmoothingEnabled = false;
  for (let k = 0; k < 2; k++) {
    // Preview pixels -> the server's z-slice image pixels -> the view's canvas, shifted to its half.
    g.setTransform(k0, 0, 0, k0, k * W, 0); g.transform(...f.image); g.scale(d[0] / w, d[1] / h);
    g.drawImage(i, k * w, 0, w, h, 0, 0, w, h);
  }
  $("preview").src = c.toDataURL();
}
// Another tab on the same session may have drawn: after a classification, take the server's
// strokes when they differ from this page's.
async function syncStrokes() {
  // Not right after this page's own change (its PUT may not have landed yet).
  const id = S.id, recent = () => Date.now() - (S.strokesAt || 0) < 3000;
  if (recent()) return;
  let st; try { st = await api("GET", `/api/sessions/${id}/state`); } catch (_) { return; }
  if (id !== S.id || recent() || !Array.isArray(st.strokes) || JSON.stringify(st.strokes) === JSON.stringify(S.strokes)) return;
  S.strokes = st.strokes; if (Array.isArray(st.redo)) S.redo = st.redo;
  for (const a of ["x", "y", "z"]) drawSlice(a);
}
function progress(done, total) { const p = $("progress"); p.max = Math.max(1, total); p.value = done; p.title = `${done} of ${total} bricks classified`; }
const FEATURE_WORDS = { "filters+xyz": "filter bank and position", "hidden+filters+xyz": "filter bank, position and the INR", inr: "INR features", paper: "the paper's feature" };
function classificationWords(st) {
  const f = FEATURE_WORDS[st.features] || st.features || "";
  const words = { idle: "waiting for scribbles of two classes", classifying: `classifying (${st.done} of ${st.total} bricks)`, done: `classified the whole volume`, cancelled: "superseded by a newer stroke", failed: "classification failed", training: "training the forest" };
  return `${words[st.state] || st.state}${st.message ? ": " + st.message : ""}${f ? " — features: " + f : ""}`;
}
subscribe();

// Keyboard shortcuts (Slicer / napari style).
function toggleHelp() { const h = $("help"); h.style.display = h.style.display === "block" ? "none" : "block"; }
document.addEventListener("keydown", (e) => {
  // Typing in a text or number field (a class name, W/L, epochs) is not a shortcut.
  if (e.target.tagName === "INPUT" && (e.target.type === "text" || e.target.type === "number")) return;
  const k = e.key;
  if ((e.ctrlKey || e.metaKey) && k.toLowerCase() === "z") { e.preventDefault(); (e.shiftKey ? $("redo") : $("undo")).click(); return; }
  if ((e.ctrlKey || e.metaKey) && k.toLowerCase() === "y") { e.preventDefault(); $("redo").click(); return; }
  if (/^[1-9]$/.test(k) && S.info && S.info.classes[+k - 1]) pick(S.info.classes[+k - 1].id);
  else if (k === "b" || k === "B") pick(255);
  else if (k === "e" || k === "E") pick(0);
  else if (k === "[") { $("brush").value = S.radius = Math.max(1, S.radius - 1); $("brushv").textContent = S.radius; uiChanged(); }
  else if (k === "]") { $("brush").value = S.radius = Math.min(20, S.radius + 1); $("brushv").textContent = S.radius; uiChanged(); }
  else if (k === "h" || k === "H" || k === "?") toggleHelp();
  else if (k === "n" || k === "N") suggestSlice(S.hover);
  else if (k === "o" || k === "O") { const o = $("ovl"); o.selectedIndex = (o.selectedIndex + 1) % o.options.length; o.oninput(); uiChanged(); }
  else if (["ArrowUp", "ArrowDown", "PageUp", "PageDown"].includes(k) && S.id) {
    e.preventDefault(); setSlice(S.hover, S.idx[S.hover] + (k === "ArrowUp" || k === "PageUp" ? 1 : -1));
  }
});
loadBackend();
$("ovl").addEventListener("input", () => uiChanged());
// On load: the session the URL names; without one, the newest session (open or saved) on a
// volume of this data root, as reopening an application brings back the last document; a new
// session on the first volume only when there is none (only Open starts one otherwise).
loadVolumes().then(async () => {
  const want = new URLSearchParams(location.search).get("session");
  if (want && (await resumeSession(want))) return;
  if (!want) {
    try {
      const vols = [...$("volume").options].map((o) => o.value);
      const l = await api("GET", "/api/sessions");
      const last = (l.sessions || []).find((s) => vols.includes(s.volume));
      if (last && (await resumeSession(last.id))) return;
    } catch (_) { /* no list: a new session below */ }
  }
  if ($("volume").options.length) open();
});
