// The page: the view lives in the URL (#store=…&mode=…), the viewer
// (WebAssembly) draws into the canvas each animation frame while
// anything is left to load, and the controls edit the URL's view.
import init, { Viewer } from './brickyard_web.js';

const $ = (id) => document.getElementById(id);
const hashParams = () => new URLSearchParams(location.hash.slice(1));
const state = { viewer: null, store: null, status: null, error: null, webgpu: null };
window.brickyard = state;

function showError(msg) {
  state.error = String(msg);
  $('error').textContent = state.error;
}

async function webgpuAvailable() {
  if (!navigator.gpu) return false;
  try { return !!(await navigator.gpu.requestAdapter()); } catch { return false; }
}

async function remoteOffered() {
  try { const r = await fetch(new URL('../remote', location.href), { method: 'HEAD' }); return r.ok; } catch { return false; }
}

// The URL's `#…` as it is, for the viewer: it reads the view's keys,
// leaves the page's own (store, pool, backend, token) to the page, and
// refuses by name a key it does not know or one given twice.
function viewQuery() {
  return location.hash.slice(1);
}

function writeUrl(query) {
  const pool = hashParams().get('pool');
  const backend = hashParams().get('backend');
  const token = hashParams().get('token');
  const h = 'store=' + encodeURIComponent(state.store) + (pool ? '&pool=' + pool : '') +
    (backend ? '&backend=' + backend : '') + (token ? '&token=' + encodeURIComponent(token) : '') +
    (query ? '&' + query : '');
  if (location.hash.slice(1) !== h) history.replaceState(null, '', '#' + h);
}

function syncControls(q) {
  const p = new URLSearchParams(q);
  $('mode').value = p.get('mode') || 'dvr';
  $('tf').value = p.get('tf') || '';
  $('slice').value = p.get('slice') || '0.5';
  // (`slice` places a slice's plane: of mode=slice only.)
  $('slice').disabled = (p.get('mode') || 'dvr') !== 'slice';
  $('bias').value = p.get('bias') || '0';
  $('traversal').value = p.get('traversal') || '';
  $('traversal').disabled = (p.get('mode') || 'dvr') !== 'dvr';
  const ch = state.multi ? (p.get('channels') || p.get('channel') || 'all') : (p.get('channel') || '0');
  // A choice of several (`channels=0,2`) gets an entry of its own.
  if (![...$('channel').options].some((o) => o.value === ch)) {
    const o = document.createElement('option'); o.value = ch; o.textContent = `${ch.split(',').join(' + ')} (composited)`;
    $('channel').appendChild(o);
  }
  $('channel').value = ch;
  const info = JSON.parse(state.viewer.info());
  const w = (p.get('window') || '').split(',').map(Number);
  const [lo, hi] = w.length === 2 && w.every(Number.isFinite) ? w : info.window;
  $('wlo').value = lo; $('whi').value = hi;
  $('wtext').textContent = `${lo} – ${hi}`;
}

function setView(changes) {
  const p = new URLSearchParams(state.viewer.query());
  for (const [k, v] of Object.entries(changes)) {
    if (v === null) p.delete(k); else p.set(k, v);
  }
  try {
    state.viewer.set_query(p.toString());
    state.error = null; $('error').textContent = '';
  } catch (e) { showError(e); }
  writeUrl(state.viewer.query());
  syncControls(state.viewer.query());
  wake();
}

let histAt = 0;
function drawHistogram() {
  const c = $('hist'), g = c.getContext('2d');
  const h = state.viewer.histogram();
  const info = JSON.parse(state.viewer.info());
  g.fillStyle = '#000'; g.fillRect(0, 0, c.width, c.height);
  let max = 1;
  for (let i = 1; i < h.length; i++) max = Math.max(max, h[i]);
  g.fillStyle = '#888';
  for (let i = 0; i < h.length; i++) {
    const v = Math.log1p(h[i]) / Math.log1p(max) * c.height;
    g.fillRect(i * c.width / h.length, c.height - v, c.width / h.length, v);
  }
  const [d0, d1] = info.window;
  const x = (v) => (v - d0) / (d1 - d0) * c.width;
  const lo = Number($('wlo').value), hi = Number($('whi').value);
  g.strokeStyle = '#fc6'; g.beginPath();
  g.moveTo(x(lo), c.height); g.lineTo(x(hi), 0); g.stroke();
}

let running = false;
function wake() { if (!running) { running = true; requestAnimationFrame(tick); } }
// The next part of a frame drawn in parts: at once, as a task of its own
// (input and painting go between tasks), not a display frame later.
const partChannel = new MessageChannel();
partChannel.port1.onmessage = () => tick();

async function tick() {
  let st;
  try { st = JSON.parse(await state.viewer.frame()); } catch (e) { showError(e); running = false; return; }
  state.status = st;
  writeUrl(st.query);
  // Failing bricks and their reason, as the native viewer retries them.
  // A server found unreachable is not asked for each brick: the view is
  // drawn from what it has, and the server asked again every 20 s.
  const lf = st.labels && st.labels.failed;
  const failing = st.unreachable
    ? '\nthe server cannot be reached: the view is drawn from the data loaded before' +
      (st.failed || lf ? ` (failing bricks: ${st.failed}${lf ? `, labels: ${lf}` : ''})` : '') +
      ', nothing more is asked for; the server is tried again every 20 s' +
      (st.failures ? `\nlast: ${st.last_failure}` : '')
    : st.failed || lf ?
    `\nfailing bricks: ${st.failed}${lf ? ` (labels: ${lf})` : ''}, drawn from coarser data` +
    (st.store_changed ? '' : ' and asked for again every 20 s') +
    (st.failures ? `\nlast: ${st.last_failure}` : '') : '';
  // The LOD bias: as asked for (bias=), or raised by the pool's size.
  const sign = (b) => (b > 0 ? '+' : '') + b;
  const bias = st.bias > st.bias_asked
    ? `  (LOD bias ${sign(st.bias)}${st.bias_asked ? `, ${sign(st.bias_asked)} asked for` : ''}: the pool is too small for full detail)`
    : st.bias_asked ? `  (LOD bias ${sign(st.bias_asked)}, as asked for)` : '';
  $('status').textContent =
    (st.store_changed ? 'the store changed on the server since it was opened: reload\n' : '') +
    `${st.complete ? (st.degraded ? 'complete (degraded)' : 'complete') : 'loading'}  ${(100 * st.completeness).toFixed(1)} % exact` +
    `${bias}\n` +
    `bricks: ${st.resident} resident of ${st.pool_slots}, ${st.loaded} loaded, ${st.in_flight} in flight, ${st.queued} queued\n` +
    `read: ${(st.bytes / 1048576).toFixed(1)} MiB` +
    (st.in_flight + st.queued > 0 ? ` at ${st.mib_s.toFixed(1)} MiB/s` : '') + '\n' +
    `frame: ${st.frame_ms.toFixed(0)} ms${st.on_device ? ' (WebGPU)' : ' (CPU)'}` +
    (st.parts > 1 ? ` in ${st.parts} parts` : '') +
    (st.scale < 1 ? ` at ${Math.round(100 * st.scale)} % size while moving` : '') +
    (st.first_complete_ms ? `, first complete after ${(st.first_complete_ms / 1000).toFixed(2)} s` : '') +
    failing +
    (st.labels ? `\nlabels/${st.labels.name}: ${st.labels.complete ? 'complete' : 'loading'}, ${st.labels.resident} bricks resident` +
      (st.labels.failed ? `, ${st.labels.failed} failing (last: ${st.labels.last_failure})` : '') : '');
  // At most once a second while loading, and once the view completes
  // (a view complete within a second kept the histogram of its first
  // frame, drawn before any brick had arrived: an empty box).
  const now = performance.now();
  if (now - histAt > 1000 || (st.complete && !dragging)) { histAt = now; drawHistogram(); }
  if (st.complete && !dragging) {
    running = false;
    // Bricks failing: come back to ask for them again (the viewer does
    // every 20 s) and to check the store, without a frame meanwhile.
    // (A server found unreachable: to probe it every 20 s.)
    if (st.failed || lf || st.unreachable) setTimeout(wake, 2000);
    return;
  }
  if (st.tiles_left > 0) partChannel.port2.postMessage(0);
  else requestAnimationFrame(tick);
}

// The readout under the pointer: in a slice, the voxel there; in 3D, the
// point the pixel shows (the MIP's maximum, the DVR's half-opacity point,
// the first label drawn). Position, values, label.
function showProbe(e) {
  const c = $('view'), r = c.getBoundingClientRect();
  const x = (e.clientX - r.left) * c.width / r.width, y = (e.clientY - r.top) * c.height / r.height;
  const t = state.viewer.probe(x, y);
  if (!t) { $('probe').textContent = ''; return; }
  const p = JSON.parse(t), [vz, vy, vx] = p.voxel_zyx;
  const vals = p.values.map((v, i) => v ? `${p.values.length > 1 ? `ch${i} ` : ''}${+v.value.toPrecision(6)}${v.level ? ` (level ${v.level})` : ''}` : 'not loaded');
  const lab = p.labels === undefined ? '' : p.labels ? ` · label ${p.labels.label}${p.labels.level ? ` (level ${p.labels.level})` : ''}` : ' · label not loaded';
  const seen = p.seen ? `${p.seen.how}${p.seen.level ? ` (level ${p.seen.level})` : ''}, ` : '';
  $('probe').textContent = `${seen}voxel x ${vx} y ${vy} z ${vz}: ${vals.join(', ')}${lab}`;
}

// The labels of an `only_labels` list (`3,17,40-45`), one by one.
function labelList(text) {
  const out = [];
  for (const part of (text || '').split(',').filter((x) => x)) {
    const m = part.match(/^(-?\d+)-(-?\d+)$/);
    if (m) { for (let i = +m[1]; i <= +m[2] && out.length < 65536; i++) out.push(i); } else out.push(+part);
  }
  return out;
}

function pickAt(e) {
  const c = $('view'), r = c.getBoundingClientRect();
  const t = state.viewer.probe((e.clientX - r.left) * c.width / r.width, (e.clientY - r.top) * c.height / r.height);
  if (!t) return;
  // (The label drawn there: of the labels laid over, or of a label image.)
  const p = JSON.parse(t), id = p.labels && p.labels.label;
  if (!id) return;
  const q = new URLSearchParams(state.viewer.query());
  if (q.get('hide_labels')) return;
  const ids = labelList(q.get('only_labels'));
  const i = ids.indexOf(id);
  if (i >= 0) ids.splice(i, 1); else ids.push(id);
  ids.sort((a, b) => a - b);
  setView({ only_labels: ids.length ? ids.join(',') : null });
}

let dragging = false;
function wireControls() {
  const view = $('view');
  let last = null;
  let down = null;
  view.addEventListener('pointerdown', (e) => { dragging = true; last = down = [e.clientX, e.clientY]; view.setPointerCapture(e.pointerId); wake(); });
  view.addEventListener('pointermove', (e) => {
    if (!dragging) { showProbe(e); return; }
    state.viewer.orbit(-(e.clientX - last[0]) * 0.4, (e.clientY - last[1]) * 0.4);
    last = [e.clientX, e.clientY];
    wake();
  });
  view.addEventListener('pointerup', (e) => {
    dragging = false;
    // A click (no drag) on a label (of a slice, or a label image's
    // surface in 3D) picks it: only_labels gains it, or loses it.
    if (down && Math.hypot(e.clientX - down[0], e.clientY - down[1]) < 3) pickAt(e);
    wake();
  });
  view.addEventListener('wheel', (e) => { e.preventDefault(); state.viewer.zoom(e.deltaY < 0 ? 1.1 : 1 / 1.1); wake(); }, { passive: false });
  // The transfer function's window, dragged on the histogram: the nearer
  // end follows the pointer.
  const hist = $('hist');
  let histDrag = null;
  const histValue = (e) => {
    const info = JSON.parse(state.viewer.info());
    const [d0, d1] = info.window;
    const r = hist.getBoundingClientRect();
    return d0 + (e.clientX - r.left) / r.width * (d1 - d0);
  };
  hist.addEventListener('pointerdown', (e) => {
    const v = histValue(e);
    const lo = Number($('wlo').value), hi = Number($('whi').value);
    histDrag = Math.abs(v - lo) < Math.abs(v - hi) ? 'wlo' : 'whi';
    hist.setPointerCapture(e.pointerId);
  });
  hist.addEventListener('pointermove', (e) => {
    if (!histDrag) return;
    const v = Number(histValue(e).toPrecision(6));
    const lo = histDrag === 'wlo' ? v : Number($('wlo').value);
    const hi = histDrag === 'whi' ? v : Number($('whi').value);
    if (hi > lo) { state.viewer.moving(); $(histDrag).value = v; setView({ window: `${lo},${hi}` }); histAt = 0; }
  });
  hist.addEventListener('pointerup', () => { histDrag = null; });
  // The octree draws DVR: other modes go through the page tables.
  // (`slice` belongs to slices.)
  $('mode').onchange = () => setView($('mode').value === 'dvr' ? { mode: null, slice: null }
    : { mode: $('mode').value, traversal: null, slice: $('mode').value === 'slice' ? $('slice').value : null });
  $('traversal').onchange = () => setView({ traversal: $('traversal').value || null });
  $('tf').onchange = () => setView({ tf: $('tf').value || null });
  const win = () => setView({ window: `${$('wlo').value},${$('whi').value}` });
  $('wlo').onchange = win; $('whi').onchange = win;
  $('channel').onchange = () => state.multi
    ? setView({ channels: $('channel').value === 'all' ? null : $('channel').value, channel: null, window: null })
    : setView({ channel: $('channel').value === '0' ? null : $('channel').value, window: null });
  $('slice').oninput = () => setView({ slice: $('slice').value });
  $('bias').oninput = () => state.viewer.moving() || setView({ bias: $('bias').value === '0' ? null : $('bias').value });
  window.addEventListener('hashchange', () => {
    // What the viewer was opened with (the store, its labels, the pool,
    // who draws, the token) changes only by opening it again.
    const h = hashParams();
    if (h.get('store') !== state.store || h.get('labels') !== state.labels || h.get('pool') !== state.opened.pool ||
      h.get('backend') !== state.opened.backend || h.get('token') !== state.opened.token) { location.reload(); return; }
    try { state.viewer.set_query(viewQuery()); syncControls(state.viewer.query()); wake(); } catch (e) { showError(e); }
  });
}

async function main() {
  await init();
  state.webgpu = await webgpuAvailable();
  const store = hashParams().get('store');
  if (!store) {
    $('open').style.display = 'block';
    $('open').onsubmit = (e) => { e.preventDefault(); location.hash = 'store=' + encodeURIComponent($('url').value); location.reload(); };
    return;
  }
  state.store = store;
  state.labels = hashParams().get('labels');
  state.opened = { pool: hashParams().get('pool'), backend: hashParams().get('backend'), token: hashParams().get('token') };
  const backend = hashParams().get('backend') || 'auto';
  let notice = state.webgpu
    ? ''
    : 'WebGPU is not available in this browser: drawing on the CPU in WebAssembly.';
  if (!state.webgpu && await remoteOffered()) notice += '\nThe server also renders remotely: ';
  $('notice').textContent = notice;
  if (!state.webgpu && await remoteOffered()) {
    const a = document.createElement('a'); a.href = new URL('../remote', location.href).href; a.textContent = 'open the remote-rendering client';
    $('notice').appendChild(a);
  }
  const pool = hashParams().get('pool');
  try {
    state.viewer = await Viewer.open(new URL(store, location.href).href, $('view'), viewQuery(), pool,
      state.webgpu || !['auto', 'gpu'].includes(backend) ? backend : 'cpu', hashParams().get('token'));
  } catch (e) { showError(e); return; }
  const info = JSON.parse(state.viewer.info());
  state.device = info.device;
  if (info.device) $('notice').textContent = `Drawing through WebGPU (${info.device}).`;
  else if (state.webgpu && info.device_note) $('notice').textContent = `WebGPU not used: ${info.device_note}. Drawing on the CPU in WebAssembly.`;
  else if (state.webgpu) $('notice').textContent = 'Drawing on the CPU in WebAssembly (backend=cpu).';
  // A damaged statistics array costs speed (its bricks are loaded to learn
  // what they hold), not the view: say so.
  if (info.stats_problems.length) $('notice').textContent += `\nBrick statistics: ${info.stats_problems.length} problem(s), e.g. ${info.stats_problems[0]}`;
  state.multi = info.n_channels > 1;
  if (state.multi) { const o = document.createElement('option'); o.value = 'all'; o.textContent = 'all active (composited)'; $('channel').appendChild(o); }
  info.channels.forEach((label, i) => { const o = document.createElement('option'); o.value = String(i); o.textContent = `${i}: ${label}`; $('channel').appendChild(o); });
  if (info.channels.length === 0) { const o = document.createElement('option'); o.value = '0'; o.textContent = '0'; $('channel').appendChild(o); }
  syncControls(state.viewer.query());
  wireControls();
  wake();
}

main().catch(showError);
