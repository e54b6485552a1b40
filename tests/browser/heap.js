// The operator page's JS heap (after a forced GC) and DOM size at 1 minute
// and every 5 minutes up to MINUTES, in headless Chromium; one JSON line
// per look. Run by hand against a running daemon (not part of CI), e.g.
// from tests/browser/measure_page.sh:
//
//   node tests/browser/heap.js http://127.0.0.1:8080/ 30
//
// Environment: SHOTPILOT_CHROMIUM (default /usr/bin/chromium),
// SHOTPILOT_FEATURES=1 (the tracked-features overlay on).
'use strict';

const { chromium } = require('playwright-core');

(async () => {
  const url = process.argv[2], minutes = Number(process.argv[3] || 30);
  if (!url) throw new Error('usage: node heap.js URL [MINUTES]');
  const browser = await chromium.launch({
    executablePath: process.env.SHOTPILOT_CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-dev-shm-usage'],
  });
  try {
    const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
    const errors = [];
    page.on('pageerror', (e) => errors.push(String(e)));
    const cdp = await page.context().newCDPSession(page);
    await page.goto(url, { waitUntil: 'domcontentloaded' });
    // SHOTPILOT_FEATURES=1: with the tracked-features overlay on (it
    // loads a frame up to 5 times a second).
    if (process.env.SHOTPILOT_FEATURES === '1') await page.check('#featurestoggle');
    const t0 = Date.now();
    const marks = [1];
    for (let m = 5; m <= minutes; m += 5) marks.push(m);
    if (!marks.includes(minutes)) marks.push(minutes);
    for (const m of marks) {
      const wait = t0 + m * 60000 - Date.now();
      if (wait > 0) await new Promise((r) => setTimeout(r, wait));
      await cdp.send('HeapProfiler.collectGarbage');
      const h = await cdp.send('Runtime.getHeapUsage');
      const look = await page.evaluate(() => ({
        dom_nodes: document.getElementsByTagName('*').length,
        gallery: document.querySelectorAll('#gallery figure').length,
        keyframes: Number(document.getElementById('gallery').dataset.total || 0),
        loops: document.getElementById('b-loops').textContent,
        features: document.getElementById('features').dataset.state,
      }));
      console.log(JSON.stringify({ minute: m, used_mb: +(h.usedSize / 1048576).toFixed(2), total_mb: +(h.totalSize / 1048576).toFixed(2), ...look, page_errors: errors.length }));
    }
  } finally {
    await browser.close();
  }
})().catch((e) => { console.error(e); process.exit(1); });
