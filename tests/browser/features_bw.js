// By hand, not part of CI: what the page's tracked-features overlay costs
// on the wire. Opens the operator page in headless Chromium, switches the
// overlay on and counts, for SECONDS, the bytes (headers and bodies) of its
// requests: GET /api/v1/features and the frames' pictures. Prints one JSON
// line (kB per minute of each, and the frames drawn). Started by
// tests/browser/measure_page.sh, or:
//
//   node tests/browser/features_bw.js http://127.0.0.1:8080/ 60
//
// Environment: SHOTPILOT_CHROMIUM (default /usr/bin/chromium).
'use strict';

const { chromium } = require('playwright-core');

(async () => {
  const url = process.argv[2], seconds = Number(process.argv[3] || 60);
  if (!url) throw new Error('usage: node features_bw.js URL [SECONDS]');
  const browser = await chromium.launch({
    executablePath: process.env.SHOTPILOT_CHROMIUM || '/usr/bin/chromium',
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-dev-shm-usage'],
  });
  try {
    const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
    await page.goto(url, { waitUntil: 'domcontentloaded' });
    const bytes = { features: 0, frames: 0 }, count = { features: 0, frames: 0 };
    let counting = false;
    page.on('requestfinished', async (req) => {
      if (!counting) return;
      const u = new URL(req.url()).pathname;
      const kind = /^\/api\/v1\/features\/\d+\/frame\.jpg$/.test(u) ? 'frames' : u === '/api/v1/features' ? 'features' : null;
      if (!kind) return;
      const s = await req.sizes();
      bytes[kind] += s.responseBodySize + s.responseHeadersSize + s.requestHeadersSize;
      count[kind]++;
    });
    await page.check('#featurestoggle');
    await page.waitForFunction(() => document.getElementById('features').dataset.state === 'drawn', null, { timeout: 60000 });
    const seq0 = Number(await page.$eval('#features', (c) => c.dataset.seq));
    counting = true;
    const t0 = Date.now();
    await page.waitForTimeout(seconds * 1000);
    counting = false;
    const min = (Date.now() - t0) / 60000;
    const last = await page.$eval('#features', (c) => ({ seq: Number(c.dataset.seq), counts: JSON.parse(c.dataset.counts), drawn: JSON.parse(c.dataset.drawn) }));
    console.log(JSON.stringify({
      seconds, features_kb_per_min: +(bytes.features / 1e3 / min).toFixed(1), frames_kb_per_min: +(bytes.frames / 1e3 / min).toFixed(1),
      features_replies: count.features, frames_drawn: count.frames, frames_advanced: last.seq - seq0, last,
    }));
  } finally {
    await browser.close();
  }
})().catch((e) => { console.error(e); process.exit(1); });
