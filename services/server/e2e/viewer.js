// End-to-end test of the slice viewer in real headless Chromium (Debian's chromium, driven by
// playwright-core). Run by services/cli/tests/e2e.rs:
//   node viewer.js URL SHOTS_DIR
// The data root holds `viewer-ct.nii` (written by the test): 48 x 40 x 30 voxels of
// 0.8 x 0.8 x 2 mm, stored with scl_slope 2 and scl_inter -1024, in HU: air (-1000) around a
// body box (x 6..42, y 5..35: 40 + x + 2y HU) holding a bone cube (x 30..38, y 8..14,
// z 18..24: 1000 + x HU). Checks, each against the page's pixels, its DOM or the API:
//   1. the page fits 1280 x 800 without scrolling, the slice views are larger than 293 px;
//   2. window/level in HU: W 400 L 40 by default (CT, from the data), the bone preset and a
//      right-drag change the numbers, the requests and the pixels;
//   3. the wheel and PgUp/PgDn step the slice under the mouse; each view shows "i / n" and the
//      slice's world position from the affine;
//   4. Shift+click sets the crosshair point: the other views go to its slices and all three
//      draw the crosshair; C hides it;
//   5. Ctrl+wheel zooms about the cursor (the voxel under it stays), middle-drag and Space+drag
//      pan, a stroke
//      drawn while zoomed and panned lands on the bone cube's voxels (GET strokes), R resets;
//   6. the cursor readout: voxel index, world mm, HU value equal to the generated volume's,
//      and after classification the label's name and probability;
//   7. the brush outline's size on screen is the brush radius in voxels (an ellipse in the
//      anisotropic coronal view), with its size in mm;
//   8. applyUi restores the viewer's settings, and a reload brings them back; the layout still
//      fits after recommended views, and the views grow with a larger window.
// Screenshots go to SHOTS_DIR/viewer-*.png.
const { launch } = require("./common");
const path = require("path");

const failures = [];
const check = (ok, what) => { if (!ok) failures.push(what); console.log(`${ok ? "ok  " : "FAIL"} ${what}`); };
const CUBE = { x: [30, 38], y: [8, 14], z: [18, 24] };
const hu = ([x, y, z]) => {
  if (x >= CUBE.x[0] && x < CUBE.x[1] && y >= CUBE.y[0] && y < CUBE.y[1] && z >= CUBE.z[0] && z < CUBE.z[1]) return 1000 + x;
  if (x >= 6 && x < 42 && y >= 5 && y < 35) return 40 + x + 2 * y;
  return -1000;
};
const AFF = [[0.8, 0, 0, -19.2], [0, 0.8, 0, -16], [0, 0, 2, -30]];
const world = (p) => AFF.map((r) => r[0] * p[0] + r[1] * p[1] + r[2] * p[2] + r[3]);
const inCube = (p) => p[0] >= CUBE.x[0] && p[0] < CUBE.x[1] && p[1] >= CUBE.y[0] && p[1] < CUBE.y[1];

(async () => {
  const [url, shots] = process.argv.slice(2);
  const browser = await launch();
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  const shot = (name) => page.screenshot({ path: path.join(shots, `viewer-${name}.png`) });
  const errors = [], sliceUrls = [];
  page.on("pageerror", (e) => errors.push(e.message));
  page.on("request", (r) => { if (/\/slice\//.test(r.url())) sliceUrls.push(r.url()); });
  await page.goto(url);
  await page.waitForFunction(() => document.getElementById("volume").options.length > 0, null, { timeout: 60000 });
  await page.selectOption("#volume", "viewer-ct.nii");
  await page.evaluate(() => { document.getElementById("status").textContent = ""; });
  await page.click("#open");
  await page.waitForFunction(() => S.info && S.info.volume === "viewer-ct.nii" && document.getElementById("status").textContent.includes(" x "), null, { timeout: 120000 });
  await page.waitForTimeout(1500);

  // Helpers: a view's canvas box, the bright (bone) pixels' centroid in page coordinates, a
  // canvas's drawn pixels.
  const canvasBox = (a) => page.locator("#c" + a).boundingBox();
  const bright = (a) => page.evaluate((a) => {
    const c = document.getElementById("c" + a), g = c.getContext("2d"), d = g.getImageData(0, 0, c.width, c.height).data, r = c.getBoundingClientRect();
    let sx = 0, sy = 0, n = 0, x0 = 1e9, x1 = -1, y0 = 1e9, y1 = -1;
    for (let y = 0; y < c.height; y++) for (let x = 0; x < c.width; x++) { const i = (y * c.width + x) * 4; if (d[i] > 250 && d[i + 1] > 250 && d[i + 2] > 250) { sx += x; sy += y; n++; x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); } }
    const k = r.width / c.width;
    return n ? { n, x: r.left + (sx / n + 0.5) * k, y: r.top + (sy / n + 0.5) * k, w: (x1 - x0 + 1) * k, h: (y1 - y0 + 1) * k } : { n: 0 };
  }, a);
  const drawn = (id) => page.evaluate((id) => {
    const c = document.getElementById(id), d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data; let n = 0;
    for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n;
  }, id);
  const pixels = (a) => page.evaluate((a) => { const c = document.getElementById("c" + a); return Array.from(c.getContext("2d").getImageData(0, 0, c.width, c.height).data); }, a);
  const changed = (p, q) => { let n = 0; for (let i = 0; i < Math.min(p.length, q.length); i += 4) if (Math.abs(p[i] - q[i]) > 20) n++; return n; };
  const readout = async (x, y) => {
    await page.evaluate(() => { delete document.getElementById("readout").dataset.voxel; RO.last = ""; });
    await page.mouse.move(x, y);
    await page.waitForFunction(() => document.getElementById("readout").dataset.voxel, null, { timeout: 10000 }).catch(() => {});
    await page.waitForTimeout(300);
    const s = await page.evaluate(() => document.getElementById("readout").dataset.voxel);
    return s ? JSON.parse(s) : null;
  };
  const idx = () => page.evaluate(() => ({ ...S.idx }));

  // 1. Layout at 1280 x 800.
  const fits = () => page.evaluate(() => {
    const de = document.documentElement, panes = ["x", "y", "z"].map((a) => document.getElementById("c" + a).getBoundingClientRect());
    const panels = [...document.querySelectorAll("main > .panel")].map((p) => p.getBoundingClientRect().bottom);
    return { sw: de.scrollWidth, sh: de.scrollHeight, iw: innerWidth, ih: innerHeight, panes: panes.map((r) => [Math.round(r.width), Math.round(r.height)]), bottom: Math.max(...panels) };
  });
  const f1 = await fits();
  check(f1.sw <= f1.iw && f1.sh <= f1.ih && f1.bottom <= f1.ih, `the page fits 1280 x 800 without scrolling: ${JSON.stringify(f1)}`);
  check(f1.panes.every(([w, h]) => w > 293 && h > 293), `slice views larger than 293 px: ${JSON.stringify(f1.panes)}`);
  await shot("01-opened");

  // 2. Window/level in HU.
  const wlText = () => page.evaluate(() => [+document.getElementById("win").value, +document.getElementById("lev").value, document.getElementById("wlunit").textContent.trim()]);
  const wl0 = await wlText();
  check(wl0[0] === 400 && wl0[1] === 40 && wl0[2] === "HU", `CT default window W 400 L 40 HU: ${wl0}`);
  check(sliceUrls.some((u) => /window=400&level=40\b/.test(u)), "slices requested with window=400&level=40");
  const before = await pixels("z");
  const presets = await page.evaluate(() => [...document.getElementById("wlpreset").options].map((o) => o.textContent));
  check(["soft tissue: W 400 L 40", "lung: W 1500 L -600", "bone: W 1800 L 400", "brain: W 80 L 40"].every((p) => presets.some((o) => o.endsWith(p))), `CT presets: ${JSON.stringify(presets)}`);
  const bone = await page.evaluate(() => [...document.getElementById("wlpreset").options].find((o) => /bone/.test(o.textContent)).value);
  await page.selectOption("#wlpreset", bone);
  await page.waitForTimeout(1200);
  const wl1 = await wlText();
  check(wl1[0] === 1800 && wl1[1] === 400, `bone preset: ${wl1}`);
  check(sliceUrls.some((u) => /window=1800&level=400\b/.test(u)), "slices requested with window=1800&level=400");
  const dBone = changed(before, await pixels("z"));
  check(dBone > 1000, `the bone window changed the axial pixels (${dBone})`);
  await shot("02-bone-window");
  // Right-drag: across widens the window, down raises the level.
  const bz = await canvasBox("z");
  await page.mouse.move(bz.x + bz.width / 2, bz.y + bz.height / 2);
  await page.mouse.down({ button: "right" });
  for (let i = 1; i <= 5; i++) await page.mouse.move(bz.x + bz.width / 2 + 20 * i, bz.y + bz.height / 2 + 10 * i);
  await page.mouse.up({ button: "right" });
  await page.waitForTimeout(800);
  const wl2 = await wlText();
  check(wl2[0] > 1800 * 1.5 && wl2[1] > 400 + 200, `right-drag changed window and level: ${wl2}`);
  // Typed numbers: the window follows, and digits typed there pick no class.
  const cls0 = await page.evaluate(() => S.cls);
  await page.locator("#win").click({ clickCount: 3 });
  await page.keyboard.type("2");
  await page.keyboard.press("Enter");
  await page.waitForTimeout(600);
  const typed = await page.evaluate(() => [S.ui.window, S.cls]);
  check(typed[0] === 2 && typed[1] === cls0 && sliceUrls.some((u) => /window=2&level=/.test(u)), `typing W 2: window ${typed[0]}, class ${typed[1]} (was ${cls0})`);
  const soft = await page.evaluate(() => [...document.getElementById("wlpreset").options].find((o) => /soft/.test(o.textContent)).value);
  await page.selectOption("#wlpreset", soft);
  await page.waitForTimeout(800);

  // 3. Slice stepping: wheel and keys on the view under the mouse; "i / n" and world mm.
  const z0 = (await idx()).z;
  await page.mouse.move(bz.x + bz.width / 2, bz.y + bz.height / 2);
  await page.mouse.wheel(0, 100);
  await page.waitForTimeout(300);
  const z1 = (await idx()).z;
  check(z1 === z0 - 1, `wheel down: axial slice ${z0} -> ${z1}`);
  for (let i = 0; i < 7; i++) await page.keyboard.press("PageUp");
  await page.mouse.wheel(0, -100);
  await page.waitForTimeout(300);
  const z2 = (await idx()).z;
  check(z2 === z1 + 8, `PageUp x7 and wheel up: ${z1} -> ${z2}`);
  const lab = await page.evaluate(() => document.getElementById("sz").textContent);
  check(lab === `${z2} / 30 · S ${(2 * z2 - 30).toFixed(1)} mm`, `axial label "${lab}" (want ${z2} / 30 · S ${(2 * z2 - 30).toFixed(1)} mm)`);
  await page.waitForTimeout(800);

  // 4. Crosshair: Shift+click on the bone cube.
  let cube = await bright("z");
  check(cube.n > 50, `the bone cube shows on axial slice ${z2} (${cube.n} pixels)`);
  await page.keyboard.down("Shift");
  await page.mouse.click(cube.x, cube.y);
  await page.keyboard.up("Shift");
  await page.waitForTimeout(1200);
  const p = await idx();
  check(inCube([p.x, p.y]) && p.z === z2, `Shift+click set the point in the cube: ${JSON.stringify(p)}`);
  const sliders = await page.evaluate(() => [+document.getElementById("ix").value, +document.getElementById("iy").value]);
  check(sliders[0] === p.x && sliders[1] === p.y, `coronal and sagittal went to the point's slices: ${sliders}`);
  const labs = await page.evaluate(() => [document.getElementById("sx").textContent, document.getElementById("sy").textContent]);
  check(labs[0].startsWith(`${p.x} / 48 · R ${(0.8 * p.x - 19.2).toFixed(1)} mm`) && labs[1].startsWith(`${p.y} / 40 · A ${(0.8 * p.y - 16).toFixed(1)} mm`), `slice labels: ${labs}`);
  const ccor = await bright("y"), csag = await bright("x");
  check(ccor.n > 20 && csag.n > 20, `the cube shows in the coronal (${ccor.n}) and sagittal (${csag.n}) views`);
  const lines = [await drawn("tx"), await drawn("ty")];
  check(lines.every((n) => n > 200), `crosshair lines drawn in the coronal and sagittal views: ${lines}`);
  await shot("03-crosshair");
  await page.keyboard.press("c");
  await page.waitForTimeout(200);
  const off = [await drawn("tx"), await drawn("ty")];
  check(off.every((n) => n === 0), `C hides the crosshair: ${off}`);
  await page.keyboard.press("c");

  // 5. Zoom about the cursor, pan, draw while zoomed, reset.
  cube = await bright("z");
  const r0 = await readout(cube.x, cube.y);
  for (let i = 0; i < 4; i++) { await page.keyboard.down("Control"); await page.mouse.wheel(0, -100); await page.keyboard.up("Control"); await page.waitForTimeout(100); }
  await page.waitForTimeout(300);
  const zoom = await page.evaluate(() => S.ui.views.z.zoom);
  check(zoom > 1.8, `Ctrl+wheel zoomed the axial view (${zoom})`);
  const r1 = await readout(cube.x + 1, cube.y);
  check(r0 && r1 && Math.abs(r0.index[0] - r1.index[0]) <= 1 && Math.abs(r0.index[1] - r1.index[1]) <= 1, `zoom about the cursor keeps the voxel under it: ${r0 && r0.index} vs ${r1 && r1.index}`);
  const zc = await bright("z");
  check(zc.n > cube.n * 2.5, `the cube is larger zoomed (${cube.n} -> ${zc.n} pixels)`);
  bz.cx = bz.x + bz.width / 2; bz.cy = bz.y + bz.height / 2;
  await page.mouse.move(bz.cx, bz.cy);
  await page.mouse.down({ button: "middle" });
  // Towards the pane's middle, so the cube stays in view.
  const sx = zc.x < bz.cx ? 10 : -10, sy = zc.y < bz.cy ? 6 : -6;
  for (let i = 1; i <= 6; i++) await page.mouse.move(bz.cx + sx * i, bz.cy + sy * i);
  await page.mouse.up({ button: "middle" });
  await page.waitForTimeout(300);
  const zp = await bright("z");
  check(Math.abs(zp.x - zc.x - 6 * sx) < 3 && Math.abs(zp.y - zc.y - 6 * sy) < 3, `middle-drag panned the view by (${6 * sx}, ${6 * sy}): (${(zp.x - zc.x).toFixed(1)}, ${(zp.y - zc.y).toFixed(1)})`);
  // Space+left-drag pans too (back where it was), and draws nothing.
  const nSpace = await page.evaluate(() => S.strokes.length);
  await page.keyboard.down(" ");
  await page.mouse.move(bz.cx, bz.cy); await page.mouse.down();
  for (let i = 1; i <= 6; i++) await page.mouse.move(bz.cx - sx * i, bz.cy - sy * i);
  await page.mouse.up(); await page.keyboard.up(" ");
  await page.waitForTimeout(300);
  const zs = await bright("z");
  check(Math.abs(zs.x - zc.x) < 3 && Math.abs(zs.y - zc.y) < 3 && (await page.evaluate(() => S.strokes.length)) === nSpace, `Space+drag panned back without drawing: (${(zs.x - zc.x).toFixed(1)}, ${(zs.y - zc.y).toFixed(1)})`);
  await page.mouse.move(bz.cx, bz.cy); await page.mouse.down({ button: "middle" });
  for (let i = 1; i <= 6; i++) await page.mouse.move(bz.cx + sx * i, bz.cy + sy * i);
  await page.mouse.up({ button: "middle" });
  await page.waitForTimeout(300);
  await shot("04-zoomed-panned");
  // A class-1 stroke across the cube's middle, while zoomed and panned.
  const nBefore = await page.evaluate(() => S.strokes.length);
  await page.keyboard.press("1");
  await page.mouse.move(zp.x - zp.w / 4, zp.y);
  await page.mouse.down();
  for (let i = 1; i <= 8; i++) await page.mouse.move(zp.x - zp.w / 4 + zp.w / 2 * i / 8, zp.y);
  await page.mouse.up();
  await page.waitForTimeout(1000);
  const strokes = await page.evaluate(async () => (await fetch(`/api/sessions/${S.id}/strokes`)).json());
  const st = strokes[nBefore];
  check(st && st.axis === "z" && st.slice === z2 && st.class === 1, `the stroke reached the server: ${JSON.stringify(st)}`);
  check(st && st.points.length >= 2 && st.points.every((q) => inCube(q)), `every stroke point lies on the cube's voxels: ${st && JSON.stringify(st.points)}`);
  // Background on the body and the air, in the fitted view after R.
  await page.mouse.move(bz.cx, bz.cy);
  await page.keyboard.press("r");
  await page.waitForTimeout(300);
  const reset = await page.evaluate(() => S.ui.views.z);
  check(reset.zoom === 1 && reset.cx === 0.5 && reset.cy === 0.5, `R reset the view: ${JSON.stringify(reset)}`);
  const rect = await page.evaluate(() => viewRect("z"));
  const at = (fx, fy) => [bz.x + rect.x + rect.w * fx, bz.y + rect.y + rect.h * fy];
  // The air along the top, and the body opposite the cube across the middle.
  const fc = await bright("z"), ox = 1 - (fc.x - bz.x - rect.x) / rect.w, oy = 1 - (fc.y - bz.y - rect.y) / rect.h;
  await page.keyboard.press("b");
  for (const [a, b] of [[[0.03, 0.03], [0.6, 0.03]], [[ox - 0.1, oy], [ox + 0.1, oy]]]) {
    await page.mouse.move(...at(...a)); await page.mouse.down();
    for (let i = 1; i <= 6; i++) await page.mouse.move(...at(a[0] + (b[0] - a[0]) * i / 6, a[1] + (b[1] - a[1]) * i / 6));
    await page.mouse.up();
  }
  await page.waitForFunction(() => /classified the whole volume/.test(document.getElementById("status").textContent), null, { timeout: 180000 }).catch(() => check(false, "classification finished"));
  await page.waitForTimeout(1500);

  // 6. The readout: index, world, HU, label and probability (the overlay off to find the cube).
  await page.selectOption("#ovl", "");
  await page.waitForTimeout(1000);
  cube = await bright("z");
  const rc = await readout(cube.x, cube.y);
  check(rc && inCube(rc.index) && rc.index[2] === z2, `readout on the cube: ${rc && rc.index}`);
  check(rc && rc.value === hu(rc.index) && rc.unit === "HU", `HU at ${rc && rc.index}: ${rc && rc.value} (want ${rc && hu(rc.index)})`);
  check(rc && world(rc.index).every((v, k) => Math.abs(v - rc.world[k]) < 1e-6), `world mm at ${rc && rc.index}: ${rc && rc.world} (want ${rc && world(rc.index)})`);
  const name1 = await page.evaluate(() => S.info.classes.find((c) => c.id === 1).name);
  check(rc && rc.label === 1 && rc.label_name === name1 && rc.probabilities["1"] >= 0.5, `label on the cube: ${rc && rc.label_name} ${rc && JSON.stringify(rc.probabilities)}`);
  const shown = await page.locator("#readout").textContent();
  check(shown.includes(`(${rc.index.join(", ")})`) && shown.includes(`${rc.value} HU`) && shown.includes(name1), `readout text: ${shown}`);
  const ra = await readout(...at(0.01, 0.01));
  check(ra && ra.value === -1000 && ra.value === hu(ra.index), `readout on the air: ${ra && ra.index} ${ra && ra.value}`);
  await page.selectOption("#ovl", "labels");
  await page.mouse.move(cube.x, cube.y);
  await page.waitForTimeout(1500);
  await shot("05-readout-classified");
  await page.selectOption("#ovl", "");
  // Bad coordinates are refused.
  const bad = await page.evaluate(async () => { const r = await fetch(`/api/sessions/${S.id}/voxel/48/0/0`); return [r.status, (await r.json()).error]; });
  check(bad[0] === 400 && /outside/.test(bad[1]), `a voxel outside the volume: ${bad}`);

  // 7. The brush outline at its true size: radius 3 voxels, 0.8 mm across and 2 mm down in the
  // coronal view (an ellipse 2.5 times as tall as wide).
  await page.evaluate(() => { const b = document.getElementById("brush"); b.value = 3; b.dispatchEvent(new Event("input")); });
  const by = await canvasBox("y"), ry = await page.evaluate(() => viewRect("y"));
  const cx = by.x + ry.x + ry.w * 0.5, cy = by.y + ry.y + ry.h * 0.5;
  await page.mouse.move(cx - 3, cy); await page.mouse.move(cx, cy);
  await page.waitForTimeout(300);
  await page.keyboard.press("c"); // crosshair off: only the brush outline on the layer
  await page.waitForTimeout(200);
  const ell = await page.evaluate(() => {
    const c = document.getElementById("ty"), d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data, k = c.getBoundingClientRect().width / c.width;
    let x0 = 1e9, x1 = -1, y0 = 1e9, y1 = -1;
    for (let y = 0; y < c.height; y++) for (let x = 0; x < c.width; x++) if (d[(y * c.width + x) * 4 + 3] > 60) { x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
    const r = viewRect("y");
    return { w: (x1 - x0) * k, h: (y1 - y0) * k, voxW: r.w / S.info.dims[0], voxH: r.h / S.info.dims[2], mm: document.getElementById("brushmm").textContent };
  });
  check(Math.abs(ell.w - 6 * ell.voxW) < Math.max(3, 0.15 * 6 * ell.voxW) && Math.abs(ell.h - 6 * ell.voxH) < Math.max(3, 0.15 * 6 * ell.voxH), `the coronal brush outline spans 2r voxels: ${JSON.stringify(ell)}`);
  check(ell.h / ell.w > 2.1 && ell.h / ell.w < 2.9, `the outline is an ellipse 2.5 times as tall as wide: ${(ell.h / ell.w).toFixed(2)}`);
  check(ell.mm === "vox = 2.4 × 6.0 mm", `brush size in mm: ${ell.mm}`);
  await shot("06-brush-coronal");
  await page.keyboard.press("c");

  // 8. applyUi, the persisted state, and the layout in other states.
  const ui = await page.evaluate(() => JSON.parse(JSON.stringify(S.ui)));
  check(ui.idx && ui.idx.x === p.x && ui.window === 400 && ui.level === 40 && ui.crosshair === true && ui.views && ui.views.z, `S.ui holds the viewer's settings: ${JSON.stringify(ui)}`);
  const applied = await page.evaluate(() => {
    S.ui = { ...S.ui, idx: { x: 3, y: 4, z: 99 }, window: 1500, level: -600, crosshair: false, views: { z: { zoom: 3, cx: 0.3, cy: 0.6 }, y: "junk" } };
    applyUi();
    return { idx: { ...S.idx }, win: document.getElementById("win").value, lev: document.getElementById("lev").value, cross: document.getElementById("cross").checked, vz: S.ui.views.z, vy: S.ui.views.y, label: document.getElementById("sz").textContent };
  });
  check(applied.idx.x === 3 && applied.idx.y === 4 && applied.idx.z === 29 && applied.win === "1500" && applied.lev === "-600" && !applied.cross && applied.vz.zoom === 3 && applied.vy.zoom === 1 && applied.label.startsWith("29 / 30"), `applyUi applied and sanitised: ${JSON.stringify(applied)}`);
  await page.waitForTimeout(1000);
  await shot("07-applied-ui");
  await page.evaluate(() => { S.ui.window = 400; S.ui.level = 40; S.ui.crosshair = true; S.ui.views = {}; S.ui.idx = { x: 34, y: 11, z: 20 }; applyUi(); });
  await page.locator("#recommend").click();
  await page.waitForFunction(() => document.querySelectorAll("#thumbs figure").length > 0, null, { timeout: 120000 }).catch(() => check(false, "recommended views arrived"));
  await page.waitForTimeout(1500);
  const f2 = await fits();
  check(f2.sw <= f2.iw && f2.sh <= f2.ih && f2.bottom <= f2.ih, `still fits 1280 x 800 with recommended views: ${JSON.stringify(f2)}`);
  await shot("08-recommended");
  // A reload brings the viewer's settings back (saved with the session, applied by applyUi).
  const lung = await page.evaluate(() => [...document.getElementById("wlpreset").options].find((o) => /lung/.test(o.textContent)).value);
  await page.selectOption("#wlpreset", lung);
  const bs = await canvasBox("y");
  await page.mouse.move(bs.x + bs.width / 2, bs.y + bs.height / 2);
  for (let i = 0; i < 3; i++) { await page.keyboard.down("Control"); await page.mouse.wheel(0, -100); await page.keyboard.up("Control"); }
  for (let i = 0; i < 3; i++) await page.keyboard.press("PageDown");
  await page.waitForTimeout(1500);
  const saved = await page.evaluate(() => ({ idx: { ...S.idx }, zoom: S.ui.views.y.zoom, cy: S.ui.views.y.cy }));
  await page.reload();
  await page.waitForFunction(() => S.info && S.info.volume === "viewer-ct.nii" && document.getElementById("status").textContent.includes(" x "), null, { timeout: 60000 }).catch(() => {});
  await page.waitForTimeout(1500);
  const back = await page.evaluate(() => ({ idx: { ...S.idx }, zoom: S.ui.views && S.ui.views.y && S.ui.views.y.zoom, cy: S.ui.views && S.ui.views.y && S.ui.views.y.cy, win: document.getElementById("win").value, lev: document.getElementById("lev").value, label: document.getElementById("sy").textContent }));
  check(JSON.stringify(back.idx) === JSON.stringify(saved.idx) && Math.abs(back.zoom - saved.zoom) < 1e-9 && Math.abs(back.cy - saved.cy) < 1e-9 && back.win === "1500" && back.lev === "-600" && back.label.startsWith(`${saved.idx.y} / 40`), `a reload restores slices, zoom, pan and window/level: ${JSON.stringify(saved)} -> ${JSON.stringify(back)}`);
  await shot("08b-reloaded");
  await page.setViewportSize({ width: 1680, height: 1050 });
  await page.waitForTimeout(1500);
  const f3 = await fits();
  check(f3.sw <= f3.iw && f3.sh <= f3.ih && f3.panes.every(([w, h], i) => w > f2.panes[i][0] + 100 && h > f2.panes[i][1] + 100), `the views grow with the window: ${JSON.stringify(f2.panes)} -> ${JSON.stringify(f3.panes)}`);
  const big = await bright("z");
  check(big.n > cube.n * 1.5, `the larger view repainted the slice larger (${cube.n} -> ${big.n} bright pixels)`);
  await shot("09-large-window");

  await browser.close();
  check(errors.length === 0, `page errors: ${errors}`);
  console.log(JSON.stringify({ failures }, null, 1));
  if (failures.length) process.exit(1);
})().catch((e) => { console.error(e); process.exit(1); });
