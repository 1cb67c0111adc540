// End-to-end test of the page's session plumbing and 3-D view in real headless Chromium
// (Debian's chromium, driven by playwright-core). Run by services/cli/tests/e2e.rs:
//   node session.js URL SHOTS_DIR
// The data root holds the phantom (opened first), `z-orientation-marker.nii` (bright walls
// meeting at the patient's right-anterior-superior corner) and `z-corner-marker.nii` (a bright
// cube in that corner only). Checks, in order:
//   1. the page opens a session and names it in its URL (?session=ID);
//   2. strokes, an undone stroke (redo), a class colour and the page's settings survive a
//      reload: same session id, strokes, redo stack, colour and settings;
//   3. a second tab on the same URL shows the same session, and its stroke reaches the first;
//      the bare URL resumes the newest session (only Open starts one);
//   4. after a burst of strokes, prior toggles and colour changes the 3-D image equals a fresh
//      render of the same state (at most MAX_STALE pixels differ by more than 30 in RGB);
//   5. dragging the 3-D view rotates it (azimuth and image change), the wheel zooms it;
//   6. the orientation marker draws its letters; the recommended views' thumbnails follow a
//      colour change; a transfer-function opacity edit changes the default labels view;
//   7. the Export menu closes after a choice and on a click elsewhere; scribbles export;
//   8. on the corner volume, from four views, the marker's R+A+S points toward the bright cube
//      in the render (cosine > 0.8); on the wall marker, the training preview's input half has
//      the bright corner where the axial view has it (top left, radiological) and its aspect.
// Screenshots go to SHOTS_DIR/session-*.png.
const { launch, pixels, changed } = require("./common");
const path = require("path");

const MAX_STALE = 20;
const failures = [];
const check = (ok, what) => { if (!ok) failures.push(what); console.log(`${ok ? "ok  " : "FAIL"} ${what}`); };

(async () => {
  const [url, shots] = process.argv.slice(2);
  const browser = await launch();
  const ctx = await browser.newContext({ viewport: { width: 1280, height: 860 } });
  let page = await ctx.newPage();
  const errors = [];
  const watch = (p) => p.on("pageerror", (e) => errors.push(e.message));
  watch(page);
  const shot = (name, p = page) => p.screenshot({ path: path.join(shots, `session-${name}.png`) });
  const opened = (p = page) => p.waitForFunction(() => / x /.test(document.getElementById("status").textContent) && S.id, null, { timeout: 60000 });
  // Nothing in flight, and no render asked for since: the 3-D view shows the latest state.
  const settled = async (p = page) => {
    await p.waitForFunction(() => !S.renderPending && !S.thumbsPending, null, { timeout: 60000 });
    let n = await p.evaluate(() => S.renders || 0);
    for (;;) {
      await p.waitForTimeout(1500);
      const m = await p.evaluate(() => (S.renderPending || S.thumbsPending ? -1 : S.renders || 0));
      if (m === n) return;
      n = m;
    }
  };
  const classified = (p = page) => p.waitForFunction(() => /classified the whole volume/.test(document.getElementById("status").textContent), null, { timeout: 120000 });
  const box = async (sel) => page.locator(sel).boundingBox();
  const draw = async (x0, y0, x1, y1) => {
    const b = await box("#cz");
    await page.mouse.move(b.x + b.width * x0, b.y + b.height * y0);
    await page.mouse.down();
    for (let i = 1; i <= 8; i++) await page.mouse.move(b.x + b.width * (x0 + (x1 - x0) * i / 8), b.y + b.height * (y0 + (y1 - y0) * i / 8));
    await page.mouse.up();
  };
  const setColor = async (i, hex) => {
    const el = page.locator("#classes input[type=color]").nth(i);
    await el.evaluate((e, v) => { e.value = v; e.dispatchEvent(new Event("change")); }, hex);
  };

  // 1. A new session, named in the URL.
  await page.goto(url);
  await opened();
  await page.waitForFunction(() => document.getElementById("render").naturalWidth > 0, null, { timeout: 60000 });
  const id = await page.evaluate(() => S.id);
  check(page.url().includes(`session=${encodeURIComponent(id)}`), `the URL names the session ${id}: ${page.url()}`);
  const header = await page.evaluate(() => { const h = document.querySelector("header"); return { scroll: h.scrollWidth, client: h.clientWidth, height: h.getBoundingClientRect().height }; });
  check(header.scroll <= header.client && header.height < 48, `header fits 1280 px on one line: ${JSON.stringify(header)}`);

  // 2. Strokes (one undone), a colour and settings; then a reload.
  await page.keyboard.press("1");
  await draw(0.45, 0.55, 0.55, 0.55);
  await page.keyboard.press("b");
  await draw(0.03, 0.03, 0.3, 0.03);
  await draw(0.2, 0.4, 0.35, 0.4);
  await page.keyboard.press("1");
  await draw(0.5, 0.2, 0.55, 0.25);
  await page.click("#undo");
  await classified();
  await setColor(0, "#ff00ff");
  await page.locator("#az").fill("75"); await page.locator("#az").dispatchEvent("input");
  await page.locator("#el").fill("-10"); await page.locator("#el").dispatchEvent("input");
  await page.selectOption("#ovl", "uncertainty");
  await page.locator("#vpcount").fill("2"); await page.locator("#vpcount").dispatchEvent("change");
  await page.locator("#epochs").fill("1.5"); await page.locator("#epochs").dispatchEvent("change");
  await page.check("#neuro");
  await page.keyboard.press("]"); await page.keyboard.press("]");
  await page.keyboard.press("2").catch(() => {});
  await page.keyboard.press("b");
  await page.waitForTimeout(1200);
  const before = await page.evaluate(() => ({ id: S.id, strokes: S.strokes.length, redo: S.redo.length, color: S.info.classes[0].color, az: $("az").value, el: $("el").value, ovl: $("ovl").value, vpcount: $("vpcount").value, epochs: $("epochs").value, neuro: $("neuro").checked, brush: $("brush").value, cls: S.cls }));
  await shot("01-before-reload");
  await page.reload();
  await opened();
  await page.waitForFunction(() => document.getElementById("render").naturalWidth > 0, null, { timeout: 60000 });
  const after = await page.evaluate(() => ({ id: S.id, strokes: S.strokes.length, redo: S.redo.length, color: S.info.classes[0].color, az: $("az").value, el: $("el").value, ovl: $("ovl").value, vpcount: $("vpcount").value, epochs: $("epochs").value, neuro: $("neuro").checked, brush: $("brush").value, cls: S.cls }));
  check(before.strokes === 3 && before.redo === 1, `before the reload: 3 strokes and 1 to redo: ${JSON.stringify(before)}`);
  check(JSON.stringify(before) === JSON.stringify(after), `a reload keeps the session, strokes, redo, colour and settings:\n  before ${JSON.stringify(before)}\n  after  ${JSON.stringify(after)}`);
  await shot("02-reloaded");

  // 3. A second tab on the same URL: the same session.
  const tab = await ctx.newPage(); watch(tab);
  await tab.goto(page.url());
  await opened(tab);
  const other = await tab.evaluate(() => ({ id: S.id, strokes: S.strokes.length, color: S.info.classes[0].color, az: $("az").value }));
  check(other.id === id && other.strokes === after.strokes && JSON.stringify(other.color) === JSON.stringify(after.color) && other.az === after.az, `a second tab shows the same session: ${JSON.stringify(other)}`);
  await shot("03-second-tab", tab);
  // A stroke drawn in the second tab reaches the first once classified.
  await tab.evaluate(() => { const z = S.idx.z; S.strokes.push({ class: 255, axis: "z", slice: z, points: [[2, 40], [10, 40]], radius: 1 }); S.redo = []; sendStrokes(); });
  const synced = await page.waitForFunction((n) => S.strokes.length === n, after.strokes + 1, { timeout: 90000 }).then(() => true).catch(() => false);
  check(synced, `a stroke from the second tab reaches the first (${await page.evaluate(() => S.strokes.length)} strokes)`);
  await tab.close();

  // 4. A burst of updates: the 3-D view ends on the latest state.
  await page.uncheck("#neuro");
  await page.keyboard.press("1");
  await draw(0.4, 0.6, 0.6, 0.62);
  await page.click("#prior");
  await setColor(0, "#00ffff");
  await page.keyboard.press("b");
  await draw(0.7, 0.2, 0.8, 0.25);
  await page.click("#prior");
  await setColor(0, "#ffaa00");
  await page.click("#prior");
  await classified();
  await settled();
  const shown = await pixels(page, "#render");
  const fresh = await page.evaluate(async () => {
    const cam = S.shownCam, id = S.id;
    // Another frame first, so the server draws this one from scratch, not from its last frame.
    await fetch(`/api/sessions/${id}/render?${renderQuery(cam, 128)}&t=${Date.now()}`);
    const i = new Image(); i.src = `/api/sessions/${id}/render?${renderQuery(cam, 400)}&t=${Date.now()}`; await i.decode();
    const c = document.createElement("canvas"); c.width = i.naturalWidth; c.height = i.naturalHeight;
    const g = c.getContext("2d"); g.drawImage(i, 0, 0);
    return { px: Array.from(g.getImageData(0, 0, c.width, c.height).data), cam: JSON.stringify(cam), now: JSON.stringify(camera()) };
  });
  const stale = changed(shown, fresh.px);
  check(fresh.cam === fresh.now, `the shown frame is of the current camera: ${fresh.cam} vs ${fresh.now}`);
  check(stale <= MAX_STALE, `after a burst the 3-D view equals a fresh render: ${stale} pixels differ (at most ${MAX_STALE})`);
  const burstColor = await page.evaluate(() => S.info.classes[0].color);
  check(JSON.stringify(burstColor) === "[255,170,0]", `the last colour holds: ${burstColor}`);
  await shot("04-burst");

  // 5. Drag rotates, the wheel zooms.
  const r0 = await pixels(page, "#render"), az0 = await page.locator("#az").inputValue();
  const rb = await box("#render");
  await page.mouse.move(rb.x + rb.width / 2, rb.y + rb.height / 2);
  await page.mouse.down();
  for (let i = 1; i <= 10; i++) await page.mouse.move(rb.x + rb.width / 2 + 8 * i, rb.y + rb.height / 2 + 2 * i);
  await page.mouse.up();
  await settled();
  const r1 = await pixels(page, "#render"), az1 = await page.locator("#az").inputValue();
  const dRot = changed(r0, r1);
  check(az1 !== az0 && dRot >= 50, `drag rotates: azimuth ${az0} -> ${az1}, ${dRot} pixels changed`);
  await shot("05-rotated");
  const z0 = +(await page.locator("#zoom").inputValue());
  await page.mouse.move(rb.x + rb.width / 2, rb.y + rb.height / 2);
  await page.mouse.wheel(0, -400);
  await settled();
  const r2 = await pixels(page, "#render"), z1 = +(await page.locator("#zoom").inputValue());
  const dZoom = changed(r1, r2);
  check(z1 > z0 && dZoom >= 50, `wheel zooms: ${z0} -> ${z1}, ${dZoom} pixels changed`);

  // 6. The orientation marker, the thumbnails after a colour change, TF opacity in labels mode.
  const marker = await page.evaluate(() => {
    const c = document.getElementById("orient"), d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 100) n++;
    return { letters: c.dataset.letters || "", inked: n };
  });
  check(["RL", "AP", "SI"].every((p) => [...p].some((t) => marker.letters.includes(t))) && marker.inked > 100, `the orientation marker is drawn with its letters: ${JSON.stringify(marker)}`);
  await page.click("#recommend");
  await page.waitForFunction(() => document.querySelectorAll("#thumbs figure").length === 2 && [...document.querySelectorAll("#thumbs img")].every((i) => i.complete && i.naturalWidth > 0), null, { timeout: 120000 });
  await settled();
  const thumbMarks = await page.evaluate(() => [...document.querySelectorAll("#thumbs canvas.orient")].map((c) => c.dataset.letters || ""));
  check(thumbMarks.length === 2 && thumbMarks.every((l) => l.length >= 4), `each thumbnail has its marker: ${JSON.stringify(thumbMarks)}`);
  const t0 = await pixels(page, "#thumbs img");
  await setColor(0, "#2040ff");
  await page.waitForTimeout(300);
  await settled();
  const t1 = await pixels(page, "#thumbs img");
  const dThumb = changed(t0, t1);
  check(dThumb >= 20, `a colour change re-renders the thumbnails: ${dThumb} pixels changed`);
  await shot("06-thumbs");
  check((await page.locator("#mode").inputValue()) === "labels", "the 3-D view is in labels mode");
  const targets = await page.evaluate(() => [...document.querySelectorAll("#tftarget option")].map((o) => o.value));
  check(!targets.some((t) => t.startsWith("p:")), `labels mode offers no probability maps: ${targets}`);
  const l0 = await pixels(page, "#render");
  await page.selectOption("#tftarget", "i:1");
  const tb = await box("#tfc");
  for (const x of [0.35, 0.65, 0.97]) { await page.mouse.click(tb.x + tb.width * (8 + x * 496) / 512, tb.y + tb.height * 190 / 200); await page.waitForTimeout(300); }
  await settled();
  const l1 = await pixels(page, "#render");
  const dTf = changed(l0, l1);
  check(dTf >= 50, `a class's opacity edit changes the labels view: ${dTf} pixels`);
  await shot("07-tf-labels");

  // 7. The Export menu closes after a choice and on a click elsewhere; scribbles export.
  await page.click("#exportmenu summary");
  check(await page.evaluate(() => $("exportmenu").open), "the Export menu opens");
  await page.click("#exportz");
  await page.waitForTimeout(300);
  check(!(await page.evaluate(() => $("exportmenu").open)), "the Export menu closes after a choice");
  await page.click("#exportmenu summary");
  await page.mouse.click(640, 600);
  await page.waitForTimeout(200);
  check(!(await page.evaluate(() => $("exportmenu").open)), "the Export menu closes on a click elsewhere");
  const scrib = await page.evaluate(async () => { const r = await fetch($("exports").href); return [r.status, (await r.arrayBuffer()).byteLength]; });
  check(scrib[0] === 200 && scrib[1] > 100, `the scribbles export: ${scrib}`);
  await page.click("#sessmenu summary");
  await page.waitForFunction(() => document.querySelectorAll("#sesslist button").length > 0, null, { timeout: 10000 }).catch(() => {});
  const listed = await page.evaluate(() => [...document.querySelectorAll("#sesslist button")].map((b) => b.dataset.id));
  check(listed.includes(id), `the Sessions menu lists ${id}: ${listed}`);
  await shot("08-sessions-menu");
  await page.mouse.click(640, 600);

  // 8. The corner volume (a new session by Open): the marker's R, A, S against the render.
  const openVolume = async (v) => {
    await page.selectOption("#volume", v);
    await page.evaluate(() => { document.getElementById("status").textContent = ""; });
    await page.click("#open");
    await opened();
  };
  await openVolume("z-corner-marker.nii");
  check((await page.evaluate(() => S.id)) !== id, "Open starts a new session");
  // The bare URL (no ?session) resumes the newest session and opens none: only Open does.
  const newest = await page.evaluate(() => S.id);
  const count = async () => page.evaluate(async () => (await (await fetch("/api/sessions")).json()).sessions.length);
  const before9 = await count();
  const bare = await ctx.newPage(); watch(bare);
  await bare.goto(url);
  await opened(bare);
  const got = await bare.evaluate(() => S.id);
  const after9 = await count();
  check(got === newest && after9 === before9, `the bare URL resumes the newest session (${got}, want ${newest}; sessions ${before9} -> ${after9})`);
  await bare.close();
  await page.selectOption("#mode", "intensity");
  for (const [az, el] of [[30, 20], [-120, 35], [150, -30], [80, 70]]) {
    await page.evaluate(([az, el]) => { $("az").value = az; $("el").value = el; $("zoom").value = 1; render(); }, [az, el]);
    await settled();
    const r = await page.evaluate(() => {
      const i = document.getElementById("render"), c = document.createElement("canvas");
      c.width = i.naturalWidth; c.height = i.naturalHeight; const g = c.getContext("2d"); g.drawImage(i, 0, 0);
      const d = g.getImageData(0, 0, c.width, c.height).data; let sx = 0, sy = 0, n = 0;
      for (let y = 0; y < c.height; y++) for (let x = 0; x < c.width; x++) { const k = (y * c.width + x) * 4; if (d[k] + d[k + 1] + d[k + 2] > 240) { sx += x; sy += y; n++; } }
      const ax = orientationAxes(S.shownCam.az, S.shownCam.el), v = ["R", "A", "S"].reduce((s, t) => [s[0] + ax[t].x, s[1] + ax[t].y], [0, 0]);
      const o = [sx / n - c.width / 2, sy / n - c.height / 2];
      return { n, offset: o, ras: v, cos: (o[0] * v[0] + o[1] * v[1]) / Math.hypot(...o) / Math.hypot(...v) };
    });
    check(r.n > 50 && r.cos > 0.8, `az ${az} el ${el}: the marker's R+A+S points toward the bright corner (cos ${r.cos.toFixed(2)}): ${JSON.stringify(r)}`);
  }
  await page.evaluate(() => { $("az").value = 30; $("el").value = 20; render(); });
  await settled();
  await shot("09-marker");
  // The training preview (every 40 steps: 8 epochs here) on the wall marker: its input half
  // is oriented like the axial view, the marker top left.
  await openVolume("z-orientation-marker.nii");
  await page.locator("#epochs").fill("8");
  await page.click("#train");
  await page.waitForFunction(() => document.getElementById("preview").naturalWidth > 0, null, { timeout: 180000 }).catch(() => {});
  const pv = await page.evaluate(() => {
    const i = document.getElementById("preview"); if (!i.naturalWidth) return null;
    const c = document.createElement("canvas"); c.width = i.naturalWidth; c.height = i.naturalHeight;
    const g = c.getContext("2d"); g.drawImage(i, 0, 0);
    const w = c.width / 2, d = g.getImageData(w, 0, w, c.height).data; let sx = 0, sy = 0, n = 0;
    for (let y = 0; y < c.height; y++) for (let x = 0; x < w; x++) if (d[(y * w + x) * 4] > 200) { sx += x; sy += y; n++; }
    const f = frame("z");
    return { cx: sx / n / w, cy: sy / n / c.height, n, aspect: w / c.height, view: f.W / f.H };
  });
  check(pv && pv.n > 0 && pv.cx < 0.5 && pv.cy < 0.5 && Math.abs(pv.aspect - pv.view) < 0.05, `the preview's input is oriented like the axial view (marker top left): ${JSON.stringify(pv)}`);
  await page.click("#stop").catch(() => {});
  await shot("10-preview");

  await browser.close();
  check(errors.length === 0, `page errors: ${errors}`);
  console.log(JSON.stringify({ id, stale, dRot, dZoom, dThumb, dTf, failures }, null, 1));
  if (failures.length) process.exit(1);
})().catch((e) => { console.error(e); process.exit(1); });
