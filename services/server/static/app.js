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
    const gpu = b.train === "gpu" || b.render === "gpu";
    const e = $("engines");
    e.textContent = gpu ? `GPU${b.software ? " (software)" : ""}: ${b.adapter}` : "CPU";
    e.title = `INR training: ${b.train}, rendering: ${b.render} (requested: ${b.requested}${b.gpu_build ? "" : "; this build has no GPU engines"})`;
    e.style.background = gpu ? "#1f4d2b" : "#333";
    e.style.color = gpu ? "#9e9" : "#aaa";
  } catch (_) { $("engines").textContent = "engines unknown"; }
}

async function open() {
  status("opening " + $("volume").value + " ...");
  try {
    S.info = await api("POST", "/api/sessions", { volume: $("volume").value, restore: true });
  } catch (e) { status("error: " + e.message); return; }
  S.id = S.info.id; S.strokes = []; S.redo = []; progress(0, 1);
  // A session restored from its last run brings its strokes back.
  if (S.info.strokes > 0) { try { S.strokes = await api("GET", `/api/sessions/${S.id}/strokes`); } catch (_) {} }
  const d = S.info.dims;
  for (const a of ["x", "y", "z"]) {
    const n = d[{ x: 0, y: 1, z: 2 }[a]];
    $("i" + a).max = n - 1; $("i" + a).value = S.idx[a] = Math.floor(n / 2);
  }
  $("export").href = `/api/sessions/${S.id}/export/labels.nii.gz`;
  layoutViews(); renderClasses(); await loadTf(); refreshAll();
  $("trinfo").textContent = S.info.trained ? `INR trained (model ${S.info.model_version})` : "not trained"; $("preview").removeAttribute("src");
  await loadFeatures();
  $("prior").checked = !S.info.prior || S.info.prior.enabled; priorInfo(S.info.prior); $("suggestinfo").textContent = "";
  status(`${S.info.volume}: ${d.join(" x ")}`);
}

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
  try { S.info = await api("PUT", `/api/sessions/${S.id}/classes`, S.info.classes); renderClasses(); fillTfTargets(); drawTf(); refreshAll(); }
  catch (e) { status("error: " + e.message); }
}
function pick(id) {
  S.cls = id; renderClasses();
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
$("brush").oninput = (e) => { S.radius = +e.target.value; $("brushv").textContent = S.radius; };

function wl() {
  const [lo, hi] = S.info.percentiles; const w = (hi - lo) * $("win").value / 100;
  const l = lo + (hi - lo) * $("lev").value / 100; return `window=${w}&level=${l}`;
}
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
  // Continuous voxel coordinates (along u, along v) → canvas pixels, and back.
  const toScreen = (U, V) => { const vh = h === ax.u ? U : V, vw = h === ax.u ? V : U;
    return [sx > 0 ? vh * kh : (d[h] - vh) * kh, sy > 0 ? vw * kw : (d[w] - vw) * kw]; };
  const toVoxel = (X, Y) => { const vh = sx > 0 ? X / kh : d[h] - X / kh, vw = sy > 0 ? Y / kw : d[w] - Y / kw;
    return h === ax.u ? [vh, vw] : [vw, vh]; };
  const affine = (f) => { const o = f(0, 0), x = f(1, 0), y = f(0, 1); return [x[0] - o[0], x[1] - o[1], y[0] - o[0], y[1] - o[1], o[0], o[1]]; };
  return {
    view, W: Math.max(1, Math.round(d[h] * kh)), H: Math.max(1, Math.round(d[w] * kw)),
    letters: { left: OPP[right], right, top: up, bottom: OPP[up] },
    voxel: affine(toScreen), // voxel (u, v) → canvas
    image: affine((i, j) => toScreen(i, ax.flip ? d[ax.v] - j : j)), // server image → canvas
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
  }
}
// One paint per update: both images are fetched, then base, overlay and strokes are drawn at
// once, and only by the latest request for that view.
const paintSeq = { x: 0, y: 0, z: 0 };
async function drawSlice(a) {
  if (!S.id) return;
  const seq = ++paintSeq[a], c = $("c" + a), idx = S.idx[a], id = S.id;
  let kind = $("ovl").value, cls = "";
  if (kind.startsWith("cls-")) { kind = kind.slice(4); cls = `&class=${S.cls || 255}`; }
  const [base, o] = await Promise.all([
    loadImg(`/api/sessions/${id}/slice/${a}/${idx}?${wl()}`),
    kind ? loadImg(`/api/sessions/${id}/overlay/${a}/${idx}?kind=${kind}${cls}&t=${Date.now()}`) : null,
  ]);
  if (!base || seq !== paintSeq[a] || id !== S.id) return;
  const f = frame(a);
  if (c.width !== f.W || c.height !== f.H) { c.width = f.W; c.height = f.H; }
  const g = c.getContext("2d"); g.imageSmoothingEnabled = false;
  g.setTransform(1, 0, 0, 1, 0, 0); g.clearRect(0, 0, c.width, c.height);
  g.setTransform(...f.image); g.drawImage(base, 0, 0);
  if (o) g.drawImage(o, 0, 0);
  drawStrokes(a, g);
}
function drawStrokes(a, g, extra) {
  g.setTransform(...frame(a).voxel);
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
}
function refreshAll() { for (const a of ["x", "y", "z"]) drawSlice(a); render(); fractions(); }
async function render() {
  if (!S.id || S.renderPending) return; S.renderPending = true;
  const q = new URLSearchParams({ az: $("az").value, el: $("el").value, size: 400, zoom: $("zoom").value });
  if ($("mode").value) q.set("mode", $("mode").value);
  const i = await loadImg(`/api/sessions/${S.id}/render?${q}&t=${Date.now()}`);
  if (i) $("render").src = i.src;
  S.renderPending = false;
}
async function fractions() {
  if (!S.id) return;
  const f = await api("GET", `/api/sessions/${S.id}/fractions`);
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
function fillTfTargets() {
  const opts = [["intensity", "intensity (all)"]];
  for (const c of S.info.classes) { opts.push([`p:${c.id}`, `${c.name}: opacity over probability`]); opts.push([`i:${c.id}`, `${c.name}: opacity over intensity`]); }
  $("tftarget").innerHTML = opts.map(([v, t]) => `<option value="${v}">${t}</option>`).join("");
  if (!opts.some((o) => o[0] === TF.target)) TF.target = "intensity";
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
  const defInt = () => ({ opacity: S.tf.intensity ? JSON.parse(JSON.stringify(S.tf.intensity.opacity)) : [[rawToMap(lo), 0.35]] });
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
  try { S.info = await api("PUT", `/api/sessions/${S.id}/tf`, S.tf); render(); }
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
$("tftarget").onchange = (e) => { TF.target = e.target.value; drawTf(); };
$("tf").onchange = async (e) => {
  if (!e.target.value || !S.id) return;
  S.tf = await api("GET", `/api/presets/${e.target.value}`); e.target.value = ""; drawTf(); pushTf();
};
$("tfreset").onclick = async () => { if (!S.id) return; S.info = await api("PUT", `/api/sessions/${S.id}/tf`, null); await loadTf(); render(); };

// Drawing strokes.
let drawing = null;
for (const a of ["x", "y", "z"]) {
  const c = $("c" + a), ax = AX[a];
  const pos = (e) => { const r = c.getBoundingClientRect(), d = S.info.dims;
    const [U, V] = frame(a).toVoxel((e.clientX - r.left) * c.width / r.width, (e.clientY - r.top) * c.height / r.height);
    return [Math.max(0, Math.min(d[ax.u] - 1, Math.floor(U))), Math.max(0, Math.min(d[ax.v] - 1, Math.floor(V)))]; };
  c.onmouseenter = () => { S.hover = a; };
  c.onmousedown = (e) => { if (!S.id || e.button !== 0) return; drawing = { class: S.cls, axis: a, slice: S.idx[a], points: [pos(e)], radius: S.radius }; };
  c.onmousemove = (e) => { if (!drawing || drawing.axis !== a) return; drawing.points.push(pos(e)); drawStrokes(a, c.getContext("2d"), drawing); };
  c.onmouseup = c.onmouseleave = () => { if (!drawing || drawing.axis !== a) return; S.strokes.push(drawing); S.redo = []; drawing = null; sendStrokes(); };
  $("i" + a).oninput = (e) => { S.idx[a] = +e.target.value; drawSlice(a); };
}
async function sendStrokes() {
  try { const r = await api("PUT", `/api/sessions/${S.id}/strokes?focus=${S.idx.x},${S.idx.y},${S.idx.z}`, S.strokes); status("classifying the slices on screen first ..."); progress(0, 1); S.firstPaint = true; }
  catch (e) { status("error: " + e.message); }
  for (const a of ["x", "y", "z"]) drawSlice(a);
}
$("undo").onclick = () => { if (S.strokes.length) { S.redo.push(S.strokes.pop()); sendStrokes(); } };
$("redo").onclick = () => { if (S.redo.length) { S.strokes.push(S.redo.pop()); sendStrokes(); } };
for (const id of ["win", "lev", "ovl"]) $(id).oninput = () => { for (const a of ["x", "y", "z"]) drawSlice(a); };
$("neuro").checked = localStorage.getItem("neuvolex.neurological") === "1";
$("neuro").onchange = (e) => {
  localStorage.setItem("neuvolex.neurological", e.target.checked ? "1" : "0");
  if (S.info) { layoutViews(); for (const a of ["x", "y", "z"]) drawSlice(a); }
};
for (const id of ["az", "el", "mode", "zoom"]) $(id).oninput = render;
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
  if (j.view) { $("az").value = j.view.az; $("el").value = j.view.el; $("mode").value = j.view.mode || "labels"; }
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
  refreshAll();
};
async function suggestSlice(axis) {
  if (!S.id) return;
  try {
    const r = await api("GET", `/api/sessions/${S.id}/suggest`);
    const sug = r.suggestions.find((s) => "xyz"[s.axis] === axis) || r.axial;
    if (!sug) { $("suggestinfo").textContent = "no uncertain voxel"; return; }
    const a = "xyz"[sug.axis];
    $("i" + a).value = S.idx[a] = sug.slice; drawSlice(a);
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
    const mode = $("mode").value;
    r.views.forEach((v, i) => {
      const q = new URLSearchParams({ az: v.azimuth.toFixed(1), el: v.elevation.toFixed(1), size: 128, zoom: $("zoom").value });
      if (mode) q.set("mode", mode);
      const fig = document.createElement("figure"), img = document.createElement("img"), cap = document.createElement("figcaption");
      img.src = `/api/sessions/${S.id}/render?${q}`;
      img.alt = `view ${i + 1}`;
      cap.textContent = `${i + 1}. ${v.reason}`;
      fig.title = `${v.reason}\nazimuth ${v.azimuth.toFixed(0)}\u00b0, elevation ${v.elevation.toFixed(0)}\u00b0; ${v.in_view} of ${r.clusters} feature clusters in view, entropy ${v.entropy.toFixed(2)}`;
      fig.onclick = () => { $("az").value = Math.round(v.azimuth); $("el").value = Math.round(v.elevation); render(); };
      fig.append(img, cap);
      $("thumbs").appendChild(fig);
    });
  } catch (e) { $("vpinfo").textContent = "error: " + e.message; }
};

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
    if (d.status && d.status.state === "done") progress(1, 1);
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
  on("preview", (d) => { $("preview").src = `/api/sessions/${S.id}/preview.png?t=${Date.now()}`; $("preview").title = `reconstruction (left) beside the input (right), PSNR ${d.psnr.toFixed(1)} dB`; });
  on("viewpoints_progress", (d) => { $("vpinfo").textContent = `aggregating ${d.bricks}/${d.total} bricks; best so far azimuth ${d.best.azimuth.toFixed(0)}, elevation ${d.best.elevation.toFixed(0)}`; });
  on("actor_failed", (d) => { status("a worker failed and was restarted: " + d.error); });
  // A lost server shows at once; the stream reconnects by itself, and the session is checked
  // again (a restarted server may have closed it).
  ev.onerror = () => { document.querySelector("header").classList.add("offline"); };
  ev.onopen = async () => {
    const h = document.querySelector("header"), was = h.classList.contains("offline");
    h.classList.remove("offline");
    if (was && S.id) { try { await api("GET", `/api/sessions/${S.id}`); } catch (_) { status("the server restarted: reopening ..."); open(); } }
  };
  S.events = ev;
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
  if (e.target.tagName === "INPUT" && e.target.type === "text") return;
  const k = e.key;
  if ((e.ctrlKey || e.metaKey) && k.toLowerCase() === "z") { e.preventDefault(); (e.shiftKey ? $("redo") : $("undo")).click(); return; }
  if ((e.ctrlKey || e.metaKey) && k.toLowerCase() === "y") { e.preventDefault(); $("redo").click(); return; }
  if (/^[1-9]$/.test(k) && S.info && S.info.classes[+k - 1]) pick(S.info.classes[+k - 1].id);
  else if (k === "b" || k === "B") pick(255);
  else if (k === "e" || k === "E") pick(0);
  else if (k === "[") { $("brush").value = S.radius = Math.max(1, S.radius - 1); $("brushv").textContent = S.radius; }
  else if (k === "]") { $("brush").value = S.radius = Math.min(20, S.radius + 1); $("brushv").textContent = S.radius; }
  else if (k === "h" || k === "H" || k === "?") toggleHelp();
  else if (k === "n" || k === "N") suggestSlice(S.hover);
  else if (k === "o" || k === "O") { const o = $("ovl"); o.selectedIndex = (o.selectedIndex + 1) % o.options.length; o.oninput(); }
  else if (["ArrowUp", "ArrowDown", "PageUp", "PageDown"].includes(k) && S.id) {
    e.preventDefault(); const a = S.hover, s = $("i" + a); s.value = S.idx[a] = Math.max(0, Math.min(+s.max, S.idx[a] + (k === "ArrowUp" || k === "PageUp" ? 1 : -1))); drawSlice(a);
  }
});
loadBackend();
loadVolumes().then(() => { if ($("volume").options.length) open(); });
