// Helpers shared by the browser tests (ui.js, session.js, viewer.js).
"use strict";
const { chromium } = require("playwright-core");

// Debian's Chromium, headless, with no network beyond the page's own server.
const launch = () => chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync"],
});

// The RGBA pixels of an <img> or <canvas> in the page.
const pixels = (page, sel) => page.evaluate((sel) => {
  const el = document.querySelector(sel);
  const c = document.createElement("canvas");
  c.width = el.naturalWidth || el.width; c.height = el.naturalHeight || el.height;
  const g = c.getContext("2d"); g.drawImage(el, 0, 0);
  return Array.from(g.getImageData(0, 0, c.width, c.height).data);
}, sel);

// Pixels whose RGB differs by more than 30 in sum, plus any difference in size.
const changed = (a, b) => {
  let n = 0;
  for (let i = 0; i < Math.min(a.length, b.length); i += 4) {
    if (Math.abs(a[i] - b[i]) + Math.abs(a[i + 1] - b[i + 1]) + Math.abs(a[i + 2] - b[i + 2]) > 30) n++;
  }
  return n + Math.abs(a.length - b.length) / 4;
};

module.exports = { launch, pixels, changed };
