// Pages opened in headless Chromium (CPU drawing), each waited for until it
// reports an error or a complete view (or WAIT_MS pass), and what the page
// tells its user recorded:
//   node status.mjs CHROMIUM OUT_DIR WAIT_MS NAME=PAGE_URL [NAME=PAGE_URL ...]
// OUT_DIR/status.json, per NAME: the error shown, the status line's text,
// the viewer's status figures, the notice and the Channel choice shown.
// Exits non-zero only when the driver itself fails.
import { chromium } from 'playwright-core';
import { writeFileSync } from 'node:fs';
import { execFileSync } from 'node:child_process';

const [exe0, out, wait, ...pages] = process.argv.slice(2);
const exe = exe0.includes('/') ? exe0 : execFileSync('which', [exe0]).toString().trim();
const args = ['--no-sandbox', '--disable-background-networking', '--disable-component-update', '--no-first-run'];
const browser = await chromium.launch({ executablePath: exe, args, headless: true });
const report = {};
try {
  for (const spec of pages) {
    const at = spec.indexOf('=');
    const [name, url] = [spec.slice(0, at), spec.slice(at + 1)];
    const page = await browser.newPage();
    await page.goto(url);
    try {
      await page.waitForFunction(() => {
        const b = window.brickyard;
        return b && (b.error || (b.status && b.status.complete));
      }, null, { timeout: Number(wait), polling: 100 });
    } catch { /* not complete in time: reported as it is */ }
    report[name] = await page.evaluate(() => {
      const sel = document.getElementById('channel');
      return {
        error: window.brickyard.error || null, status: window.brickyard.status || null,
        text: document.getElementById('status').textContent,
        notice: document.getElementById('notice').textContent,
        channel: sel.selectedIndex >= 0 ? sel.options[sel.selectedIndex].textContent : '',
      };
    });
    await page.close();
  }
  writeFileSync(`${out}/status.json`, JSON.stringify(report, null, 1));
  await browser.close();
} catch (e) {
  report.failure = String(e && e.stack || e);
  writeFileSync(`${out}/status.json`, JSON.stringify(report, null, 1));
  await browser.close();
  console.error(report.failure);
  process.exit(1);
}
