// The page's readout and label picking in headless Chromium (WebGPU
// hidden: the CPU draws, which is quicker to start):
//   node readout.mjs CHROMIUM PAGE_URL OUT_DIR
// 1. open PAGE_URL (a slice with labels=…) and wait until it is complete;
// 2. move the pointer over an 11 × 11 grid of the canvas, keeping every
//    readout line seen;
// 3. click at the first point whose readout names a label (not 0): the URL must gain only_labels=ID; click again: it must
//    lose it.
// Writes OUT_DIR/readout.json; exits non-zero on any failure.
import { chromium } from 'playwright-core';
import { writeFileSync } from 'node:fs';
import { execFileSync } from 'node:child_process';

const [exe0, url, out] = process.argv.slice(2);
const exe = exe0.includes('/') ? exe0 : execFileSync('which', [exe0]).toString().trim();
const args = ['--no-sandbox', '--disable-background-networking', '--disable-component-update', '--no-first-run'];
const browser = await chromium.launch({ executablePath: exe, args, headless: true });
const report = { lines: [] };
try {
  const page = await browser.newPage();
  await page.addInitScript(() => { delete Navigator.prototype.gpu; });
  const complete = async (what) => {
    await page.waitForFunction(() => window.brickyard && (window.brickyard.error || (window.brickyard.status && window.brickyard.status.complete)), null, { timeout: 180000, polling: 100 });
    const e = await page.evaluate(() => window.brickyard.error);
    if (e) throw new Error(`${what}: the page reports: ${e}`);
  };
  await page.goto(url);
  await complete('first load');
  const box = await page.locator('#view').boundingBox();
  const canvas = await page.evaluate(() => [document.getElementById('view').width, document.getElementById('view').height]);
  let at = null;
  for (let j = 1; j < 12; j++) {
    for (let i = 1; i < 12; i++) {
      const [fx, fy] = [i / 12, j / 12];
      await page.mouse.move(box.x + box.width * fx, box.y + box.height * fy);
      const t = await page.locator('#probe').textContent();
      // Canvas pixels of the pointer, for the check of the voxel.
      report.lines.push({ x: fx * canvas[0], y: fy * canvas[1], text: t });
      const m = t.match(/label (\d+)/);
      if (m && m[1] !== '0' && !at) at = [box.x + box.width * fx, box.y + box.height * fy, +m[1]];
    }
  }
  if (!at) throw new Error('the readout named no label');
  report.label = at[2];
  await page.mouse.click(at[0], at[1]);
  await page.waitForTimeout(200);
  await complete('after a click');
  report.hash_after_click = await page.evaluate(() => location.hash);
  await page.mouse.click(at[0], at[1]);
  await page.waitForTimeout(200);
  await complete('after a second click');
  report.hash_after_second_click = await page.evaluate(() => location.hash);
} catch (e) {
  report.error = String(e);
}
writeFileSync(`${out}/readout.json`, JSON.stringify(report, null, 1));
await browser.close();
process.exit(report.error ? 1 : 0);
