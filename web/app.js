// shotpilot operator page: status, live video, map top view, keyframes,
// anchor editor with a live perspective-warp preview, shot submit, mission
// upload and start. Plain JS, no libraries.
'use strict';

const API = '/api/v1';
const $ = (id) => document.getElementById(id);
const state = {
  status: null, shots: [], mapProject: null,
  keyframes: [], kf: null, kfChosen: null, kfImage: null, anchors: null, drag: -1,
  shot: null, map: null, srcPixels: null,
};

// ---- token and requests -------------------------------------------------
$('token').value = localStorage.getItem('shotpilot.token') || '';
$('token').addEventListener('change', () => localStorage.setItem('shotpilot.token', $('token').value));

async function api(method, path, body) {
  const headers = {};
  const tok = $('token').value.trim();
  if (tok) headers['Authorization'] = 'Bearer ' + tok;
  if (body !== undefined) headers['Content-Type'] = 'application/json';
  const r = await fetch(API + path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  const text = await r.text();
  let data = null;
  try { data = text ? JSON.parse(text) : null; } catch (_) { data = { raw: text }; }
  if (!r.ok) {
    const msg = data && data.error ? `${data.error.code}: ${data.error.message}` : `HTTP ${r.status}`;
    throw new Error(msg);
  }
  return data;
}

// ---- status (server-sent events) -----------------------------------------
function badge(id, level, text) {
  const b = $(id);
  b.dataset.level = level; b.textContent = text; b.hidden = false;
}
function showStatus(s) {
  const v = s.video || {}, c = v.counters || {}, sl = s.slam || {}, ve = s.vehicle || {};
  state.status = s;
  // Badges: link, GPS fix, battery (when sent), SLAM state, georeference.
  if (ve.configured === false) badge('b-link', 'warn', 'no vehicle link');
  else if (ve.connected) badge('b-link', 'ok', `${ve.flavour || 'vehicle'} · ${ve.mode || '?'}${ve.armed ? ' · ARMED' : ''}`);
  else badge('b-link', 'bad', 'vehicle not heard');
  if (ve.position) badge('b-gps', 'ok', `GPS fix · ${ve.position.rel_alt_m.toFixed(1)} m`);
  else badge('b-gps', ve.configured === false ? 'warn' : 'bad', 'no GPS position');
  if (ve.battery && ve.battery.remaining_pct != null) {
    const pct = ve.battery.remaining_pct;
    badge('b-battery', pct > 30 ? 'ok' : pct > 15 ? 'warn' : 'bad', `battery ${pct.toFixed(0)} %`);
  }
  // A frame the telemetry posed (vision found too little) is tracking on
  // borrowed time: shown as a warning with how it was posed.
  const aided = sl.state === 'tracking' && sl.last_source && sl.last_source !== 'vision';
  const slamLevel = sl.state === 'tracking' && !aided ? 'ok' : (sl.state === 'initializing' || aided ? 'warn' : 'bad');
  const slamState = aided ? `${sl.state} (posed by ${sl.last_source})` : (sl.state || '?');
  badge('b-slam', slamLevel, `SLAM ${slamState} · ${sl.keyframes ?? 0} kf · ${sl.points ?? 0} pts`);
  const nl = sl.loops_closed ?? 0, nm = sl.merges_made ?? 0;
  badge('b-loops', nl || nm ? 'ok' : 'none', `${nl} loop${nl === 1 ? '' : 's'} closed${nm ? ` · ${nm} map${nm === 1 ? '' : 's'} merged` : ''}`);
  $('b-loops').title = [
    ...(sl.loops || []).map((l) => `loop: keyframe #${l.current_kf} joined #${l.loop_kf} (${l.inliers} inliers, scale ${fmt(l.scale, 3)}, ${fmt(l.rotation_deg, 2)}°)`),
    ...(sl.merges || []).map((m) => `merge: map ${m.from_map} joined map ${m.into_map} at keyframe #${m.current_kf} ~ #${m.merge_kf} (${m.keyframes_moved} keyframes moved)`),
  ].join('\n');
  const g = ve.georeference || {};
  if (g.state === 'ok') badge('b-geo', 'ok', `georef ok · rms ${(g.rms_m * 100).toFixed(1)} cm`);
  else badge('b-geo', g.state === 'waiting' ? 'warn' : 'bad', `georef ${g.state || 'none'}`);
  $('b-geo').title = geoText(g);
  // The line beside the badges: only what needs the operator's attention.
  const msgs = (linkText(v.link) + mapStartText(sl.map_start) + errorsText(s.errors) + (g.state && g.state !== 'ok' ? geoText(g) : ''))
    .split(' | ').map((x) => x.trim()).filter(Boolean);
  $('status').textContent = msgs.join(' · ');
  $('status').dataset.errors = String((s.errors || []).length);
  const src = v.source || {};
  $('videostats').textContent =
    (src.kind ? `${src.kind} ${src.url || ''} ${src.codec || ''}${src.transport ? '/' + src.transport : ''} · ` : '') +
    `${(v.decoded_fps || 0).toFixed(1)} fps · ${(v.bitrate_kbps || 0).toFixed(0)} kbit/s · ` +
    (v.link && v.link.frames ? `usable ${(v.link.usable_share * 100).toFixed(0)} % · ` : '') +
    `received ${c.received} · decoded ${c.decoded} · dropped ${c.dropped} · late ${c.late || 0} · skipped ${c.skipped || 0} · damaged ${c.damaged || 0} (masked ${((c.masked_share || 0) * 100).toFixed(1)} %) · lost pkts ${c.lost_packets || 0}${c.retransmit_asked ? ` (NACK ${c.retransmit_recovered}/${c.retransmit_asked})` : ""} · bad ${c.bad} · reconnects ${Math.max(0, (c.connects || 1) - 1)}` +
    (v.width ? ` · ${v.width}x${v.height}` : '') +
    (src.last_error ? ` · ${src.last_error}` : '');
  if ((sl.keyframes ?? 0) !== state.keyframes.length) refreshKeyframes();
  renderMapEvents(sl);
  drawMap();
  drawOverlay();
}
// The video link's loss when it leaves SLAM too few usable frames.
function linkText(l) {
  if (!l || !l.unreliable) return '';
  return ` | video link: ${(l.usable_share * 100).toFixed(0)} % of frames usable (${(l.masked_share * 100).toFixed(0)} % of rows masked) over the last ${l.window_s.toFixed(0)} s: shots are unreliable; a sender that retransmits (RTP with NACK), shorter key-frame intervals on the camera, or a stronger link, would help`;
}
function errorsText(errors) {
  if (!errors || !errors.length) return '';
  return errors.map((e) => ` | ERROR writing ${e.what}: ${e.message}`).join('');
}
// Where the SLAM's map came from: the saved map continued (and whether
// tracking has relocalised into it yet), or why it was not used.
function mapStartText(m) {
  if (!m) return '';
  if (m.mode === 'continued') {
    return m.relocalised_at_frame == null
      ? ` | saved map (${m.keyframes} kf, ${m.points} pts): not relocalised yet, fly over the mapped area`
      : ` | saved map continued (${m.keyframes} kf), relocalised at frame ${m.relocalised_at_frame}`;
  }
  if (m.mode === 'fresh_after_error') return ` | saved map not used: ${m.error || '?'}${m.set_aside ? ` (kept as ${m.set_aside})` : ''}`;
  return '';
}
function geoText(g) {
  if (!g) return '';
  const restored = g.evidence && g.evidence.restored_pairs ? `, ${g.evidence.restored_pairs} pairs from the saved georeference` : '';
  if (g.state === 'ok') return ` | georef ok: scale ${g.scale.toFixed(3)}, rms ${(g.rms_m * 100).toFixed(1)} cm, ${g.keyframes_used} kf${restored}`;
  return ` | georef ${g.state}: ${g.reason || ''}`;
}
const isObj = (v) => v !== null && typeof v === 'object' && !Array.isArray(v);
function mergePatch(doc, patch) {
  for (const [k, v] of Object.entries(patch)) {
    if (isObj(v) && isObj(doc[k])) mergePatch(doc[k], v); else doc[k] = v;
  }
}
function connectEvents() {
  const es = new EventSource(API + '/events');
  // The whole status on (re)connection, then only what changed (a JSON
  // merge patch: objects merge member by member, anything else replaces,
  // null reads as absent); a patch before a whole status is not applied.
  let doc = null;
  es.addEventListener('status', (e) => { try { doc = JSON.parse(e.data); showStatus(doc); } catch (_) {} });
  es.addEventListener('status_patch', (e) => { try { if (doc) { mergePatch(doc, JSON.parse(e.data)); showStatus(doc); } } catch (_) {} });
  es.addEventListener('shot', (e) => { try { onShotEvent(JSON.parse(e.data)); } catch (_) {} });
  // The daemon replays its kept history on each connection.
  es.onopen = () => { timelines.clear(); $('timeline').textContent = 'no shot events yet'; };
  es.onerror = () => { doc = null; $('status').textContent = 'daemon unreachable, retrying…'; badge('b-link', 'bad', 'daemon unreachable'); };
}

// ---- shot events: timeline, live overlay, before/after ----------------------
// `shot` events (see openapi.json, ShotEvent): localised / not_localised,
// georeferenced, uploaded, started, flying (distance, at most 1 Hz), retargeted
// (the target moved by a refit in flight), arrived,
// round (shot error), overlay (the desired outline in the live frame),
// done, stopped. Hooks for tests and tools: each timeline is
// `.tl[data-shot]` with `li[data-kind]` entries (one `flying` line per
// round, updated); #overlay's data-state (none, outline, lost, ended),
// data-shot, data-error, data-corners; #beforeafter's data-state (none,
// loading, ready, unavailable) and data-shot.
const timelines = new Map();
let overlay = null;
const MILESTONES = new Set(['localised', 'not_localised', 'georeferenced', 'uploaded', 'started', 'retargeted', 'arrived', 'round', 'done', 'stopped']);
function eventText(e) {
  switch (e.kind) {
    case 'localised': return `localised: ${e.inliers} inliers, ${fmt(e.rms_error_px, 2)} px${e.position_sigma_pct == null ? '' : `, sigma ${fmt(e.position_sigma_pct, 2)} % of the distance, ${fmt(e.rotation_sigma_deg, 2)}°`}`;
    case 'not_localised': return `not localised: ${e.reason}`;
    case 'georeferenced': return `georeferenced: target ${fmt(e.lat_deg, 7)}, ${fmt(e.lon_deg, 7)}, ${fmt(e.alt_m, 1)} m, yaw ${fmt(e.yaw_deg, 1)}°, pitch ${fmt(e.gimbal_pitch_deg, 1)}°${e.position_sigma_m == null ? '' : `, position sigma ${fmt(e.position_sigma_m, 2)} m`}`;
    case 'uploaded': return `mission uploaded: ${e.items} items`;
    case 'started': return 'mission started';
    case 'flying': {
      // The straight line (a correction may be all vertical), then its parts.
      const v = e.vertical_m, up = typeof v === 'number' && v < 0 ? 'down' : 'up';
      return `round ${e.round}: flying, ${fmtM(e.distance_m)} m to the target (${fmtM(e.horizontal_m)} m horizontally, ${fmtM(Math.abs(v))} m ${up}; ${fmtM(e.start_m)} m when the flight began)`;
    }
    case 'retargeted': return `round ${e.round}: target moved ${fmtM(e.shift_m)} m by the georeference refitted in flight (heading ${fmt(e.yaw_deg, 2)}°, pitch ${fmt(e.pitch_deg, 2)}°), flying it instead (${e.count} this approach)`;
    case 'arrived': return `round ${e.round}: arrived`;
    case 'round': return `round ${e.round}: shot error ${e.shot_error_pct == null ? '–' : fmt(e.shot_error_pct, 2) + ' %'}${e.floor_pct == null ? '' : `, floor ${fmt(e.floor_pct, 2)} %`} → ${e.decision}${e.note ? ` (${e.note})` : ''}`;
    case 'done': return `done: ${e.stop}${e.reason ? ` (${e.reason})` : ''}`;
    case 'stopped': return `stopped: ${e.reason}`;
    default: return e.kind;
  }
}
function renderTimeline(id) {
  const t = timelines.get(id);
  const box = $('timeline');
  if (box.firstChild && box.firstChild.nodeType === Node.TEXT_NODE) box.textContent = '';
  let div = box.querySelector(`.tl[data-shot="${id}"]`);
  if (!div) { div = el('div', { class: 'tl', 'data-shot': id }); box.prepend(div); }
  div.textContent = '';
  div.append(el('div', { class: 'head' }, id));
  const ol = el('ol');
  for (const e of t.entries) {
    const li = el('li', { 'data-kind': e.kind }, `${new Date(e.at_unix * 1000).toLocaleTimeString()} ${eventText(e)}`);
    if (e.round != null) li.dataset.round = e.round;
    if (e.shot_error_pct != null) li.dataset.error = e.shot_error_pct;
    if (e.kind === 'flying') { li.dataset.distance = e.distance_m; li.dataset.start = e.start_m; }
    // Hooks for tests and tools: the localisation's sigma.
    if (e.position_sigma_pct != null) li.dataset.sigmaPct = e.position_sigma_pct;
    if (e.rotation_sigma_deg != null) li.dataset.sigmaDeg = e.rotation_sigma_deg;
    if (e.position_sigma_m != null) li.dataset.sigmaM = e.position_sigma_m;
    ol.append(li);
  }
  div.append(ol);
  div.dataset.last = t.entries.length ? t.entries[t.entries.length - 1].kind : '';
}
function onShotEvent(e) {
  if (!timelines.has(e.shot)) timelines.set(e.shot, { entries: [] });
  const t = timelines.get(e.shot);
  if (e.kind === 'overlay') { showOverlay(e); return; }
  if (e.kind === 'flying') {
    // One line per round's flight, updated in place.
    const i = t.entries.findIndex((x) => x.kind === 'flying' && x.round === e.round);
    if (i >= 0) t.entries[i] = e; else t.entries.push(e);
  } else t.entries.push(e);
  renderTimeline(e.shot);
  if (e.kind === 'started') { overlay = { shot: e.shot, ev: null }; drawOverlay(); }
  if (e.kind === 'done' || e.kind === 'stopped') {
    if (overlay && overlay.shot === e.shot) { overlay.ended = true; drawOverlay(); }
    showBeforeAfter(e.shot, e);
  }
  // Milestones change the stored shot: the shots panel follows.
  if (MILESTONES.has(e.kind)) refreshShots();
}
function showOverlay(e) {
  if (!overlay || overlay.shot !== e.shot || overlay.ended) overlay = { shot: e.shot, ev: null };
  overlay.ev = e;
  drawOverlay();
}
function drawOverlay() {
  const cv = $('overlay'), g = cv.getContext('2d');
  cv.hidden = !$('overlaytoggle').checked;
  g.clearRect(0, 0, cv.width, cv.height);
  const sl = (state.status && state.status.slam) || {};
  // The tracking state, always.
  g.font = '14px sans-serif'; g.fillStyle = sl.state === 'tracking' ? '#7fd67f' : '#ff9a6b';
  g.fillText(`SLAM ${sl.state || '?'}`, 8, cv.height - 10);
  if (!overlay) { cv.dataset.state = 'none'; return; }
  cv.dataset.shot = overlay.shot;
  const e = overlay.ev;
  if (overlay.ended) { cv.dataset.state = 'ended'; $('overlayinfo').textContent = `${overlay.shot}: refinement ended`; return; }
  if (!e) { cv.dataset.state = 'none'; return; }
  if (e.width && e.height && (cv.width !== e.width || cv.height !== e.height)) { cv.width = e.width; cv.height = e.height; }
  if (!e.corners_px) {
    cv.dataset.state = 'lost'; delete cv.dataset.corners; delete cv.dataset.error;
    $('overlayinfo').textContent = `${overlay.shot}: no outline (${e.note || 'no homography'})`;
    return;
  }
  cv.dataset.state = 'outline';
  cv.dataset.corners = JSON.stringify(e.corners_px);
  cv.dataset.error = String(e.shot_error_pct);
  g.strokeStyle = '#ff4d4d'; g.lineWidth = 3; g.beginPath();
  e.corners_px.forEach((c, i) => (i ? g.lineTo(c[0], c[1]) : g.moveTo(c[0], c[1])));
  g.closePath(); g.stroke();
  g.font = 'bold 18px sans-serif'; g.fillStyle = '#ffd24d';
  const txt = `${overlay.shot}: shot error ${fmt(e.shot_error_pct, 2)} %`;
  g.fillText(txt, 8, 22);
  $('overlayinfo').textContent = `${txt} · ${e.inliers} inliers`;
}
$('overlaytoggle').addEventListener('change', drawOverlay);

// ---- tracked features over the live video ----------------------------------
// With the toggle on, the page asks for the SLAM's keypoints of its newest
// processed frame (GET /features: at most [server] features_max of them,
// inliers first, packed in 5 bytes each) and for that frame's picture
// (GET /features/{seq}/frame.jpg), and draws the keypoints on the very
// frame they were found in (the live video underneath runs ahead by the
// SLAM's latency). At most FEATURES_HZ looks a second, one after the
// other; nothing is asked while the toggle is off (the event stream does
// not carry them). Hooks for tests and tools: #features's data-state
// (off, waiting, drawn, none), data-seq, data-slam (the tracking state
// after the frame), data-counts (the frame's keypoints per state, as the
// API reported them), data-drawn (the keypoints drawn per state),
// data-colors (each state's colour) and data-order (the drawing order).
const FEATURE_STATES = ['inlier', 'outlier', 'unmatched'];
const FEATURE_COLORS = { inlier: '#39d353', outlier: '#ff3b3b', unmatched: '#4da3ff' };
// `?features_hz=N` in the page's address sets the rate (0.2 to 15; each
// look costs the frame's JPEG, some 75 kB on the simulator's video).
const FEATURES_HZ = Math.min(15, Math.max(0.2, Number(new URLSearchParams(location.search).get('features_hz')) || 5));
// Each keypoint is a square of 2 FEATURE_HALF + 1 pixels a side, drawn
// state by state in FEATURE_ORDER: the many unmatched at the bottom, the
// few outliers on top (they often lie on an inlier: the same corner
// found on two pyramid levels, one kept, one rejected).
const FEATURE_HALF = 2;
const FEATURE_ORDER = ['unmatched', 'inlier', 'outlier'];
let featuresRun = 0;
$('features').dataset.colors = JSON.stringify(FEATURE_COLORS);
$('features').dataset.order = JSON.stringify(FEATURE_ORDER);
// The packed keypoints (see GET /features' `encoding`): x, y in pixels and
// the state's index in FEATURE_STATES.
function unpackFeatures(b64) {
  const bin = atob(b64), n = Math.floor(bin.length / 5), out = new Array(n);
  for (let i = 0; i < n; i++) {
    const c = (k) => bin.charCodeAt(i * 5 + k);
    out[i] = { x: (c(0) | (c(1) << 8)) / 8, y: (c(2) | (c(3) << 8)) / 8, s: c(4) };
  }
  return out;
}
function loadImage(src) {
  return new Promise((res, rej) => { const i = new Image(); i.onload = () => res(i); i.onerror = () => rej(new Error('the frame is gone')); i.src = src; });
}
function drawFeatures(cv, f, img) {
  if (cv.width !== f.width || cv.height !== f.height) { cv.width = f.width; cv.height = f.height; }
  const g = cv.getContext('2d');
  g.drawImage(img, 0, 0, cv.width, cv.height);
  const pts = unpackFeatures(f.points);
  const drawn = { inlier: 0, outlier: 0, unmatched: 0 };
  // A square centred on each keypoint's pixel (pixel centres at
  // integers), in FEATURE_ORDER.
  const side = 2 * FEATURE_HALF + 1;
  for (const name of FEATURE_ORDER) {
    const s = FEATURE_STATES.indexOf(name);
    g.fillStyle = FEATURE_COLORS[name];
    for (const p of pts) {
      if (p.s !== s) continue;
      g.fillRect(Math.round(p.x) - FEATURE_HALF, Math.round(p.y) - FEATURE_HALF, side, side);
      drawn[name]++;
    }
  }
  Object.assign(cv.dataset, { state: 'drawn', seq: String(f.seq), slam: f.state, counts: JSON.stringify(f.counts), drawn: JSON.stringify(drawn) });
  const c = f.counts, total = c.inlier + c.outlier + c.unmatched, shown = pts.length;
  $('featuresinfo').textContent = `frame #${f.seq} (SLAM ${f.state}): ${c.inlier} inliers (green), ${c.outlier} outliers (red), ${c.unmatched} unmatched (blue)` +
    (shown < total ? ` · ${shown} of ${total} drawn` : '');
}
async function featuresLoop(run) {
  const cv = $('features');
  let seen = null;
  while (run === featuresRun) {
    const t0 = performance.now();
    try {
      const f = await api('GET', '/features');
      if (f.seq !== seen) {
        const img = await loadImage(f.frame_url);
        if (run !== featuresRun) return;
        drawFeatures(cv, f, img);
        seen = f.seq;
      }
    } catch (e) {
      if (run !== featuresRun) return;
      if (seen == null) cv.dataset.state = 'none';
      $('featuresinfo').textContent = `tracked features: ${e.message}${seen == null ? '' : ` (showing frame #${seen})`}`;
    }
    await new Promise((r) => setTimeout(r, Math.max(0, 1000 / FEATURES_HZ - (performance.now() - t0))));
  }
}
function setFeatures() {
  const on = $('featurestoggle').checked, cv = $('features');
  featuresRun++;
  cv.hidden = !on;
  if (on) {
    cv.dataset.state = 'waiting';
    $('featuresinfo').textContent = 'tracked features: waiting for a processed frame…';
    featuresLoop(featuresRun);
  } else {
    cv.dataset.state = 'off';
    $('featuresinfo').textContent = '';
  }
}
$('featurestoggle').addEventListener('change', setFeatures);
// The desired picture and the live frame of the last round, side by side
// and overlaid (the slider sets the desired picture's opacity), and the
// server-composed PNG.
async function showBeforeAfter(id, ended) {
  const box = $('beforeafter');
  box.dataset.shot = id; box.dataset.state = 'loading';
  const t = Date.now();
  const achieved = `${API}/shots/${id}/achieved.jpg?t=${t}`, desired = `${API}/shots/${id}/image.jpg?t=${t}`;
  const ok = await fetch(achieved, { method: 'HEAD' }).then((r) => r.ok, () => false);
  if (box.dataset.shot !== id) return;
  const rounds = (timelines.get(id) || { entries: [] }).entries.filter((x) => x.kind === 'round');
  const last = rounds[rounds.length - 1];
  $('ba-title').textContent = `${id} · ${eventText(ended)}${last ? ` · final shot error ${last.shot_error_pct == null ? '–' : fmt(last.shot_error_pct, 2) + ' %'}` : ''}`;
  box.dataset.error = last && last.shot_error_pct != null ? String(last.shot_error_pct) : '';
  if (!ok) {
    box.dataset.state = 'unavailable';
    box.querySelector('.ba').hidden = true; $('ba-download').hidden = true;
    $('ba-msg').textContent = `${id}: no live frame was measured (no refinement round reached)`;
    return;
  }
  const imgs = [[$('ba-desired'), desired], [$('ba-achieved'), achieved], [$('ba-under'), achieved], [$('ba-over'), desired]];
  await Promise.all(imgs.map(([i, src]) => new Promise((res) => { i.onload = res; i.onerror = res; i.src = src; })));
  if (box.dataset.shot !== id) return;
  $('ba-msg').textContent = '';
  box.querySelector('.ba').hidden = false;
  $('ba-over').style.opacity = String(1 - $('ba-slider').value / 100);
  const dl = $('ba-download');
  dl.href = `${API}/shots/${id}/before_after.png`; dl.download = `${id}_before_after.png`; dl.hidden = false;
  box.dataset.state = 'ready';
}
$('ba-slider').addEventListener('input', () => { $('ba-over').style.opacity = String(1 - $('ba-slider').value / 100); });

// ---- map --------------------------------------------------------------------
// With a georeference: a world map, north up, local NED metres at home
// (east to the right, north up), with a scale bar; the SLAM map goes
// through the georeference's ned_from_map (p_ned = s R p_map + t).
// Without one: the SLAM map's top view (camera axes x right, y down, z
// forward; x to the right, z up on the canvas), and the reason.
const view = { zoom: 1, pan: [0, 0], fit: true };
function quatRotate(q, p) {
  const [x, y, z, w] = q;
  const tx = 2 * (y * p[2] - z * p[1]), ty = 2 * (z * p[0] - x * p[2]), tz = 2 * (x * p[1] - y * p[0]);
  return [p[0] + w * tx + (y * tz - z * ty), p[1] + w * ty + (z * tx - x * tz), p[2] + w * tz + (x * ty - y * tx)];
}
function nedFromMap(g) {
  const t = g && g.state === 'ok' && g.ned_from_map;
  if (!t) return null;
  return (p) => { const r = quatRotate(t.rotation_xyzw, p); return [t.scale * r[0] + t.translation[0], t.scale * r[1] + t.translation[1], t.scale * r[2] + t.translation[2]]; };
}
// Flat-earth offset from home, metres north/east (for mission items, which
// carry lat/lon only; under a centimetre off over the geofence's hundreds of metres).
function nedOfLatLon(home, lat, lon) {
  const R = 6378137.0, la = home.lat_deg * Math.PI / 180;
  return [(lat - home.lat_deg) * Math.PI / 180 * R, (lon - home.lon_deg) * Math.PI / 180 * R * Math.cos(la)];
}
function shotsOnMap() {
  const out = [];
  for (const s of state.shots || []) {
    const d = s.mission && s.mission.details;
    const rt = d && d.refinement && d.refinement.target;
    const t = d && d.target;
    if (!t || !t.p_ned_vehicle) continue;
    out.push({ id: s.id, p: t.p_ned_vehicle, yaw: t.yaw_deg, pitch: t.gimbal_pitch_deg, items: d.planned_items || [], state: s.mission.state, refined: rt });
  }
  return out;
}
function drawMap() {
  const cv = $('map'), g = cv.getContext('2d');
  g.fillStyle = '#0b0d10'; g.fillRect(0, 0, cv.width, cv.height);
  const m = state.map, s = state.status || {}, ve = s.vehicle || {}, geo = ve.georeference || {};
  const toNed = nedFromMap(geo);
  if (!toNed) { $('mapmode').textContent = `(SLAM view: no georeference${geo.reason ? ' — ' + geo.reason : geo.state ? ' — ' + geo.state : ''})`; cv.dataset.mode = 'slam'; delete cv.dataset.vehicleNed; drawSlamView(cv, g, m); return; }
  $('mapmode').textContent = '(north up, metres from home)';
  $('maplegend').textContent = 'green: home and geofence · grey: map points · blue: keyframes (click one to choose it) · magenta: keyframes a closed loop joined · yellow: vehicle · red: target cameras, viewing direction and aim on the ground · dashed: mission path';
  cv.dataset.mode = 'world';
  // world (north, east) -> canvas
  const pts = (m ? m.points : []).map((p) => toNed(p));
  const kfs = (m ? m.trajectory : []).map((p) => toNed(p));
  // the keyframes the gallery lists (ids known), for drawing and choosing
  const kfList = state.keyframes.map((k) => ({ id: k.id, p: toNed(k.world_from_cam.translation) }));
  const shots = shotsOnMap();
  const pos = ve.position, veh = pos && pos.ned_m;
  if (view.fit) {
    const ns = [0], es = [0];
    for (const k of kfs) { ns.push(k[0]); es.push(k[1]); }
    for (const t of shots) { ns.push(t.p[0]); es.push(t.p[1]); }
    if (veh) { ns.push(veh[0]); es.push(veh[1]); }
    const span = Math.max(Math.max(...ns) - Math.min(...ns), Math.max(...es) - Math.min(...es), 20) * 1.3;
    view.zoom = Math.min(cv.width, cv.height) / span;
    view.pan = [(Math.max(...ns) + Math.min(...ns)) / 2, (Math.max(...es) + Math.min(...es)) / 2];
  }
  const sc = view.zoom, [cn, ce] = view.pan;
  const P = (n, e) => [cv.width / 2 + (e - ce) * sc, cv.height / 2 - (n - cn) * sc];
  state.mapProject = { P, kfs: kfList };
  // geofence and home
  const fence = ve.fence;
  const [hu, hv] = P(0, 0);
  if (fence) { g.strokeStyle = '#3fae5a'; g.setLineDash([6, 4]); g.beginPath(); g.arc(hu, hv, fence.radius_m * sc, 0, 2 * Math.PI); g.stroke(); g.setLineDash([]); }
  g.fillStyle = '#3fae5a'; g.fillRect(hu - 5, hv - 5, 10, 10);
  g.font = '11px sans-serif'; g.fillText('H', hu + 7, hv - 7);
  // map points (downsampled by the API) and keyframe trajectory
  g.fillStyle = '#8a9199';
  for (const p of pts) { const [u, v] = P(p[0], p[1]); g.fillRect(u, v, 1.5, 1.5); }
  g.strokeStyle = '#4da3ff'; g.lineWidth = 1.5; g.beginPath();
  kfs.forEach((k, i) => { const [u, v] = P(k[0], k[1]); i ? g.lineTo(u, v) : g.moveTo(u, v); });
  g.stroke();
  kfList.forEach((k) => {
    const [u, v] = P(k.p[0], k.p[1]);
    const sel = state.kf && k.id === state.kf.id;
    g.fillStyle = sel ? '#ffd24d' : '#4da3ff'; g.beginPath(); g.arc(u, v, sel ? 5 : 3, 0, 2 * Math.PI); g.fill();
  });
  drawLoops(cv, g, P, kfList);
  // shots: target camera, viewing direction, aim on the ground, mission path
  for (const t of shots) {
    const [u, v] = P(t.p[0], t.p[1]);
    const home = geo.home || (ve.georeference && ve.georeference.home);
    if (home && t.items.length) {
      g.strokeStyle = '#ff9a9a'; g.setLineDash([4, 4]); g.beginPath(); g.moveTo(hu, hv);
      for (const it of t.items) {
        if (!(it.command === 16 || it.command === 22) || !it.x || !it.y) continue;
        const [n, e] = nedOfLatLon(home, it.x / 1e7, it.y / 1e7); const [a, b] = P(n, e); g.lineTo(a, b);
      }
      g.stroke(); g.setLineDash([]);
    }
    const yaw = (t.yaw || 0) * Math.PI / 180, pitch = (t.pitch || 0) * Math.PI / 180;
    const alt = -t.p[2];
    // where the optical axis meets the ground (home's altitude)
    const reach = pitch < -0.02 ? Math.min(alt / Math.tan(-pitch), 500) : 30;
    const [gu, gv] = P(t.p[0] + reach * Math.cos(yaw), t.p[1] + reach * Math.sin(yaw));
    g.strokeStyle = '#ff4d4d'; g.lineWidth = 1.5; g.beginPath(); g.moveTo(u, v); g.lineTo(gu, gv); g.stroke();
    g.beginPath(); g.arc(gu, gv, 4, 0, 2 * Math.PI); g.stroke();
    g.fillStyle = '#ff4d4d'; g.beginPath(); g.arc(u, v, 5, 0, 2 * Math.PI); g.fill();
    g.fillText(t.id.replace('shot-', '#'), u + 7, v + 4);
  }
  // vehicle: position and heading
  if (veh) {
    const [u, v] = P(veh[0], veh[1]);
    const h = ((pos.heading_deg ?? 0) * Math.PI) / 180;
    g.save(); g.translate(u, v); g.rotate(h);
    g.fillStyle = '#ffd24d'; g.beginPath(); g.moveTo(0, -10); g.lineTo(6, 7); g.lineTo(0, 3); g.lineTo(-6, 7); g.closePath(); g.fill();
    g.restore();
    // Hook for tests and tools: the drawn position, metres north, east.
    cv.dataset.vehicleNed = `${veh[0].toFixed(3)},${veh[1].toFixed(3)}`;
    cv.dataset.vehicleCanvas = `${u.toFixed(1)},${v.toFixed(1)}`;
  } else delete cv.dataset.vehicleNed;
  // scale bar: 1, 2 or 5 x 10^k metres, about a fifth of the width
  const want = cv.width / 5 / sc, k = Math.pow(10, Math.floor(Math.log10(want)));
  const len = [1, 2, 5, 10].map((f) => f * k).filter((l) => l <= want).pop() || k;
  g.strokeStyle = '#e4e6e8'; g.lineWidth = 2; g.beginPath();
  g.moveTo(10, cv.height - 12); g.lineTo(10 + len * sc, cv.height - 12); g.stroke();
  g.fillStyle = '#e4e6e8'; g.fillText(`${len} m`, 12, cv.height - 16);
  cv.dataset.scaleBarM = String(len);
  g.fillText('N ↑', cv.width - 28, 14);
}
// The loops closed (status slam.loops, the latest few): the two keyframes
// each joined, linked in magenta, over the keyframes `kfs` ({id, p}) drawn
// by `P`. Hook for tests and tools: the map's data-loops, the pairs drawn.
function drawLoops(cv, g, P, kfs) {
  const loops = ((state.status && state.status.slam) || {}).loops || [];
  const at = new Map(kfs.map((k) => [k.id, k.p]));
  const drawn = [];
  g.strokeStyle = '#e05cff'; g.fillStyle = '#e05cff'; g.lineWidth = 2;
  for (const l of loops) {
    const a = at.get(l.current_kf), b = at.get(l.loop_kf);
    if (!a || !b) continue;
    const [au, av] = P(a[0], a[1]), [bu, bv] = P(b[0], b[1]);
    g.setLineDash([3, 3]); g.beginPath(); g.moveTo(au, av); g.lineTo(bu, bv); g.stroke(); g.setLineDash([]);
    for (const [u, v] of [[au, av], [bu, bv]]) { g.beginPath(); g.arc(u, v, 6, 0, 2 * Math.PI); g.stroke(); }
    drawn.push([l.current_kf, l.loop_kf]);
  }
  cv.dataset.loops = JSON.stringify(drawn);
}
// The map's events, newest first: each loop closed (status slam.loops,
// the latest few) and each map merged after a tracking loss (slam.merges)
// with its figures; their keyframes are buttons that choose the keyframe in
// the editor and centre the world map on it. Hooks for tests and tools:
// #mapevents li[data-kind="loop"] with data-current and data-loop (the two
// keyframes), li[data-kind="merge"] with data-current and data-merge, each
// with data-at (unix seconds).
let mapEventsSeen = '';
function renderMapEvents(sl) {
  const loops = sl.loops || [], merges = sl.merges || [];
  const key = JSON.stringify([loops.map((l) => [l.current_kf, l.loop_kf, l.at_unix]), merges.map((m) => [m.current_kf, m.merge_kf, m.at_unix])]);
  if (key === mapEventsSeen) return;
  mapEventsSeen = key;
  const box = $('mapevents');
  box.textContent = '';
  if (!loops.length && !merges.length) { box.append(el('li', { class: 'none' }, 'no loops closed or maps merged yet')); return; }
  const kfButton = (id) => {
    const b = el('button', { class: 'kf', 'data-kf': id, 'aria-label': `keyframe ${id}: choose it and show it on the map` }, `#${id}`);
    b.addEventListener('click', () => showKeyframe(id));
    return b;
  };
  const time = (at) => new Date(at * 1000).toLocaleTimeString();
  const items = [];
  loops.forEach((l, i) => items.push({ at: l.at_unix, i, li: () => {
    const li = el('li', { 'data-kind': 'loop', 'data-current': l.current_kf, 'data-loop': l.loop_kf, 'data-at': l.at_unix });
    li.append(`${time(l.at_unix)} loop closed: keyframe `, kfButton(l.current_kf), ' saw ', kfButton(l.loop_kf),
      ` again (${l.inliers} inliers, scale ${fmt(l.scale, 3)}, rotation ${fmt(l.rotation_deg, 2)}°, ${l.fused} points fused)`);
    return li;
  } }));
  merges.forEach((m, i) => items.push({ at: m.at_unix, i, li: () => {
    const li = el('li', { 'data-kind': 'merge', 'data-current': m.current_kf, 'data-merge': m.merge_kf, 'data-at': m.at_unix });
    li.append(`${time(m.at_unix)} maps merged: map ${m.from_map} (started after a tracking loss) joined map ${m.into_map} where keyframe `, kfButton(m.current_kf), ' saw ', kfButton(m.merge_kf),
      ` (${m.inliers} inliers, scale ${fmt(m.scale, 3)}, ${m.keyframes_moved} keyframes moved, ${m.fused} points fused)`);
    return li;
  } }));
  // Newest first; within one kind the status's order breaks ties.
  items.sort((a, b) => b.at - a.at || b.i - a.i);
  for (const it of items) box.append(it.li());
}
// Choose keyframe `id` in the editor and centre the world map on it (a
// keyframe the map culled since says so).
function showKeyframe(id) {
  const kf = state.keyframes.find((k) => k.id === id);
  if (!kf) { $('kfgoinfo').textContent = `no keyframe #${id} in the map (culled)`; return; }
  chooseKeyframe(kf);
  const pr = state.mapProject, k = pr && pr.kfs.find((x) => x.id === id);
  if (k && $('map').dataset.mode === 'world') { view.fit = false; view.pan = [k.p[0], k.p[1]]; drawMap(); }
}
function drawSlamView(cv, g, m) {
  if (!m) return;
  const target = state.shot && state.shot.localisation ? state.shot.localisation.world_from_cam.translation : null;
  const xs = [], zs = [];
  for (const p of m.points) { xs.push(p[0]); zs.push(p[2]); }
  for (const t of m.trajectory) { xs.push(t[0]); zs.push(t[2]); }
  if (target) { xs.push(target[0]); zs.push(target[2]); }
  if (!xs.length) return;
  const pct = (a, q) => { const s = [...a].sort((u, v) => u - v); return s[Math.floor(q * (s.length - 1))]; };
  const x0 = pct(xs, 0.02), x1 = pct(xs, 0.98), z0 = pct(zs, 0.02), z1 = pct(zs, 0.98);
  const span = Math.max(x1 - x0, z1 - z0, 1e-6) * 1.15;
  const cx = (x0 + x1) / 2, cz = (z0 + z1) / 2, sc = Math.min(cv.width, cv.height) / span;
  const P = (x, z) => [cv.width / 2 + (x - cx) * sc, cv.height / 2 - (z - cz) * sc];
  g.fillStyle = '#8a9199';
  for (const p of m.points) { const [u, v] = P(p[0], p[2]); g.fillRect(u, v, 1.5, 1.5); }
  g.strokeStyle = '#4da3ff'; g.lineWidth = 2; g.beginPath();
  m.trajectory.forEach((t, i) => { const [u, v] = P(t[0], t[2]); i ? g.lineTo(u, v) : g.moveTo(u, v); });
  g.stroke();
  state.mapProject = { P, kfs: state.keyframes.map((k) => ({ id: k.id, p: [k.world_from_cam.translation[0], k.world_from_cam.translation[2]] })) };
  drawLoops(cv, g, P, state.mapProject.kfs);
  if (target) {
    const [u, v] = P(target[0], target[2]);
    g.fillStyle = '#ff4d4d'; g.beginPath(); g.arc(u, v, 6, 0, 2 * Math.PI); g.fill();
  }
}
// pan (drag), zoom (wheel, + / -, keyboard), click a keyframe to choose it
(function mapControls() {
  const cv = $('map');
  let drag = null;
  const canvasXY = (e) => { const r = cv.getBoundingClientRect(); return [(e.clientX - r.left) * cv.width / r.width, (e.clientY - r.top) * cv.height / r.height]; };
  const zoomBy = (f) => { view.fit = false; view.zoom *= f; drawMap(); };
  const panBy = (du, dv) => { view.fit = false; view.pan = [view.pan[0] + dv / view.zoom, view.pan[1] - du / view.zoom]; drawMap(); };
  cv.addEventListener('pointerdown', (e) => { drag = { at: canvasXY(e), moved: 0 }; cv.setPointerCapture(e.pointerId); });
  cv.addEventListener('pointermove', (e) => {
    if (!drag) return;
    const [u, v] = canvasXY(e), du = u - drag.at[0], dv = v - drag.at[1];
    drag.moved += Math.abs(du) + Math.abs(dv); drag.at = [u, v];
    if (cv.dataset.mode === 'world' && drag.moved > 3) panBy(-du, -dv);
  });
  cv.addEventListener('pointerup', (e) => {
    const d = drag; drag = null;
    if (!d || d.moved > 3) return;
    const [u, v] = canvasXY(e), pr = state.mapProject;
    if (!pr) return;
    let best = null, bd = 10;
    for (const k of pr.kfs) { const [a, b] = pr.P(k.p[0], k.p[1]); const dd = Math.hypot(a - u, b - v); if (dd < bd) { bd = dd; best = k.id; } }
    const kf = best != null && state.keyframes.find((x) => x.id === best);
    if (kf) chooseKeyframe(kf);
  });
  cv.addEventListener('wheel', (e) => { if (cv.dataset.mode !== 'world') return; e.preventDefault(); zoomBy(e.deltaY < 0 ? 1.25 : 0.8); }, { passive: false });
  cv.addEventListener('keydown', (e) => {
    const step = 40, keys = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
    if (keys[e.key]) { e.preventDefault(); panBy(...keys[e.key]); } else if (e.key === '+' || e.key === '=') zoomBy(1.25); else if (e.key === '-') zoomBy(0.8); else if (e.key === '0') { view.fit = true; drawMap(); }
  });
  $('zoomin').addEventListener('click', () => zoomBy(1.25));
  $('zoomout').addEventListener('click', () => zoomBy(0.8));
  $('zoomfit').addEventListener('click', () => { view.fit = true; drawMap(); });
})();
async function refreshMap() {
  try { state.map = await api('GET', '/map?max_points=5000'); drawMap(); } catch (_) {}
}

// ---- keyframes ------------------------------------------------------------
// A bounded gallery: the newest GALLERY_LATEST keyframes, the ones shots
// were drawn on or localised through, and the chosen one; every other
// keyframe is reached on the map (click it) or by its number (#kfgo).
// `?kf_gallery=N` in the page's address sets the bound. Hooks for tests
// and tools: #gallery's data-total (the map's keyframes) and data-shown.
const GALLERY_LATEST = Math.max(1, Number(new URLSearchParams(location.search).get('kf_gallery')) || 24);
let kfBusy = false;
function shotKeyframes() {
  const out = new Set();
  for (const s of state.shots || []) {
    if (s.source && s.source.kind === 'anchors' && s.source.keyframe_id != null) out.add(s.source.keyframe_id);
    if (s.localisation && s.localisation.keyframe_id != null) out.add(s.localisation.keyframe_id);
  }
  return out;
}
function galleryFigure(kf) {
  const fig = document.createElement('figure');
  fig.dataset.id = kf.id;
  const img = document.createElement('img');
  img.loading = 'lazy';
  img.src = `${API}/keyframes/${kf.id}/image.jpg`;
  const cap = document.createElement('figcaption');
  cap.textContent = `#${kf.id}`;
  fig.append(img, cap);
  fig.addEventListener('click', () => chooseKeyframe(kf));
  fig.tabIndex = 0;
  fig.setAttribute('role', 'button');
  fig.setAttribute('aria-label', `keyframe ${kf.id}`);
  fig.addEventListener('keydown', (e) => { if (e.key === 'Enter' || e.key === ' ') { e.preventDefault(); chooseKeyframe(kf); } });
  return fig;
}
function renderGallery() {
  const gal = $('gallery'), all = state.keyframes;
  const ids = all.map((k) => k.id).sort((x, y) => x - y);
  const pinned = shotKeyframes();
  if (state.kfChosen != null) pinned.add(state.kfChosen);
  // Keyframes the map has culled leave the gallery (a shot on one would be
  // refused as unknown_keyframe).
  const want = new Set([...ids.slice(-GALLERY_LATEST), ...ids.filter((id) => pinned.has(id))]);
  const have = new Map();
  for (const f of [...gal.querySelectorAll('figure')]) {
    if (!want.has(Number(f.dataset.id))) f.remove(); else have.set(Number(f.dataset.id), f);
  }
  // In id order, the new ones inserted where they belong.
  let prev = null;
  for (const kf of [...all].sort((x, y) => x.id - y.id)) {
    if (!want.has(kf.id)) continue;
    let fig = have.get(kf.id);
    if (!fig) { fig = galleryFigure(kf); if (prev) prev.after(fig); else gal.prepend(fig); }
    fig.classList.toggle('selected', kf.id === state.kfChosen);
    prev = fig;
  }
  gal.dataset.total = String(all.length);
  gal.dataset.shown = String(want.size);
  $('kfcount').textContent = want.size < all.length ? `(${want.size} of ${all.length})` : `(${all.length})`;
  $('kfnote').textContent = want.size < all.length
    ? `the newest ${GALLERY_LATEST}, those shots use and the chosen one; choose any other on the map or by number`
    : '';
}
async function refreshKeyframes() {
  if (kfBusy) return;
  kfBusy = true;
  try {
    const r = await api('GET', '/keyframes');
    state.keyframes = r.keyframes;
    renderGallery();
    // The map's clickable keyframes come from this list: redraw, so a
    // click lands on where the keyframes are now, not where they were.
    drawMap();
  } catch (_) {
  } finally { kfBusy = false; }
}
function goToKeyframe() {
  const id = Number($('kfgo').value);
  const kf = state.keyframes.find((k) => k.id === id);
  $('kfgoinfo').textContent = kf ? '' : `no keyframe #${$('kfgo').value} in the map`;
  if (kf) chooseKeyframe(kf);
}
$('kfgobtn').addEventListener('click', goToKeyframe);
$('kfgo').addEventListener('keydown', (e) => { if (e.key === 'Enter') goToKeyframe(); });

function chooseKeyframe(kf) {
  state.kfChosen = kf.id;
  renderGallery();
  const img = new Image();
  img.onload = () => {
    state.kf = kf; state.kfImage = img;
    const ed = $('editor');
    ed.width = img.naturalWidth; ed.height = img.naturalHeight;
    const off = document.createElement('canvas');
    off.width = img.naturalWidth; off.height = img.naturalHeight;
    const og = off.getContext('2d');
    og.drawImage(img, 0, 0);
    state.srcPixels = og.getImageData(0, 0, off.width, off.height);
    const w = img.naturalWidth, h = img.naturalHeight;
    state.anchors = [[w * 0.25, h * 0.25], [w * 0.75, h * 0.25], [w * 0.75, h * 0.75], [w * 0.25, h * 0.75]];
    $('submit').disabled = false;
    $('editinfo').textContent = `keyframe #${kf.id} (${w}x${h})`;
    ed.dataset.keyframe = kf.id;
    drawEditor();
  };
  img.src = `${API}/keyframes/${kf.id}/image.jpg`;
}

// ---- anchor editor and preview ----------------------------------------------
function drawEditor() {
  const ed = $('editor'), g = ed.getContext('2d');
  if (!state.kfImage) return;
  g.drawImage(state.kfImage, 0, 0);
  const a = state.anchors;
  // Anchors are in keyframe pixels with pixel centres at integers (the
  // daemon's convention: the corners of the shot are pixels (0,0) and
  // (w-1,h-1)); on the canvas a pixel's centre is at +0.5.
  g.strokeStyle = '#ffd24d'; g.lineWidth = 2; g.beginPath();
  a.forEach((p, i) => (i ? g.lineTo(p[0] + 0.5, p[1] + 0.5) : g.moveTo(p[0] + 0.5, p[1] + 0.5)));
  g.closePath(); g.stroke();
  // Hook for tests and tools: the anchors in keyframe pixels.
  ed.dataset.anchors = JSON.stringify(a.map((p) => [Math.round(p[0] * 10) / 10, Math.round(p[1] * 10) / 10]));
  const names = ['TL', 'TR', 'BR', 'BL'];
  a.forEach((p, i) => {
    g.fillStyle = i === state.drag ? '#ff4d4d' : '#ffd24d';
    g.beginPath(); g.arc(p[0] + 0.5, p[1] + 0.5, 7, 0, 2 * Math.PI); g.fill();
    g.fillStyle = '#000'; g.font = '10px sans-serif'; g.fillText(names[i], p[0] - 5.5, p[1] + 3.5);
  });
  drawPreview();
}

// Homography H (3x3, row-major, h33 = 1) with dst ~ H src for four pairs.
function homography4(src, dst) {
  const A = [], b = [];
  for (let i = 0; i < 4; i++) {
    const [x, y] = src[i], [u, v] = dst[i];
    A.push([x, y, 1, 0, 0, 0, -u * x, -u * y]); b.push(u);
    A.push([0, 0, 0, x, y, 1, -v * x, -v * y]); b.push(v);
  }
  // Gaussian elimination with partial pivoting.
  for (let c = 0; c < 8; c++) {
    let p = c;
    for (let r = c + 1; r < 8; r++) if (Math.abs(A[r][c]) > Math.abs(A[p][c])) p = r;
    if (Math.abs(A[p][c]) < 1e-12) return null;
    [A[c], A[p]] = [A[p], A[c]]; [b[c], b[p]] = [b[p], b[c]];
    for (let r = c + 1; r < 8; r++) {
      const f = A[r][c] / A[c][c];
      for (let k = c; k < 8; k++) A[r][k] -= f * A[c][k];
      b[r] -= f * b[c];
    }
  }
  const h = new Array(8);
  for (let r = 7; r >= 0; r--) {
    let s = b[r];
    for (let k = r + 1; k < 8; k++) s -= A[r][k] * h[k];
    h[r] = s / A[r][r];
  }
  return [...h, 1];
}

function drawPreview() {
  const pv = $('preview'), g = pv.getContext('2d');
  const src = state.srcPixels;
  if (!src) return;
  const W = pv.width, H = pv.height;
  // The shot's corner pixels go to the anchors (pixel centres at integers).
  const h = homography4([[0, 0], [W - 1, 0], [W - 1, H - 1], [0, H - 1]], state.anchors);
  const out = g.createImageData(W, H);
  if (h) {
    const sw = src.width, sh = src.height, s = src.data, o = out.data;
    for (let y = 0; y < H; y++) {
      for (let x = 0; x < W; x++) {
        const w = h[6] * x + h[7] * y + h[8];
        const u = (h[0] * x + h[1] * y + h[2]) / w;
        const v = (h[3] * x + h[4] * y + h[5]) / w;
        const i = (y * W + x) * 4;
        o[i + 3] = 255;
        if (!(u >= 0 && v >= 0 && u <= sw - 1 && v <= sh - 1)) continue;
        const x0 = Math.floor(u), y0 = Math.floor(v);
        const x1 = Math.min(x0 + 1, sw - 1), y1 = Math.min(y0 + 1, sh - 1);
        const ax = u - x0, ay = v - y0;
        for (let ch = 0; ch < 3; ch++) {
          const g00 = s[(y0 * sw + x0) * 4 + ch], g10 = s[(y0 * sw + x1) * 4 + ch];
          const g01 = s[(y1 * sw + x0) * 4 + ch], g11 = s[(y1 * sw + x1) * 4 + ch];
          o[i + ch] = (1 - ay) * ((1 - ax) * g00 + ax * g10) + ay * ((1 - ax) * g01 + ax * g11);
        }
      }
    }
  }
  g.putImageData(out, 0, 0);
}

function editorPoint(ev) {
  const ed = $('editor'), r = ed.getBoundingClientRect();
  // Canvas coordinates to keyframe pixels (pixel centres at integers).
  return [(ev.clientX - r.left) * ed.width / r.width - 0.5, (ev.clientY - r.top) * ed.height / r.height - 0.5];
}
$('editor').addEventListener('pointerdown', (ev) => {
  if (!state.anchors) return;
  const p = editorPoint(ev);
  const ed = $('editor'), scale = ed.width / ed.getBoundingClientRect().width;
  let best = -1, bd = 20 * scale;
  state.anchors.forEach((a, i) => { const d = Math.hypot(a[0] - p[0], a[1] - p[1]); if (d < bd) { bd = d; best = i; } });
  state.drag = best;
  if (best >= 0) $('editor').setPointerCapture(ev.pointerId);
  drawEditor();
});
$('editor').addEventListener('pointermove', (ev) => {
  if (state.drag < 0) return;
  state.anchors[state.drag] = editorPoint(ev);
  drawEditor();
});
const endDrag = () => { state.drag = -1; drawEditor(); };
$('editor').addEventListener('pointerup', endDrag);
$('editor').addEventListener('pointercancel', endDrag);

// ---- shot, mission -----------------------------------------------------------
// `state` is a hook for tests and tools (#result's data-state): idle,
// busy, localised, not_localised, error.
function showResult(obj, isError, state) {
  const el = $('result');
  el.classList.toggle('error', !!isError);
  el.dataset.state = state || (isError ? 'error' : 'busy');
  el.textContent = typeof obj === 'string' ? obj : JSON.stringify(obj, null, 2);
}
function showShot(s) {
  state.shot = s;
  const l = s.localisation;
  const lines = [`shot ${s.id}: ${s.status}`];
  if (l) {
    const t = l.world_from_cam.translation;
    lines.push(`camera at (${t.map((v) => v.toFixed(3)).join(', ')})`, `inliers ${l.inliers}, rms error ${l.rms_error_px.toFixed(2)} px`);
  } else if (s.reason) lines.push(`reason: ${s.reason}`);
  if (s.mission) lines.push(`mission: ${s.mission.state}, ${s.mission.items} items`);
  const t = s.mission && s.mission.details && s.mission.details.target;
  if (t) lines.push(`target: ${t.lat_deg.toFixed(7)}, ${t.lon_deg.toFixed(7)}, ${t.alt_above_home_m.toFixed(1)} m, yaw ${t.yaw_deg.toFixed(1)}°, pitch ${t.gimbal_pitch_deg.toFixed(1)}°`);
  const rf = s.mission && s.mission.details && s.mission.details.refinement;
  if (rf && Array.isArray(rf.rounds)) {
    for (const r of rf.rounds) {
      const e = r.shot_error_pct == null ? 'no shot error' : `shot error ${r.shot_error_pct.toFixed(2)} %`;
      const c = r.correction ? `, corrected by (${r.correction.step_ned_m.map((v) => v.toFixed(2)).join(', ')}) m, yaw ${r.correction.yaw_step_deg.toFixed(2)}°, pitch ${r.correction.pitch_step_deg.toFixed(2)}°` : '';
      const fl = r.floor_pct == null ? '' : `, floor ${r.floor_pct.toFixed(2)} %`;
      lines.push(`refinement round ${r.round}: ${e}${fl}, ${r.decision}${c}${r.note ? ` (${r.note})` : ''}`);
    }
    if (rf.stop) lines.push(`refinement: ${rf.stop}${rf.reason ? ` (${rf.reason})` : ''}`);
  }
  $('result').dataset.shotId = s.id;
  showResult(lines.join('\n'), false, s.status);
  // No image element shown (no broken-image placeholder) until there is one.
  if (s.has_image) { $('shotimg').src = `${API}/shots/${s.id}/image.jpg?t=${Date.now()}`; $('shotimg').hidden = false; } else { $('shotimg').hidden = true; }
  $('upload').disabled = !l;
  $('start').disabled = !s.mission;
  for (const c of document.querySelectorAll('.shotcard')) c.classList.toggle('selected', c.dataset.id === s.id);
  drawMap();
  refreshShots();
}
$('submit').addEventListener('click', async () => {
  if (!state.kf) return;
  $('submit').disabled = true;
  showResult('submitting…');
  try {
    const a = state.anchors.map((p) => [Math.round(p[0] * 10) / 10, Math.round(p[1] * 10) / 10]);
    showShot(await api('POST', '/shots', { keyframe_id: state.kf.id, anchors: a }));
  } catch (e) { showResult(String(e.message || e), true); }
  $('submit').disabled = false;
});
$('upload').addEventListener('click', async () => {
  if (!state.shot) return;
  showResult('uploading mission…');
  try { showShot(await api('POST', `/shots/${state.shot.id}/mission`)); } catch (e) { showResult(String(e.message || e), true); }
});
$('start').addEventListener('click', async () => {
  if (!state.shot) return;
  // Progress follows from the event stream (the timeline).
  try { showShot(await api('POST', `/shots/${state.shot.id}/start`)); } catch (e) { showResult(String(e.message || e), true); }
});

// ---- shots and their refinement rounds ----------------------------------------
// One card per shot (newest first): status, source, mission, and, once its
// mission was started, a table of the refinement rounds and why the loop
// stopped (or that it is still running). Hooks for tests and tools: each
// card has data-id, each round row data-round, the stop line data-stop.
const fmt = (v, d) => (typeof v === 'number' && isFinite(v) ? v.toFixed(d) : '–');
// Metres: centimetres under 10 m (a correction is often a few decimetres).
const fmtM = (v) => fmt(v, typeof v === 'number' && Math.abs(v) < 10 ? 2 : 1);
function el(tag, attrs, text) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === 'class') e.className = v; else e.setAttribute(k, v);
  }
  if (text !== undefined) e.textContent = text;
  return e;
}
function sourceText(src) {
  if (!src) return '';
  if (src.kind === 'anchors') return `anchors on keyframe #${src.keyframe_id}`;
  if (src.kind === 'photo') return `photo ${src.width}x${src.height}`;
  return src.kind || '';
}
function stopText(rf) {
  if (!rf.stop) return { key: 'running', text: `refining… (${(rf.rounds || []).length} round${(rf.rounds || []).length === 1 ? '' : 's'} so far)` };
  const why = rf.reason ? `: ${rf.reason}` : '';
  const note = rf.daemon_note ? ` (daemon: ${rf.daemon_note})` : '';
  return { key: rf.stop, text: `stopped: ${rf.stop}${why}${note}` };
}
function roundsTable(rounds) {
  const t = el('table', { class: 'rounds' });
  const head = el('tr');
  for (const h of ['round', 'shot error %', 'error px', 'inliers', 'decision', 'correction (N, E, D) m', 'yaw °', 'pitch °', 'note', 'floor %']) head.append(el('th', {}, h));
  t.append(head);
  for (const r of rounds) {
    const tr = el('tr', { 'data-round': r.round });
    const c = r.correction;
    tr.append(
      el('td', {}, String(r.round)),
      el('td', {}, fmt(r.shot_error_pct, 2)),
      el('td', {}, fmt(r.shot_error_px, 1)),
      el('td', {}, r.inliers == null ? '–' : String(r.inliers)),
      el('td', { class: 'text' }, r.decision || ''),
      el('td', {}, c ? c.step_ned_m.map((v) => fmt(v, 2)).join(', ') + (c.limited ? ' (limited)' : '') : '–'),
      el('td', {}, c ? fmt(c.yaw_step_deg, 2) : '–'),
      el('td', {}, c ? fmt(c.pitch_step_deg, 2) : '–'),
      el('td', { class: 'text' }, r.note || ''),
      el('td', {}, fmt(r.floor_pct, 2)),
    );
    t.append(tr);
  }
  return t;
}
function shotCard(s) {
  const card = el('div', { class: 'shotcard', 'data-id': s.id });
  if (state.shot && state.shot.id === s.id) card.classList.add('selected');
  const parts = [s.id, s.status, sourceText(s.source)];
  if (s.localisation) parts.push(`${s.localisation.inliers} inliers, ${fmt(s.localisation.rms_error_px, 2)} px`);
  else if (s.reason) parts.push(s.reason);
  if (s.mission) {
    // As read back from the vehicle at start / reconnection, with why.
    const v = s.mission.details && s.mission.details.vehicle;
    parts.push(`mission ${s.mission.state}${v && v.reason ? ` (${v.reason})` : ''}, ${s.mission.items} items`);
  }
  const head = el('div', { class: 'head' }, parts.join(' · '));
  head.addEventListener('click', () => showShot(s));
  card.append(head);
  const rf = s.mission && s.mission.details && s.mission.details.refinement;
  if (rf) {
    const rounds = Array.isArray(rf.rounds) ? rf.rounds : [];
    if (rounds.length) card.append(roundsTable(rounds));
    const st = stopText(rf);
    card.append(el('div', { class: 'stop', 'data-stop': st.key }, st.text));
  } else if (s.mission && s.mission.state === 'started') {
    card.append(el('div', { class: 'stop', 'data-stop': 'running' }, 'refining… (waiting for the first arrival)'));
  }
  return card;
}
let shotsBusy = false, shotsSeen = '';
async function refreshShots() {
  if (shotsBusy) return;
  shotsBusy = true;
  try {
    const r = await api('GET', '/shots');
    state.shots = r.shots;
    renderGallery();
    const text = JSON.stringify(r.shots);
    if (text !== shotsSeen) {
      shotsSeen = text;
      const box = $('shots');
      box.textContent = '';
      const shots = [...r.shots].reverse();
      for (const s of shots) box.append(shotCard(s));
      if (!shots.length) box.textContent = 'no shots yet';
      $('shotcount').textContent = `(${r.count})`;
      // The shot in the result pane follows the daemon (rounds arrive while
      // the loop runs).
      const cur = state.shot && r.shots.find((s) => s.id === state.shot.id);
      if (cur && JSON.stringify(cur) !== JSON.stringify(state.shot)) showShot(cur);
    }
  } catch (_) {
  } finally { shotsBusy = false; }
}

// ---- stop -------------------------------------------------------------------------
// Holds the vehicle and cancels the refinement loop; the daemon replies once
// the vehicle acknowledged (or says why it did not).
$('stop').addEventListener('click', async () => {
  const out = $('stopresult');
  $('stop').disabled = true;
  out.dataset.state = 'busy'; out.textContent = 'stopping…';
  try {
    const r = await api('POST', '/vehicle/stop');
    out.dataset.state = 'ok';
    out.textContent = `holding: ${r.mode} acknowledged (${r.ack})` + (r.shot ? ` · ${r.shot} stopped` : '') + (r.refinement_cancelled ? ' · refinement cancelled' : '');
    out.dataset.ack = r.ack; out.dataset.mode = r.mode;
    refreshShots();
  } catch (e) {
    out.dataset.state = 'error'; out.textContent = `stop failed: ${e.message}`;
  } finally { $('stop').disabled = false; }
});

// ---- start ------------------------------------------------------------------------
connectEvents();
refreshKeyframes();
refreshMap();
setInterval(refreshMap, 2000);
setInterval(refreshKeyframes, 3000);
refreshShots();
// Shot events refresh the shots panel; this only catches what they miss.
setInterval(refreshShots, 10000);
