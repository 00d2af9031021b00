// End-to-end check of the web client in headless Chromium:
//   node e2e.mjs CHROMIUM PAGE_URL OUT_DIR
// 1. open PAGE_URL (a #store=…&view), wait until the view is complete,
//    save the canvas's pixels (OUT_DIR/canvas.rgba, straight RGBA) and
//    the page's figures;
// 2. open the URL the page wrote in a page without WebGPU (navigator.gpu
//    removed before the page runs): the link reopens the same view, and
//    the page says WebGPU is missing and still draws it, on the CPU, with
//    the same pixels. (One page checks both: a software WebGPU page takes
//    over a minute to compile its shaders and load on a 2-core machine.)
// Writes OUT_DIR/report.json; exits non-zero on any failure.
import { chromium } from 'playwright-core';
import { writeFileSync } from 'node:fs';

const [exe0, url, out] = process.argv.slice(2);
// A bare name is looked up on PATH.
import { execFileSync } from 'node:child_process';
const exe = exe0.includes('/') ? exe0 : execFileSync('which', [exe0]).toString().trim();
const report = {};
const args = ['--no-sandbox', '--enable-unsafe-webgpu', '--disable-background-networking',
  '--disable-component-update', '--no-first-run', '--use-angle=swiftshader', '--enable-features=Vulkan'];
const browser = await chromium.launch({ executablePath: exe, args, headless: true });

async function waitComplete(page, what) {
  const t0 = Date.now();
  await page.waitForFunction(() => {
    const b = window.brickyard;
    return b && (b.error || (b.status && b.status.complete));
  }, null, { timeout: 180000, polling: 100 });
  const b = await page.evaluate(() => ({ error: window.brickyard.error, status: window.brickyard.status, webgpu: window.brickyard.webgpu }));
  if (b.error) throw new Error(`${what}: the page reports: ${b.error}`);
  b.wall_ms = Date.now() - t0;
  return b;
}

async function canvasPixels(page) {
  return await page.evaluate(() => {
    const c = document.getElementById('view');
    const g = c.getContext('2d');
    return { w: c.width, h: c.height, data: Array.from(g.getImageData(0, 0, c.width, c.height).data) };
  });
}

try {
  const page = await browser.newPage();
  const logs = [];
  page.on('console', (m) => logs.push(m.text()));
  page.on('pageerror', (e) => logs.push('pageerror: ' + e.message));
  const t0 = Date.now();
  await page.goto(url);
  await page.waitForFunction(() => window.brickyard && (window.brickyard.error || (window.brickyard.status && window.brickyard.status.frames >= 1)), null, { timeout: 120000, polling: 20 });
  report.first_frame_ms = Date.now() - t0;
  const first = await waitComplete(page, 'first load');
  report.complete_ms = Date.now() - t0;
  // The histogram of the complete view: its grey bars' pixels (a view
  // complete within a second kept an empty box; the page's colour space
  // shows #888 as another grey).
  report.hist_bar_pixels = await page.evaluate(() => {
    const c = document.getElementById('hist');
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let i = 0; i < d.length; i += 4) if (d[i] > 0 && d[i] === d[i + 1] && d[i + 1] === d[i + 2]) n++;
    return n;
  });
  report.status = first.status;
  report.webgpu = first.webgpu;
  report.device = await page.evaluate(() => window.brickyard.device || null);
  // Frame times of a full redraw: turn the view by a little, twice
  // (bench.mjs measures more).
  const times = [];
  for (let i = 0; i < 2; i++) {
    const ms = await page.evaluate(async () => {
      const v = window.brickyard.viewer;
      const q = v.query();
      // (Set, not appended: a key given twice is refused.)
      const nudged = new URLSearchParams(q); nudged.set('zoom', String(Number(nudged.get('zoom') || 1) * 1.0001));
      v.set_query(nudged.toString());
      const t = performance.now();
      await v.frame();
      const ms = performance.now() - t;
      v.set_query(q);
      await v.frame();
      return ms;
    });
    times.push(ms);
  }
  report.redraw_ms = times;
  await waitComplete(page, 'after redraws');
  const px = await canvasPixels(page);
  writeFileSync(`${out}/canvas.rgba`, Buffer.from(px.data));
  report.width = px.w; report.height = px.h;
  report.url = page.url();
  // 2. The URL the page wrote reopens the same view, in a page without WebGPU.
  const ctx = await browser.newContext();
  await ctx.addInitScript(() => { Object.defineProperty(Navigator.prototype, 'gpu', { get: () => undefined, configurable: true }); });
  const nogpu = await ctx.newPage();
  await nogpu.goto(report.url);
  const third = await waitComplete(nogpu, 'the link without WebGPU');
  report.reload_url = nogpu.url();
  report.reload_status = third.status;
  report.fallback_notice = await nogpu.evaluate(() => document.getElementById('notice').textContent);
  report.fallback_webgpu = third.webgpu;
  const px3 = await canvasPixels(nogpu);
  report.fallback_max_diff = px3.w === px.w && px3.h === px.h ? px3.data.reduce((m, v, i) => Math.max(m, Math.abs(v - px.data[i])), 0) : 999;
  writeFileSync(`${out}/canvas-cpu.rgba`, Buffer.from(px3.data));
  // A bad view in the URL: an error naming the key, no crash.
  const bad = await browser.newPage();
  await bad.goto(report.url.replace(/#.*/, '#store=' + encodeURIComponent(new URL(report.url).hash.match(/store=([^&]*)/)[1] ? decodeURIComponent(new URL(report.url).hash.match(/store=([^&]*)/)[1]) : '') + '&mode=volume'));
  await bad.waitForFunction(() => window.brickyard && window.brickyard.error, null, { timeout: 60000 });
  report.bad_query_error = await bad.evaluate(() => window.brickyard.error);
  report.console = logs.slice(0, 20);
  writeFileSync(`${out}/report.json`, JSON.stringify(report, null, 1));
  await browser.close();
} catch (e) {
  report.failure = String(e && e.stack || e);
  writeFileSync(`${out}/report.json`, JSON.stringify(report, null, 1));
  await browser.close();
  console.error(report.failure);
  process.exit(1);
}
