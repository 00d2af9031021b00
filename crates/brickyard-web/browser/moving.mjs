// A view dragged in headless Chromium, as a user turns it:
//   node moving.mjs CHROMIUM OUT_DIR PAGE_URL
// Opens PAGE_URL, waits until its view is complete, then drags across the
// canvas with the mouse (small steps, a frame's time apart) and records
// every status the page sets and the canvas once mid-drag; lets go
// and waits until the view is complete again. OUT_DIR/moving.json gets
// the status before the drag, every status the page set from the press to
// the release (`drag_log`) and every text of its status line meanwhile
// (`drag_text`), the canvas's size
// and lit pixels mid-drag, the status and URL at the end; OUT_DIR/end.rgba
// the final canvas (straight RGBA); `rest_long_tasks` the durations (ms) of
// the page's tasks over 50 ms from letting go until the view is complete
// (the browser's long-task timing). Exits non-zero on any failure.
import { chromium } from 'playwright-core';
import { writeFileSync } from 'node:fs';
import { execFileSync } from 'node:child_process';

const [exe0, out, url] = process.argv.slice(2);
const exe = exe0.includes('/') ? exe0 : execFileSync('which', [exe0]).toString().trim();
const args = ['--no-sandbox', '--enable-unsafe-webgpu', '--disable-background-networking',
  '--disable-component-update', '--no-first-run', '--use-angle=swiftshader', '--enable-features=Vulkan'];
const browser = await chromium.launch({ executablePath: exe, args, headless: true });
const report = {};
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

async function waitComplete(page) {
  await page.waitForFunction(() => {
    const b = window.brickyard;
    return b && (b.error || (b.status && b.status.complete));
  }, null, { timeout: 300000, polling: 50 });
  const e = await page.evaluate(() => window.brickyard.error);
  if (e) throw new Error(`the page reports: ${e}`);
  return await page.evaluate(() => window.brickyard.status);
}

try {
  const page = await browser.newPage({ viewport: { width: 1400, height: 1000 } });
  const logs = [];
  page.on('pageerror', (e) => logs.push('pageerror: ' + e.message));
  await page.addInitScript(() => {
    window.longTasks = [];
    new PerformanceObserver((l) => { for (const e of l.getEntries()) window.longTasks.push(e.duration); })
      .observe({ type: 'longtask' });
  });
  await page.goto(url);
  report.before = await waitComplete(page);
  // Every status the page sets from here on (one per call of its frame
  // loop) and every text its status line shows: what the drag drew does
  // not depend on when this script looks.
  await page.evaluate(() => {
    const s = window.brickyard;
    let v = s.status;
    window.statusLog = [];
    Object.defineProperty(s, 'status', {
      get() { return v; },
      set(x) { v = x; window.statusLog.push(x); },
    });
    window.textLog = [];
    new MutationObserver(() => window.textLog.push(document.getElementById('status').textContent))
      .observe(document.getElementById('status'), { childList: true, characterData: true, subtree: true });
  });
  const box = await page.locator('#view').boundingBox();
  const [x0, y] = [box.x + box.width * 0.3, box.y + box.height * 0.5];
  await page.mouse.move(x0, y);
  await page.mouse.down();
  for (let i = 1; i <= 12; i++) {
    await page.mouse.move(x0 + 6 * i, y);
    await sleep(60);
    if (i === 8) {
      report.mid_canvas = await page.evaluate(() => {
        const c = document.getElementById('view');
        const px = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let lit = 0;
        for (let k = 0; k < px.length; k += 4) if (px[k] + px[k + 1] + px[k + 2] > 24) lit++;
        return { width: c.width, height: c.height, lit, text: document.getElementById('status').textContent };
      });
    }
  }
  await page.evaluate(() => { window.longTasks = []; });
  await page.mouse.up();
  [report.drag_log, report.drag_text] = await page.evaluate(() => {
    const l = [window.statusLog, window.textLog];
    window.statusLog = []; window.textLog = [];
    return l;
  });
  report.end = await waitComplete(page);
  await sleep(100);
  report.rest_long_tasks = await page.evaluate(() => window.longTasks);
  const r = await page.evaluate(() => {
    const c = document.getElementById('view');
    return { width: c.width, height: c.height, data: Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data), url: location.href };
  });
  writeFileSync(`${out}/end.rgba`, Buffer.from(r.data));
  report.width = r.width; report.height = r.height; report.url = r.url;
  report.logs = logs;
  writeFileSync(`${out}/moving.json`, JSON.stringify(report, null, 1));
  await browser.close();
} catch (e) {
  report.failure = String(e && e.stack || e);
  writeFileSync(`${out}/moving.json`, JSON.stringify(report, null, 1));
  await browser.close();
  console.error(report.failure);
  process.exit(1);
}
