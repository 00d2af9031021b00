// Pages drawn in headless Chromium, their canvases saved:
//   node canvas.mjs CHROMIUM OUT_DIR NAME=PAGE_URL [NAME=PAGE_URL ...]
// Each page opens in turn and is waited for until its view is complete;
// OUT_DIR/NAME.rgba gets its canvas's pixels (straight RGBA) and
// OUT_DIR/canvas.json, per NAME, its size, status, the device it drew on
// (null: the CPU), the notice it showed, the URL it wrote and its
// traversal control's value. Exits non-zero on any failure
// (a page's error included).
import { chromium } from 'playwright-core';
import { writeFileSync } from 'node:fs';
import { execFileSync } from 'node:child_process';

const [exe0, out, ...pages] = process.argv.slice(2);
const exe = exe0.includes('/') ? exe0 : execFileSync('which', [exe0]).toString().trim();
const args = ['--no-sandbox', '--enable-unsafe-webgpu', '--disable-background-networking',
  '--disable-component-update', '--no-first-run', '--use-angle=swiftshader', '--enable-features=Vulkan'];
const browser = await chromium.launch({ executablePath: exe, args, headless: true });
const report = {};
try {
  for (const spec of pages) {
    const at = spec.indexOf('=');
    const [name, url] = [spec.slice(0, at), spec.slice(at + 1)];
    const page = await browser.newPage();
    const logs = [];
    page.on('pageerror', (e) => logs.push('pageerror: ' + e.message));
    const t0 = Date.now();
    await page.goto(url);
    await page.waitForFunction(() => {
      const b = window.brickyard;
      return b && (b.error || (b.status && b.status.complete));
    }, null, { timeout: 300000, polling: 100 });
    const r = await page.evaluate(() => {
      const c = document.getElementById('view');
      const px = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
      return {
        error: window.brickyard.error || null, status: window.brickyard.status,
        device: window.brickyard.device || null, notice: document.getElementById('notice').textContent,
        width: c.width, height: c.height, data: Array.from(px), url: location.href,
        traversal: document.getElementById('traversal').value,
      };
    });
    if (r.error) throw new Error(`${name}: the page reports: ${r.error}`);
    writeFileSync(`${out}/${name}.rgba`, Buffer.from(r.data));
    delete r.data;
    r.wall_ms = Date.now() - t0;
    r.logs = logs;
    report[name] = r;
    await page.close();
  }
  writeFileSync(`${out}/canvas.json`, JSON.stringify(report, null, 1));
  await browser.close();
} catch (e) {
  report.failure = String(e && e.stack || e);
  writeFileSync(`${out}/canvas.json`, JSON.stringify(report, null, 1));
  await browser.close();
  console.error(report.failure);
  process.exit(1);
}
