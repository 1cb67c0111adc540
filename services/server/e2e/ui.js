// End-to-end test of the browser UI in real headless Chromium (Debian's chromium, driven by
// playwright-core). Run by services/cli/tests/e2e.rs:
//   node ui.js URL SHOTS_DIR SERVER_PID
// The data root holds the phantom (opened first) and `z-orientation-marker.nii`, an LPS-ordered
// volume with a bright marker on the patient's right, front and top. Checks, in order:
//   1. the page opens the phantom, its header fits 1280 px on one line, the favicon loads;
//   2. scribbles for two classes classify; the slice overlay and the 3-D view change, and the
//      3-D default draws the labels: class colour where the labels are, not a box-filling fog;
//   3. a class rename reaches the transfer-function editor and the fractions; the exported
//      labels, the fractions (API and table) and the axial overlay agree, prior on and off;
//      four recommended views arrive, each captioned with the reason it was picked;
//   4. a burst of updates paints a view once;
//   5. an edit of class 1's transfer function changes the 3-D view (probability mode);
//   6. the marker volume: each view's bright corner and edge letters where the radiological
//      convention puts them, pixels scaled by voxel spacing; then the neurological toggle;
//   7. the server killed: the page shows that it is disconnected.
// A screenshot of each state goes to SHOTS_DIR.
const { launch, pixels, changed } = require("./common");
const path = require("path");

const failures = [];
const check = (ok, what) => { if (!ok) failures.push(what); };

(async () => {
  const [url, shots, pid] = process.argv.slice(2);
  const shot = (name) => page.screenshot({ path: path.join(shots, name + ".png") });
  const browser = await launch();
  const page = await browser.newPage({ viewport: { width: 1280, height: 860 } });
  const errors = [], missing = [];
  page.on("pageerror", (e) => errors.push(e.message));
  page.on("response", (r) => { if (r.status() === 404) missing.push(r.url()); });
  await page.goto(url);
  // 1. The page loads and opens the phantom.
  const opened = () => page.waitForFunction(() => document.getElementById("status").textContent.includes(" x "), null, { timeout: 60000 });
  await opened();
  await page.waitForFunction(() => document.getElementById("render").naturalWidth > 0, null, { timeout: 60000 });
  await page.waitForTimeout(1000);
  const header = await page.evaluate(() => { const h = document.querySelector("header"); return { scroll: h.scrollWidth, client: h.clientWidth, height: h.getBoundingClientRect().height }; });
  check(header.scroll <= header.client && header.height < 48, `header fits 1280 px on one line: ${JSON.stringify(header)}`);
  const icon = await page.evaluate(async () => { const r = await fetch("/favicon.svg"); return [r.status, r.headers.get("content-type")]; });
  check(icon[0] === 200 && /svg/.test(icon[1]), `favicon: ${icon}`);
  await shot("01-opened");
  const sliceBefore = await pixels(page, "#cz");
  const renderBefore = await pixels(page, "#render");
  // 2. Scribbles for two classes in the axial view: class 1 on the bright column in the middle,
  // background on the air at the border and on the soft tissue.
  // The axial slice's rectangle on the page (each view fits its slice into its pane).
  const cbox = await page.locator("#cz").boundingBox(), vr = await page.evaluate(() => viewRect("z"));
  const box = { x: cbox.x + vr.x, y: cbox.y + vr.y, width: vr.w, height: vr.h };
  const draw = async (x0, y0, x1, y1) => {
    await page.mouse.move(box.x + box.width * x0, box.y + box.height * y0);
    await page.mouse.down();
    for (let i = 1; i <= 10; i++) await page.mouse.move(box.x + box.width * (x0 + (x1 - x0) * i / 10), box.y + box.height * (y0 + (y1 - y0) * i / 10));
    await page.mouse.up();
  };
  await page.keyboard.press("1");
  await draw(0.45, 0.55, 0.55, 0.55);
  await page.keyboard.press("b");
  await draw(0.03, 0.03, 0.3, 0.03);
  // Background on the soft tissue too, so class 1 is the bright column, not the whole body.
  await draw(0.2, 0.4, 0.35, 0.4);
  await page.waitForFunction(() => /classified the whole volume/.test(document.getElementById("status").textContent), null, { timeout: 120000 });
  await page.waitForTimeout(2500);
  const sliceAfter = await pixels(page, "#cz");
  const renderAfter = await pixels(page, "#render");
  const ds = changed(sliceBefore, sliceAfter), dr = changed(renderBefore, renderAfter);
  check(ds >= 50, `slice overlay changed (${ds} pixels)`);
  check(dr >= 50, `3-D view changed (${dr} pixels)`);
  const mode = await page.locator("#mode").inputValue();
  check(mode === "labels", `the 3-D view defaults to the labels (${mode})`);
  // The labels in class 1's colour cover part of the frame, not all of it (a fog covers all).
  const classRgb = await page.evaluate(() => S.info.classes[0].color);
  const labelShare = (() => { let n = 0, m = 0; for (let i = 0; i < renderAfter.length; i += 4) { m++; const d = Math.abs(renderAfter[i] - classRgb[0]) + Math.abs(renderAfter[i + 1] - classRgb[1]) + Math.abs(renderAfter[i + 2] - classRgb[2]); if (d < 120 && renderAfter[i + 2] + renderAfter[i] + renderAfter[i + 1] > 90) n++; } return n / m; })();
  check(labelShare > 0.001 && labelShare < 0.3, `class colour covers ${(100 * labelShare).toFixed(2)} % of the 3-D view`);
  const fractions = await page.locator("#fractions").textContent();
  check(/background/.test(fractions), `fractions list the background: ${fractions}`);
  await shot("02-classified");
  // 3. Renaming class 1 reaches the TF editor's targets and the fractions.
  await page.locator("#classes input[type=text]").first().fill("spine");
  await page.locator("#classes input[type=text]").first().dispatchEvent("change");
  await page.waitForFunction(() => [...document.querySelectorAll("#tftarget option")].some((o) => o.textContent.startsWith("spine:")), null, { timeout: 10000 }).catch(() => check(false, "rename reached the TF editor"));
  await page.waitForFunction(() => /spine/.test(document.getElementById("fractions").textContent), null, { timeout: 10000 }).catch(() => check(false, "rename reached the fractions"));
  // 3b. One label truth, with the spatial prior on and off: the exported labels, the class
  // fractions (API and table) and the axial overlay count the same class-1 voxels.
  const truth = () => page.evaluate(async () => {
    const id = S.id, d = S.info.dims, z = S.idx.z, n = d[0] * d[1];
    const fr = await (await fetch(`/api/sessions/${id}/fractions`)).json();
    const gz = await fetch(`/api/sessions/${id}/export/labels.nii.gz`);
    const buf = await new Response(gz.body.pipeThrough(new DecompressionStream("gzip"))).arrayBuffer();
    const dv = new DataView(buf);
    const off = dv.getInt32(0, true) === 540 ? Number(dv.getBigInt64(168, true)) : dv.getFloat32(108, true);
    const vox = new Uint8Array(buf, off, n * d[2]);
    let all = 0, slice = 0;
    for (let i = 0; i < vox.length; i++) if (vox[i] === 1) { all++; if (i >= z * n && i < (z + 1) * n) slice++; }
    const img = new Image(); img.src = `/api/sessions/${id}/overlay/z/${z}?kind=labels&t=${Date.now()}`; await img.decode();
    const c = document.createElement("canvas"); c.width = img.width; c.height = img.height;
    const g = c.getContext("2d"); g.drawImage(img, 0, 0);
    const px = g.getImageData(0, 0, c.width, c.height).data; let overlay = 0;
    for (let i = 3; i < px.length; i += 4) if (px[i] > 0) overlay++;
    const f = (fr.classes.find((k) => k.id === 1) || { fraction: 0 }).fraction;
    return { prior: fr.prior, all, slice, overlay, fromFractions: Math.round(f * fr.classified_voxels), percent: (100 * f).toFixed(2), table: document.getElementById("fractions").textContent };
  });
  const agree = (t, what) => {
    check(t.all > 0 && t.all === t.fromFractions, `${what}: exported class-1 voxels ${t.all} = fractions ${t.fromFractions}`);
    check(t.slice === t.overlay, `${what}: axial overlay pixels ${t.overlay} = exported class-1 voxels on the slice ${t.slice}`);
    check(t.table.includes(t.percent + "%"), `${what}: the table shows ${t.percent} %: ${t.table}`);
  };
  const on = await truth();
  check(on.prior === true, "the prior is on by default");
  agree(on, "prior on");
  await page.locator("#prior").uncheck();
  await page.waitForFunction((p) => document.getElementById("fractions").textContent !== p, on.table, { timeout: 10000 }).catch(() => {});
  await page.waitForTimeout(1500);
  const off = await truth();
  check(off.prior === false, "the prior is off after the toggle");
  agree(off, "prior off");
  console.log(`class 1 voxels: prior on ${on.all}, off ${off.all}`);
  await shot("02b-prior-off");
  await page.locator("#prior").check();
  await page.waitForTimeout(1500);
  // 3c. Recommended views: the number asked for, each captioned with why it was picked, and
  // thumbnails that are not blank.
  await page.locator("#recommend").click();
  await page.waitForFunction(() => document.querySelectorAll("#thumbs figure").length > 0, null, { timeout: 120000 }).catch(() => check(false, "recommended views arrived"));
  await page.waitForFunction(() => [...document.querySelectorAll("#thumbs img")].every((i) => i.complete && i.naturalWidth > 0), null, { timeout: 60000 }).catch(() => check(false, "thumbnails loaded"));
  const recs = await page.evaluate(() => [...document.querySelectorAll("#thumbs figure")].map((f) => f.querySelector("figcaption").textContent));
  check(recs.length === 4, `4 recommended views (got ${recs.length})`);
  check(recs.every((c) => c.length > 10), `each view says why it was picked: ${JSON.stringify(recs)}`);
  const thumbLit = await page.evaluate(() => {
    const i = document.querySelector("#thumbs img"), c = document.createElement("canvas");
    c.width = i.naturalWidth; c.height = i.naturalHeight; const g = c.getContext("2d"); g.drawImage(i, 0, 0);
    const d = g.getImageData(0, 0, c.width, c.height).data; let n = 0;
    for (let k = 0; k < d.length; k += 4) if (d[k] + d[k + 1] + d[k + 2] > 60) n++;
    return n / (d.length / 4);
  });
  check(thumbLit > 0.02, `the first thumbnail shows something (${(100 * thumbLit).toFixed(1)} % lit)`);
  console.log(`recommended views: ${JSON.stringify(recs)}`);
  await shot("02c-views");
  // 4. A burst of three updates of the axial view paints it once.
  const paints = await page.evaluate(async () => {
    const c = document.getElementById("cz"), g = c.getContext("2d"); let n = 0;
    const orig = g.clearRect.bind(g); g.clearRect = (...a) => { n++; return orig(...a); };
    drawSlice("z"); drawSlice("z"); drawSlice("z");
    await new Promise((r) => setTimeout(r, 1500));
    g.clearRect = orig; return n;
  });
  check(paints === 1, `three quick updates painted the axial view ${paints} times (want 1)`);
  // 5. The transfer-function editor: class 1 fully opaque from probability 0.3 changes the
  // probability view.
  await page.selectOption("#mode", "prob");
  await page.waitForTimeout(2500);
  const renderProb = await pixels(page, "#render");
  await page.selectOption("#tftarget", "p:1");
  const tfBox = await page.locator("#tfc").boundingBox();
  await page.mouse.click(tfBox.x + tfBox.width * (8 + 0.3 * 496) / 512, tfBox.y + tfBox.height * 10 / 200);
  await page.waitForTimeout(2500);
  const renderTf = await pixels(page, "#render");
  const dt = changed(renderProb, renderTf);
  check(dt >= 50, `TF edit changed the 3-D view (${dt} pixels)`);
  await shot("03-tf-edited");
  // 6. Orientation on the marker volume.
  await page.selectOption("#volume", "z-orientation-marker.nii");
  await page.evaluate(() => { document.getElementById("status").textContent = ""; });
  await page.click("#open");
  await opened();
  await page.waitForTimeout(1500);
  const views = () => page.evaluate(() => {
    const out = {};
    for (const a of ["x", "y", "z"]) {
      // The slice is the grey pixels (the pane around it is not grey); the marker's centroid
      // is taken relative to the slice's rectangle.
      const c = document.getElementById("c" + a), g = c.getContext("2d"), d = g.getImageData(0, 0, c.width, c.height).data;
      let sx = 0, sy = 0, n = 0, x0 = 1e9, x1 = -1, y0 = 1e9, y1 = -1;
      for (let y = 0; y < c.height; y++) for (let x = 0; x < c.width; x++) {
        const i = (y * c.width + x) * 4;
        if (d[i] === d[i + 1] && d[i + 1] === d[i + 2] && d[i + 3] === 255) { x0 = Math.min(x0, x); x1 = Math.max(x1, x); y0 = Math.min(y0, y); y1 = Math.max(y1, y); }
        if (d[i] > 200) { sx += x; sy += y; n++; }
      }
      const w = x1 - x0 + 1, h = y1 - y0 + 1;
      const v = c.closest(".view"), t = (k) => v.querySelector(".m" + k).textContent;
      out[document.getElementById("n" + a).textContent.split(" ")[0]] = { w, h, cx: (sx / n - x0) / w, cy: (sy / n - y0) / h, letters: t("l") + t("r") + t("t") + t("b") };
    }
    return out;
  });
  const corner = (v, left) => (left ? v.cx < 0.5 : v.cx > 0.5) && v.cy < 0.5;
  const rad = await views();
  check(rad.axial && corner(rad.axial, true) && rad.axial.letters === "RLAP", `radiological axial: marker top-left, letters R L A P: ${JSON.stringify(rad.axial)}`);
  check(rad.coronal && corner(rad.coronal, true) && rad.coronal.letters === "RLSI", `radiological coronal: marker top-left, letters R L S I: ${JSON.stringify(rad.coronal)}`);
  check(rad.sagittal && corner(rad.sagittal, true) && rad.sagittal.letters === "APSI", `sagittal: marker top-left, letters A P S I: ${JSON.stringify(rad.sagittal)}`);
  // 40 x 48 x 32 voxels of 2 x 1.5 x 3 mm: 80 x 72 mm axial, 80 x 96 coronal, 72 x 96 sagittal.
  const aspect = (v, want) => v && Math.abs(v.w / v.h - want) < 0.04;
  check(aspect(rad.axial, 80 / 72) && aspect(rad.coronal, 80 / 96) && aspect(rad.sagittal, 72 / 96), `pixels scaled by spacing: ${JSON.stringify(rad)}`);
  await shot("04-radiological");
  await page.check("#neuro");
  await page.waitForTimeout(1500);
  const neu = await views();
  check(neu.axial && corner(neu.axial, false) && neu.axial.letters === "LRAP", `neurological axial: marker top-right, letters L R A P: ${JSON.stringify(neu.axial)}`);
  check(neu.coronal && corner(neu.coronal, false) && neu.coronal.letters === "LRSI", `neurological coronal: marker top-right: ${JSON.stringify(neu.coronal)}`);
  check(neu.sagittal && corner(neu.sagittal, true), `neurological sagittal unchanged: ${JSON.stringify(neu.sagittal)}`);
  await shot("05-neurological");
  await page.uncheck("#neuro");
  // 7. The server goes away: the page says so.
  if (pid) {
    process.kill(+pid, "SIGKILL");
    await page.waitForFunction(() => document.querySelector("header").classList.contains("offline"), null, { timeout: 20000 }).catch(() => check(false, "disconnected state shown"));
    await shot("06-disconnected");
  }
  await browser.close();
  const notFound = missing.filter((u) => !/\/api\//.test(u));
  check(errors.length === 0, `page errors: ${errors}`);
  check(notFound.length === 0, `404s: ${notFound}`);
  console.log(JSON.stringify({ slice_pixels_changed: ds, render_pixels_changed: dr, tf_edit_pixels_changed: dt, label_share: labelShare, paints, header, radiological: rad, neurological: neu, fractions, failures }, null, 1));
  if (failures.length) process.exit(1);
})().catch((e) => { console.error(e); process.exit(1); });
