// Drives shotpilot's operator page in headless Chromium (playwright-core,
// Debian's chromium) against a running daemon; started by tests/suite/browser.rs.
//
// Environment: SHOTPILOT_URL (the daemon, e.g. http://127.0.0.1:8080),
// SHOTPILOT_TOKEN (bearer token, optional), SHOTPILOT_CHROMIUM (browser
// executable, default /usr/bin/chromium), SHOTPILOT_SCREENSHOT (PNG path).
//
// Checks, each failing the run with a message: live video shows (the MJPEG
// <img> has a size and its pixels change between two looks); keyframes are
// listed with their images in a bounded gallery (the newest few and those
// shots use; another opens by its number); a chosen keyframe opens in the
// anchor editor;
// the four anchors, dragged with the mouse, land where they were dropped;
// the preview shows the warped shot; submitting shows the daemon's answer
// (localised with pose and inliers, or not localised with its reason) and
// the desired-shot image; the shots panel lists every shot with its
// refinement rounds and stop reason; the world map draws the vehicle
// (data-vehicle-ned, compared with the simulator's truth by the caller);
// clicking a keyframe on the map chooses it; a whole shot is flown with at
// least one correction round on its timeline (with the localisation's
// sigma, and each correction's flight with the distance it began at);
// Stop (reached by keyboard) is acknowledged by the vehicle; the
// loops-closed badge, the loops drawn on the map and its list of map
// events; the tracked-features toggle (by keyboard) draws a tracked
// frame's keypoints in their states' colours, as the API describes that
// frame. A screenshot of each stage is saved beside SHOTPILOT_SCREENSHOT.
// Prints one JSON line of what it saw.
'use strict';

const { chromium } = require('playwright-core');

const BASE = process.env.SHOTPILOT_URL;
const TOKEN = process.env.SHOTPILOT_TOKEN || '';
const EXE = process.env.SHOTPILOT_CHROMIUM || '/usr/bin/chromium';
const SHOT = process.env.SHOTPILOT_SCREENSHOT || 'operator_page.png';

const GALLERY = 3;
const FEATURE_STATES_T = ['inlier', 'outlier', 'unmatched'];

function check(cond, msg) {
  if (!cond) throw new Error('check failed: ' + msg);
}

// A small hash of the live <img>'s current pixels (drawn into a canvas).
async function videoLook(page) {
  return page.evaluate(() => {
    const img = document.getElementById('video');
    const w = img.naturalWidth, h = img.naturalHeight;
    if (!w || !h) return { w, h, hash: null };
    const c = document.createElement('canvas');
    c.width = 160; c.height = 120;
    const g = c.getContext('2d');
    g.drawImage(img, 0, 0, c.width, c.height);
    const d = g.getImageData(0, 0, c.width, c.height).data;
    let hash = 2166136261, sum = 0;
    for (let i = 0; i < d.length; i += 4) {
      hash = Math.imul(hash ^ d[i], 16777619) >>> 0;
      sum += d[i];
    }
    return { w, h, hash, mean: sum / (d.length / 4) };
  });
}

// A screenshot of one stage, beside SHOTPILOT_SCREENSHOT.
const stages = [];
async function stage(page, name, full = true) {
  const path = require('path');
  const file = path.join(path.dirname(SHOT), `stage_${String(stages.length + 1).padStart(2, '0')}_${name}.png`);
  await page.screenshot({ path: file, fullPage: full });
  stages.push(file);
}

async function main() {
  check(BASE, 'SHOTPILOT_URL is set');
  const t0 = Date.now();
  const browser = await chromium.launch({
    executablePath: EXE,
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-dev-shm-usage'],
  });
  const out = {};
  try {
    const page = await browser.newPage({ viewport: { width: 1400, height: 1300 } });
    const errors = [];
    page.on('pageerror', (e) => errors.push(String(e)));
    // A gallery of the newest 3 keyframes (and those shots use): the
    // bound is exercised with the few keyframes of the test's map.
    await page.goto(BASE + `/?kf_gallery=${GALLERY}`, { waitUntil: 'domcontentloaded' });
    if (TOKEN) await page.fill('#token', TOKEN);

    // Live video: a picture with a size, whose pixels change.
    await page.waitForFunction(() => document.getElementById('video').naturalWidth > 0, null, { timeout: 20000 });
    const first = await videoLook(page);
    let second = first;
    for (let i = 0; i < 40 && second.hash === first.hash; i++) {
      await page.waitForTimeout(250);
      second = await videoLook(page);
    }
    check(first.w === 640 && first.h === 480, `live video is 640x480, got ${first.w}x${first.h}`);
    check(first.mean > 5, `live video is not black (mean ${first.mean})`);
    check(second.hash !== first.hash, 'live video frames advance within 10 s');
    // The status line follows the daemon (server-sent events).
    await page.waitForFunction(() => /SLAM tracking/.test(document.getElementById('b-slam').textContent), null, { timeout: 20000 });
    // No broken-image placeholder before the first shot.
    check(await page.$eval('#shotimg', (i) => i.hidden), 'no desired-shot image element is shown before a shot');
    await stage(page, 'status');
    out.video = { width: first.w, height: first.h, frames_advance: true };

    // Tracked features over the video: the toggle, reached by keyboard,
    // draws the SLAM's keypoints of a tracked frame on that frame, each
    // in its state's colour; what the page drew is what the API says of
    // the same frame (counts per state, the keypoints shown, and the
    // colour under each keypoint).
    await page.focus('#featurestoggle');
    await page.keyboard.press('Space');
    check(await page.$eval('#featurestoggle', (t) => t.checked), 'the features toggle is switched on by keyboard');
    await page.waitForFunction(() => {
      const c = document.getElementById('features');
      return !c.hidden && c.dataset.state === 'drawn' && c.dataset.slam === 'tracking' && JSON.parse(c.dataset.counts).inlier > 0;
    }, null, { timeout: 30000 });
    const featuresLook = () => page.evaluate(async () => {
      // The canvas and its hooks first, in one go (no draw between).
      const c = document.getElementById('features');
      const seq = Number(c.dataset.seq), drawn = JSON.parse(c.dataset.drawn), counts = JSON.parse(c.dataset.counts), colors = JSON.parse(c.dataset.colors);
      const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
      const r = await fetch(`/api/v1/features?seq=${seq}`);
      if (!r.ok) return { seq, gone: r.status };
      const f = await r.json();
      const hex = (i) => '#' + [d[i], d[i + 1], d[i + 2]].map((v) => v.toString(16).padStart(2, '0')).join('');
      // Under each keypoint: its state's colour, or, where a keypoint of a
      // state drawn later (data-order) lies within its square's reach,
      // that one's colour.
      const order = JSON.parse(c.dataset.order);
      const pts = unpackFeatures(f.points).map((p) => ({ u: Math.round(p.x), v: Math.round(p.y), st: FEATURE_STATES[p.s] }));
      const coloured = { inlier: 0, outlier: 0, unmatched: 0 }, covered = { inlier: 0, outlier: 0, unmatched: 0 }, wrong = [];
      for (const p of pts) {
        const px = hex((p.v * c.width + p.u) * 4);
        const over = pts.filter((q) => order.indexOf(q.st) > order.indexOf(p.st) && Math.abs(q.u - p.u) <= FEATURE_HALF && Math.abs(q.v - p.v) <= FEATURE_HALF);
        if (px === colors[p.st]) coloured[p.st]++;
        else if (over.some((q) => colors[q.st] === px)) covered[p.st]++;
        else wrong.push({ ...p, px });
      }
      return { seq, drawn, counts, colors, order, coloured, covered, wrong: wrong.slice(0, 10), size: [c.width, c.height], api: { seq: f.seq, state: f.state, counts: f.counts, shown: f.shown, width: f.width, height: f.height } };
    });
    let fl = await featuresLook();
    for (let i = 0; i < 5 && fl.gone; i++) fl = await featuresLook();
    check(!fl.gone, `the API still has the drawn frame's keypoints: ${JSON.stringify(fl)}`);
    const same = (a, b) => FEATURE_STATES_T.every((k) => a[k] === b[k]);
    check(fl.api.seq === fl.seq && fl.api.state === 'tracking', `the API's frame is the drawn one: ${JSON.stringify(fl)}`);
    check(same(fl.counts, fl.api.counts), `the counts per state are the API's: ${JSON.stringify(fl)}`);
    check(same(fl.drawn, fl.api.shown), `the keypoints drawn per state are those the API sent: ${JSON.stringify(fl)}`);
    const shown = fl.drawn.inlier + fl.drawn.outlier + fl.drawn.unmatched;
    check(shown > 0 && shown <= 500 && shown <= fl.api.counts.inlier + fl.api.counts.outlier + fl.api.counts.unmatched, `at most [server] features_max keypoints are drawn: ${JSON.stringify(fl)}`);
    check(fl.size[0] === fl.api.width && fl.size[1] === fl.api.height, `the canvas is the frame's size: ${JSON.stringify(fl)}`);
    // Every keypoint shows its state's colour, or that of a keypoint drawn
    // over it (the same corner found on two pyramid levels); those drawn
    // last always their own.
    for (const k of FEATURE_STATES_T) {
      check(fl.coloured[k] + fl.covered[k] === fl.drawn[k], `every ${k} keypoint is drawn in its colour or under a later one: ${JSON.stringify(fl)}`);
    }
    const top = fl.order[fl.order.length - 1];
    check(fl.wrong.length === 0 && fl.covered[top] === 0, `no keypoint shows another colour: ${JSON.stringify(fl)}`);
    out.features = fl;
    await page.$eval('#video', (v) => v.closest('.panel').scrollIntoView());
    await stage(page, 'features', false);
    await page.keyboard.press('Space');
    check(await page.$eval('#features', (c) => c.hidden && c.dataset.state === 'off'), 'the features toggle hides them again');
    out.status_line = await page.textContent('#status');

    // Keyframes listed, with their pictures. Bounded at 60 s: on a loaded
    // two-core CI run (daemon, simulator and Chromium together) this wait
    // once ran out at 20 s; the whole test takes 25 s alone.
    await page.waitForFunction(() => {
      const imgs = [...document.querySelectorAll('#gallery figure img')];
      return imgs.length >= 3 && imgs.every((i) => i.complete && i.naturalWidth > 0);
    }, null, { timeout: 60000 });
    // The gallery is bounded: the newest GALLERY keyframes and those the
    // shots use (the seeded shots' keyframe 0), in id order, as the daemon
    // lists them now. The map grows and culls while this looks: look again
    // (bounded) until one look agrees.
    const galleryLook = () => page.evaluate(async (n) => {
      const shown = [...document.querySelectorAll('#gallery figure')].map((f) => Number(f.dataset.id));
      const kfs = (await (await fetch('/api/v1/keyframes')).json()).keyframes.map((k) => k.id).sort((a, b) => a - b);
      const shots = (await (await fetch('/api/v1/shots')).json()).shots;
      const pins = new Set();
      for (const s of shots) {
        if (s.source && s.source.kind === 'anchors') pins.add(s.source.keyframe_id);
        if (s.localisation && s.localisation.keyframe_id != null) pins.add(s.localisation.keyframe_id);
      }
      const chosen = document.getElementById('editor').dataset.keyframe;
      if (chosen) pins.add(Number(chosen));
      const want = [...new Set([...kfs.slice(-n), ...kfs.filter((id) => pins.has(id))])].sort((a, b) => a - b);
      const g = document.getElementById('gallery');
      return { shown, want, total: kfs.length, pins: [...pins], page_total: Number(g.dataset.total), count: document.getElementById('kfcount').textContent, agree: JSON.stringify(shown) === JSON.stringify(want) };
    }, GALLERY);
    let gl = await galleryLook();
    for (let i = 0; i < 20 && !gl.agree; i++) { await page.waitForTimeout(500); gl = await galleryLook(); }
    check(gl.agree, `the gallery shows the newest ${GALLERY} keyframes and those shots use: ${JSON.stringify(gl)}`);
    check(gl.total > gl.shown.length, `the map has more keyframes than the gallery shows: ${JSON.stringify(gl)}`);
    check(gl.count === `(${gl.shown.length} of ${gl.page_total})`, `the count says what is shown: ${JSON.stringify(gl)}`);
    const ids = gl.shown;
    out.keyframes_listed = ids.length;
    // One the gallery does not show is reached by its number.
    const hiddenKf = await page.evaluate(() => state.keyframes.map((k) => k.id).find((id) => !document.querySelector(`#gallery figure[data-id="${id}"]`)));
    check(hiddenKf != null, 'a keyframe is not in the gallery');
    await page.fill('#kfgo', String(hiddenKf));
    await page.press('#kfgo', 'Enter');
    await page.waitForFunction((id) => document.getElementById('editor').dataset.keyframe === String(id), hiddenKf, { timeout: 10000 });
    check(await page.$eval(`#gallery figure[data-id="${hiddenKf}"]`, (f) => f.classList.contains('selected')), 'the keyframe opened by number joins the gallery, highlighted');
    out.gallery = { ...gl, opened_by_number: hiddenKf };

    // Choose the map's first keyframe: the SLAM never culls it, so it is
    // still there when the shot is submitted (a culled keyframe is refused
    // with unknown_keyframe, which the page shows as such).
    const kfId = Math.min(...ids);
    await page.click(`#gallery figure[data-id="${kfId}"]`);
    await page.waitForFunction((id) => document.getElementById('editor').dataset.keyframe === String(id), kfId, { timeout: 10000 });
    check(await page.$eval(`#gallery figure[data-id="${kfId}"]`, (f) => f.classList.contains('selected')), 'the chosen keyframe is highlighted');
    check(!(await page.isDisabled('#submit')), 'submit is enabled once a keyframe is chosen');
    out.keyframe = kfId;

    // Drags the four anchors of the keyframe in the editor; returns them.
    const dragAnchors = async () => {
      // Drag the four anchors (they start at 25 % / 75 % of the picture) out
      // to 5 % inside each corner: a shot a little closer than the keyframe,
      // which the daemon can localise (at 10 % its fit is just over the
      // 3 px reprojection gate, and the page then shows that refusal).
      await page.locator('#editor').scrollIntoViewIfNeeded();
      const look = () => page.$eval('#editor', (c) => {
        const r = c.getBoundingClientRect();
        return { left: r.left, top: r.top, cw: r.width, ch: r.height, w: c.width, h: c.height, anchors: JSON.parse(c.dataset.anchors) };
      });
      let ed = await look();
      const W = ed.w, H = ed.h;
      const targets = [[0.05 * W, 0.05 * H], [0.95 * W, 0.05 * H], [0.95 * W, 0.95 * H], [0.05 * W, 0.95 * H]];
      // Anchors are keyframe pixels with pixel centres at integers: canvas +0.5.
      const toClient = (p) => [ed.left + ((p[0] + 0.5) * ed.cw) / W, ed.top + ((p[1] + 0.5) * ed.ch) / H];
      const px = W / ed.cw; // one screen pixel in picture pixels
      const off = (a, i) => Math.hypot(a[i][0] - targets[i][0], a[i][1] - targets[i][1]);
      for (let i = 0; i < 4; i++) {
        // The page's layout can move while a drag runs (a status line
        // wraps): each drag starts from a fresh look at the editor, and
        // one that landed elsewhere is dragged again from where it is
        // (at most three times).
        for (let attempt = 0; attempt < 3; attempt++) {
          ed = await look();
          if (off(ed.anchors, i) <= 1.5 * px + 0.1) break;
          const [sx, sy] = toClient(ed.anchors[i]);
          const [tx, ty] = toClient(targets[i]);
          await page.mouse.move(sx, sy);
          await page.mouse.down();
          await page.mouse.move(tx, ty, { steps: 12 });
          await page.mouse.up();
        }
      }
      const anchors = await page.$eval('#editor', (c) => JSON.parse(c.dataset.anchors));
      for (let i = 0; i < 4; i++) {
        check(off(anchors, i) <= 1.5 * px + 0.1, `anchor ${i} dropped at (${anchors[i]}), wanted (${targets[i].map((v) => v.toFixed(1))})`);
      }
      // The live preview shows the warped picture (not black).
      const preview = await page.$eval('#preview', (c) => {
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let lit = 0;
        for (let i = 0; i < d.length; i += 4) if (d[i] + d[i + 1] + d[i + 2] > 30) lit++;
        return lit / (d.length / 4);
      });
      check(preview > 0.5, `preview is the warped shot (lit fraction ${preview.toFixed(2)})`);
      out.preview_lit_fraction = Number(preview.toFixed(3));

      return anchors;
    };
    // Submits the shot; returns the page's answer (with `lenient`, a
    // refusal such as a keyframe culled meanwhile is returned, not failed).
    const submitShot = async (lenient = false) => {
      // Submit and see the daemon's answer.
      const before = await page.$eval('#result', (r) => r.dataset.shotId || '');
      await page.click('#submit');
      await page.waitForFunction((before) => {
        const r = document.getElementById('result');
        return r.dataset.state === 'error' || (r.dataset.state !== 'idle' && r.dataset.state !== 'busy' && r.dataset.shotId !== before);
      }, before, { timeout: 60000 });
      const state = await page.$eval('#result', (r) => r.dataset.state);
      const text = await page.textContent('#result');
      if (lenient && state === 'error') return { id: null, state, text };
      check(state === 'localised' || state === 'not_localised', `a shot was created, page says: ${state}: ${text}`);
      const shotId = await page.$eval('#result', (r) => r.dataset.shotId);
      check(text.includes(`shot ${shotId}: ${state}`), `result names the shot: ${text}`);
      if (state === 'localised') {
        check(/camera at \(-?\d/.test(text) && /inliers \d+, rms error \d/.test(text), `a localised shot shows pose, inliers and error: ${text}`);
        check(!(await page.isDisabled('#upload')), 'upload is offered for a localised shot');
      } else {
        check(/reason: \S/.test(text), `a refused shot says why: ${text}`);
        check(await page.isDisabled('#upload'), 'upload is not offered for an unlocalised shot');
      }
      return { id: shotId, state, text };
    };
    out.anchors = await dragAnchors();
    const { id: shotId, state, text } = await submitShot();
    await page.waitForFunction(() => {
      const i = document.getElementById('shotimg');
      return i.complete && i.naturalWidth > 0;
    }, null, { timeout: 10000 });
    out.shot_image = await page.$eval('#shotimg', (i) => [i.naturalWidth, i.naturalHeight]);
    out.shot = { id: shotId, state, text };

    // The shots panel: the new shot, and every shot's refinement rounds and
    // stop reason as the page shows them (the Rust side compares them with
    // what the daemon stores).
    await page.waitForFunction((id) => !!document.querySelector(`#shots .shotcard[data-id="${id}"]`), shotId, { timeout: 10000 });
    out.shots_panel = await page.$$eval('#shots .shotcard', (cards) => cards.map((c) => {
      const stop = c.querySelector('.stop');
      return {
        id: c.dataset.id,
        head: c.querySelector('.head').textContent,
        rounds: [...c.querySelectorAll('.rounds tr[data-round]')].map((tr) => [...tr.children].map((td) => td.textContent)),
        stop: stop ? { key: stop.dataset.stop, text: stop.textContent } : null,
      };
    }));

    await page.screenshot({ path: SHOT, fullPage: true });
    out.screenshot = SHOT;

    // The world map: once georeferenced, north up in metres with the
    // vehicle drawn at its telemetry position (data-vehicle-ned).
    await page.waitForFunction(() => {
      const m = document.getElementById('map');
      return m.dataset.mode === 'world' && !!m.dataset.vehicleNed;
    }, null, { timeout: 120000 });
    out.map = await page.$eval('#map', (m) => ({ mode: m.dataset.mode, vehicle_ned: m.dataset.vehicleNed, scale_bar_m: Number(m.dataset.scaleBarM) }));
    await page.$eval('#map', (m) => m.scrollIntoView());
    await stage(page, 'map_world');
    // Clicking a keyframe on the map chooses it in the anchor editor.
    const mapPick = async (choose) => {
      // On the world map (a refit the georeference refused shows the SLAM
      // view until the next fit is accepted).
      try {
        await page.waitForFunction(() => document.getElementById('map').dataset.mode === 'world', null, { timeout: 60000 });
      } catch (e) {
        check(false, `the map is not georeferenced for 60 s: ${await page.textContent('#mapmode')}`);
      }
      const pick = await page.evaluate((choose) => {
        // Project the keyframes as they are now (a keyframe list or
        // georeference fetched since the last draw moves them).
        drawMap();
        const pr = state.mapProject, cv = document.getElementById('map');
        if (!pr || !pr.kfs.length) return null;
        const cur = document.getElementById('editor').dataset.keyframe;
        const veh = (cv.dataset.vehicleNed || '0,0').split(',').map(Number);
        let k;
        if (choose === 'other') k = pr.kfs.find((x) => String(x.id) !== cur) || pr.kfs[0];
        else if (choose === 'first') k = pr.kfs.reduce((a, b) => (b.id < a.id ? b : a));
        else {
          // The n-th keyframe farthest from the vehicle (a shot it must fly to).
          const far = [...pr.kfs].sort((a, b) => Math.hypot(b.p[0] - veh[0], b.p[1] - veh[1]) - Math.hypot(a.p[0] - veh[0], a.p[1] - veh[1]));
          k = far[Math.min(choose, far.length - 1)];
        }
        // Keyframes can lie close together (hovering, turning): centre the
        // view on this one and zoom until its nearest neighbour is 15 px
        // away, so the click cannot choose another (the view stays put
        // until the pick is done). A far keyframe may lie outside the view
        // an earlier pick left; after centring it must be drawn inside.
        const near = Math.min(...pr.kfs.filter((x) => x.id !== k.id).map((x) => Math.hypot(x.p[0] - k.p[0], x.p[1] - k.p[1])), 1e9);
        view.fit = false; view.pan = [k.p[0], k.p[1]];
        view.zoom = Math.min(Math.max(view.zoom, 15 / Math.max(near, 1e-4)), 2000);
        drawMap();
        const now = state.mapProject, drawn = now && now.kfs.find((x) => x.id === k.id);
        const [u, v] = drawn ? now.P(drawn.p[0], drawn.p[1]) : [-1, -1];
        const inside = u >= 0 && v >= 0 && u <= cv.width && v <= cv.height;
        return { id: k.id, inside, near_m: near, mode: cv.dataset.mode, found: !!drawn };
      }, choose);
      check(pick && pick.inside, `a keyframe is drawn on the map: ${JSON.stringify(pick)}`);
      await page.$eval('#map', (m) => m.scrollIntoView());
      const again = await page.evaluate((id) => {
        const pr = state.mapProject, cv = document.getElementById('map');
        const k = pr.kfs.find((x) => x.id === id);
        const [u, v] = pr.P(k.p[0], k.p[1]);
        const r = cv.getBoundingClientRect();
        return { x: r.left + u * r.width / cv.width, y: r.top + v * r.height / cv.height };
      }, pick.id);
      await page.mouse.click(again.x, again.y);
      await page.waitForFunction((id) => document.getElementById('editor').dataset.keyframe === String(id), pick.id, { timeout: 10000 });
      await page.evaluate(() => { view.fit = true; });
      return pick.id;
    };
    out.map_pick = await mapPick('other');

    // A whole shot: the first keyframe chosen on the map, anchors dragged,
    // submitted, uploaded, started; the timeline through arrival and a
    // refinement round, the outline overlay, the before/after view.
    const kfA = await mapPick('first');
    await dragAnchors();
    const shotA = await submitShot();
    check(shotA.state === 'localised', `the shot on keyframe ${kfA} is localised: ${shotA.text}`);
    const num = (v) => (v == null ? null : Number(v));
    const timeline = (id) => page.$$eval(`#timeline .tl[data-shot="${id}"] li`, (ls) => ls.map((l) => ({ kind: l.dataset.kind, round: l.dataset.round, error: l.dataset.error, sigma_pct: l.dataset.sigmaPct, sigma_deg: l.dataset.sigmaDeg, sigma_m: l.dataset.sigmaM, distance: l.dataset.distance, start: l.dataset.start, text: l.textContent })))
      .then((ls) => ls.map((l) => ({ ...l, round: num(l.round), error: num(l.error), sigma_pct: num(l.sigma_pct), sigma_deg: num(l.sigma_deg), sigma_m: num(l.sigma_m), distance: num(l.distance), start: num(l.start) })));
    // Uploads the shot's mission and waits for the daemon's answer: Start
    // offered, or the refusal shown (which fails the test with its text).
    const uploadMission = async (shot) => {
      await page.click('#upload');
      await page.waitForFunction(() => document.getElementById('result').dataset.state === 'error' || !document.getElementById('start').disabled, null, { timeout: 60000 });
      const text = await page.textContent('#result');
      check(!(await page.isDisabled('#start')), `the mission of shot ${shot.id} is uploaded, page says: ${text}`);
    };
    const waitKind = (id, kind, timeout) => page.waitForFunction(([id, kind]) => !!document.querySelector(`#timeline .tl[data-shot="${id}"] li[data-kind="${kind}"]`), [id, kind], { timeout });
    await uploadMission(shotA);
    await waitKind(shotA.id, 'uploaded', 10000);
    await page.click('#start');
    await waitKind(shotA.id, 'started', 30000);
    // The outline overlay while the loop runs (measured about once a second).
    await page.waitForFunction((id) => {
      const o = document.getElementById('overlay');
      return o.dataset.shot === id && o.dataset.state === 'outline';
    }, shotA.id, { timeout: 240000 });
    out.overlay = await page.$eval('#overlay', (o) => ({ state: o.dataset.state, shot: o.dataset.shot, corners: JSON.parse(o.dataset.corners), error: Number(o.dataset.error), visible: !o.hidden, info: document.getElementById('overlayinfo').textContent }));
    await page.$eval('#video', (v) => v.scrollIntoView());
    await stage(page, 'overlay');
    // The toggle hides and shows it.
    await page.click('#overlaytoggle');
    check(await page.$eval('#overlay', (o) => o.hidden), 'the overlay toggle hides the overlay');
    await page.click('#overlaytoggle');
    check(!(await page.$eval('#overlay', (o) => o.hidden)), 'the overlay toggle shows the overlay again');
    await waitKind(shotA.id, 'arrived', 240000);
    await waitKind(shotA.id, 'round', 240000);
    await page.$eval('#timeline', (t) => t.scrollIntoView());
    await stage(page, 'timeline_round');
    await page.waitForFunction((id) => {
      const l = document.querySelector(`#timeline .tl[data-shot="${id}"]`);
      return l && (l.dataset.last === 'done' || l.dataset.last === 'stopped');
    }, shotA.id, { timeout: 400000 });
    out.timeline_a = await timeline(shotA.id);
    await page.$eval(`#timeline .tl[data-shot="${shotA.id}"]`, (t) => t.scrollIntoView());
    await stage(page, 'timeline_corrected');
    // Before/after of the finished shot, and its PNG downloaded.
    await page.waitForFunction((id) => {
      const b = document.getElementById('beforeafter');
      return b.dataset.shot === id && ['ready', 'unavailable'].includes(b.dataset.state);
    }, shotA.id, { timeout: 30000 });
    out.before_after = await page.$eval('#beforeafter', (b) => ({
      state: b.dataset.state, shot: b.dataset.shot, error: b.dataset.error, title: document.getElementById('ba-title').textContent,
      images: ['ba-desired', 'ba-achieved', 'ba-under', 'ba-over'].map((i) => [document.getElementById(i).naturalWidth, document.getElementById(i).naturalHeight]),
    }));
    check(out.before_after.state === 'ready', `the before/after view shows: ${JSON.stringify(out.before_after)}`);
    // The slider fades the desired picture over the achieved frame.
    await page.$eval('#ba-slider', (s) => { s.value = '80'; s.dispatchEvent(new Event('input')); });
    const opacity = await page.$eval('#ba-over', (i) => Number(i.style.opacity));
    check(Math.abs(opacity - 0.2) < 1e-6, `the slider at 80 shows the desired picture at opacity 0.2, got ${opacity}`);
    await page.$eval('#beforeafter', (b) => b.scrollIntoView());
    await stage(page, 'before_after');
    const [download] = await Promise.all([page.waitForEvent('download', { timeout: 30000 }), page.click('#ba-download')]);
    const path = require('path');
    out.before_after_png = path.join(path.dirname(SHOT), `${shotA.id}_before_after.png`);
    await download.saveAs(out.before_after_png);
    out.shot_a = shotA;

    // A second shot, on a keyframe away from the vehicle; Stop while it
    // flies there: acknowledged, the shot stopped on its timeline.
    let shotB = null;
    for (let n = 0; n < 4 && !(shotB && shotB.state === 'localised'); n++) {
      await mapPick(n);
      await dragAnchors();
      shotB = await submitShot(true);
    }
    check(shotB.state === 'localised', `a second shot is localised: ${shotB.text}`);
    await uploadMission(shotB);
    await page.click('#start');
    await page.waitForFunction((id) => [...document.querySelectorAll(`#timeline .tl[data-shot="${id}"] li[data-kind="flying"]`)].some((l) => /flying, ([3-9]|\d\d+)\./.test(l.textContent)), shotB.id, { timeout: 120000 });
    await stage(page, 'flying_second_shot');
    await page.focus('#stop');
    await page.keyboard.press('Enter');
    await page.waitForFunction(() => ['ok', 'error'].includes(document.getElementById('stopresult').dataset.state), null, { timeout: 30000 });
    const stopText = await page.textContent('#stopresult');
    check(await page.$eval('#stopresult', (e) => e.dataset.state === 'ok' && e.dataset.ack === 'MAV_RESULT_ACCEPTED'), `the stop is acknowledged: ${stopText}`);
    check(stopText.includes(`${shotB.id} stopped`), `the stop names the shot flown: ${stopText}`);
    await waitKind(shotB.id, 'stopped', 10000);
    // Times on the daemon's clock (the simulator's truth is on it; on
    // simulated time it runs ahead of or behind this page's clock): the
    // stop as the shot recorded the vehicle's ACK, each marker sample and
    // the end of the sampling as the status says the daemon's time is.
    const daemonNow = () => page.evaluate(async () => (await (await fetch('/api/v1/status')).json()).now_unix);
    const stopped = await page.evaluate(async (id) => (await (await fetch(`/api/v1/shots/${id}`)).json()).mission.details.stop, shotB.id);
    out.stop = { text: stopText, at_unix: stopped.at_unix };
    out.timeline_b = await timeline(shotB.id);
    out.shot_b = shotB;
    await stage(page, 'stopped');
    // The marker while the vehicle holds: samples until 4 s of them lie
    // within 0.1 m (bounded), each with its time, compared with the
    // simulator's truth on the Rust side.
    const samples = [];
    // Why the marker was missing, when it was (the map's mode line).
    const missing = [];
    for (let i = 0; i < 80; i++) {
      const v = await page.$eval('#map', (m) => m.dataset.vehicleNed || '');
      const [n, e] = v.split(',').map(Number);
      const t = await daemonNow();
      if (Number.isFinite(n) && Number.isFinite(e)) samples.push({ t, n, e });
      else if (missing.length < 5) missing.push({ t, map: await page.textContent('#mapmode') });
      const recent = samples.filter((x) => x.t >= samples[samples.length - 1].t - 4);
      const spread = recent.length ? Math.max(...recent.map((x) => Math.hypot(x.n - recent[0].n, x.e - recent[0].e))) : Infinity;
      if (samples.length && samples[samples.length - 1].t - out.stop.at_unix > 8 && spread < 0.1) break;
      await page.waitForTimeout(500);
    }
    out.vehicle_samples = samples;
    out.vehicle_missing = missing;
    // When the sampling ended: the hold is judged on the simulator's truth
    // up to here (the marker is missing while the map shows the SLAM view).
    out.hold_end_unix = await daemonNow();
    await stage(page, 'holding');
    // Loops closed: the badge's count and the pairs the map drew, against
    // the status (compared on the Rust side); a loop closing between the
    // two looks is looked at again (bounded).
    const loopsLook = () => page.evaluate(async () => {
      const s = await (await fetch('/api/v1/status')).json();
      return {
        badge: document.getElementById('b-loops').textContent,
        drawn: JSON.parse(document.getElementById('map').dataset.loops || '[]'),
        events: [...document.querySelectorAll('#mapevents li[data-kind="loop"]')].map((li) => [Number(li.dataset.current), Number(li.dataset.loop)]),
        merge_events: [...document.querySelectorAll('#mapevents li[data-kind="merge"]')].map((li) => [Number(li.dataset.current), Number(li.dataset.merge)]),
        status: {
          loops_closed: s.slam.loops_closed, loops: s.slam.loops.map((l) => [l.current_kf, l.loop_kf]),
          merges_made: s.slam.merges_made, merges: s.slam.merges.map((m) => [m.current_kf, m.merge_kf]),
        },
      };
    });
    out.loops = await loopsLook();
    for (let i = 0; i < 10 && !out.loops.badge.startsWith(`${out.loops.status.loops_closed} loop`); i++) {
      await page.waitForTimeout(500);
      out.loops = await loopsLook();
    }
    // A merge as the status reports one (this flight keeps tracking, so
    // its status has none): the events list shows it beside the loops,
    // newest first, with its two keyframes as buttons; the next status
    // puts the list back.
    out.merge_render = await page.evaluate(() => {
      const sl = JSON.parse(JSON.stringify(state.status.slam));
      const at = Date.now() / 1000 + 3600;
      sl.merges = [{ current_kf: 41, merge_kf: 7, current_t: 20, merge_t: 3, from_map: 1, into_map: 0, inliers: 55, projection_matches: 120, scale: 1.02, keyframes_moved: 12, fused: 30, correction_ms: 8.5, at_unix: at }];
      renderMapEvents(sl);
      const first = document.querySelector('#mapevents li');
      const r = {
        kind: first.dataset.kind, current: first.dataset.current, merge: first.dataset.merge,
        buttons: [...first.querySelectorAll('button.kf')].map((b) => b.dataset.kf),
        text: first.textContent,
        loops_listed: document.querySelectorAll('#mapevents li[data-kind="loop"]').length,
      };
      renderMapEvents(state.status.slam);
      r.after = document.querySelectorAll('#mapevents li[data-kind="merge"]').length;
      return r;
    });
    {
      const m = out.merge_render;
      check(m.kind === 'merge' && m.current === '41' && m.merge === '7', `the newest event is the merge: ${JSON.stringify(m)}`);
      check(m.buttons.join(',') === '41,7', `the merge's keyframes are buttons: ${JSON.stringify(m)}`);
      check(/map 1 .*joined map 0/.test(m.text) && /12 keyframes moved/.test(m.text), `the merge says what joined what: ${m.text}`);
      check(m.loops_listed === out.loops.events.length, `the loops stay listed beside the merge: ${JSON.stringify(m)}`);
      check(m.after === out.loops.merge_events.length, `the status's own list is back: ${JSON.stringify(m)}`);
    }
    // Layouts: a laptop and a tablet.
    await page.setViewportSize({ width: 1280, height: 800 });
    await stage(page, 'laptop_1280x800', false);
    await page.setViewportSize({ width: 768, height: 1024 });
    await stage(page, 'tablet_768x1024', false);
    out.stages = stages;
    check(errors.length === 0, `no script errors on the page: ${errors.join('; ')}`);
    out.ms = Date.now() - t0;
  } finally {
    await browser.close();
  }
  console.log(JSON.stringify(out));
}

main().catch((e) => {
  console.error(String(e && e.stack ? e.stack : e));
  process.exit(1);
});
