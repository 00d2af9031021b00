// Figures of the web client in headless Chromium (one line of JSON per run):
//   node bench.mjs CHROMIUM PAGE_URL RUNS
// time to the first frame and to complete over the network, bytes and
// requests, the LOD bias the pool allowed, and the time of full redraws
// of the complete view (the camera nudged each time: every tile drawn).
import { chromium } from 'playwright-core';
import { execFileSync } from 'node:child_process';

const [exe0, url, runs] = process.argv.slice(2);
const exe = exe0.includes('/') ? exe0 : execFileSync('which', [exe0]).toString().trim();
const browser = await chromium.launch({ executablePath: exe, headless: true,
  args: ['--no-sandbox', '--enable-unsafe-webgpu', '--disable-background-networking', '--disable-component-update', '--no-first-run'] });
for (let i = 0; i < Number(runs || 3); i++) {
  const page = await browser.newPage();
  const t0 = Date.now();
  await page.goto(url);
  await page.waitForFunction(() => window.brickyard?.error || window.brickyard?.status?.frames >= 1, null, { timeout: 120000, polling: 10 });
  const first = Date.now() - t0;
  await page.waitForFunction(() => window.brickyard?.error || window.brickyard?.status?.complete, null, { timeout: 300000, polling: 20 });
  const complete = Date.now() - t0;
  const r = await page.evaluate(async () => {
    const b = window.brickyard;
    if (b.error) return { error: b.error };
    const st = b.status;
    const v = b.viewer;
    const q = v.query();
    const times = [];
    for (let k = 1; k <= 5; k++) {
      // (Set, not appended: a key given twice is refused.)
      const nudged = new URLSearchParams(q); nudged.set('zoom', String(Number(nudged.get('zoom') || 1) * (1 + k * 1e-6)));
      v.set_query(nudged.toString());
      const t = performance.now();
      await v.frame();
      times.push(performance.now() - t);
    }
    v.set_query(q);
    const res = performance.getEntriesByType('resource').filter((e) => /\/c\//.test(e.name)).length;
    return { status: st, redraw_ms: times, chunk_requests: res, device: b.device || null };
  });
  console.log(JSON.stringify({ run: i, first_frame_ms: first, complete_ms: complete, ...r,
    bytes: r.status?.bytes, bias: r.status?.bias, loaded: r.status?.loaded, resident: r.status?.resident, pool_slots: r.status?.pool_slots }));
  await page.close();
}
await browser.close();
