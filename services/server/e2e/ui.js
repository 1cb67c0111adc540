// End-to-end test of the browser UI in real headless Chromium (Debian's chromium, driven by
// playwright-core). Run by services/cli/tests/e2e.rs:
//   node ui.js URL SCREENSHOT
// Loads the page, draws scribbles for two classes, waits for classification, checks that the
// axial slice overlay and the 3-D image changed, edits class 1's transfer function and checks
// the 3-D image followed, and saves a screenshot.
const { chromium } = require("playwright-core");

const pixels = (page, sel) => page.evaluate((sel) => {
  const el = document.querySelector(sel);
  const c = document.createElement("canvas");
  c.width = el.naturalWidth || el.width; c.height = el.naturalHeight || el.height;
  const g = c.getContext("2d"); g.drawImage(el, 0, 0);
  return Array.from(g.getImageData(0, 0, c.width, c.height).data);
}, sel);
const changed = (a, b) => { let n = 0; for (let i = 0; i < Math.min(a.length, b.length); i += 4) if (Math.abs(a[i] - b[i]) + Math.abs(a[i + 1] - b[i + 1]) + Math.abs(a[i + 2] - b[i + 2]) > 30) n++; return n; };

(async () => {
  const [url, shot] = process.argv.slice(2);
  const browser = await chromium.launch({
    executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
    args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync"],
  });
  const page = await browser.newPage({ viewport: { width: 1400, height: 900 } });
  const errors = [];
  page.on("pageerror", (e) => errors.push(e.message));
  await page.goto(url);
  // 1. The page loads and opens the volume.
  await page.waitForFunction(() => document.getElementById("status").textContent.includes(" x "), null, { timeout: 60000 });
  await page.waitForFunction(() => document.getElementById("render").naturalWidth > 0, null, { timeout: 60000 });
  await page.waitForTimeout(1000);
  const sliceBefore = await pixels(page, "#cz");
  const renderBefore = await pixels(page, "#render");
  // 2. Scribbles for two classes: class 1 in the middle, background at the border.
  const box = await page.locator("#cz").boundingBox();
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
  // 3. Classification streams in and finishes.
  await page.waitForFunction(() => /classification done/.test(document.getElementById("status").textContent), null, { timeout: 120000 });
  await page.waitForTimeout(2500);
  // 4. The overlay and the 3-D image changed.
  const sliceAfter = await pixels(page, "#cz");
  const renderAfter = await pixels(page, "#render");
  const ds = changed(sliceBefore, sliceAfter), dr = changed(renderBefore, renderAfter);
  const fractions = await page.locator("#fractions").textContent();
  // 5. The transfer-function editor: class 1 fully opaque from probability 0.3 changes the 3-D view.
  await page.selectOption("#tftarget", "p:1");
  const tfBox = await page.locator("#tfc").boundingBox();
  await page.mouse.click(tfBox.x + tfBox.width * (8 + 0.3 * 496) / 512, tfBox.y + tfBox.height * 10 / 200);
  await page.waitForFunction(() => (document.getElementById("status").textContent || "").length > 0);
  await page.waitForTimeout(2500);
  const renderTf = await pixels(page, "#render");
  const dt = changed(renderAfter, renderTf);
  // 6. Screenshot.
  await page.screenshot({ path: shot });
  await browser.close();
  console.log(JSON.stringify({ slice_pixels_changed: ds, render_pixels_changed: dr, tf_edit_pixels_changed: dt, fractions, errors }));
  if (ds < 50 || dr < 50 || dt < 50 || errors.length || !/background/.test(fractions)) process.exit(1);
})().catch((e) => { console.error(e); process.exit(1); });
