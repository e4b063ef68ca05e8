// Viewer test: serves the pages and a flexsplat scene from localhost, loads the .glb in Babylon.js, PlayCanvas and
// three.js inside Debian's headless chromium (SwiftShader WebGL), screenshots the file's camera and reports the
// PSNR of each screenshot against flexsplat's own render of that camera.
//   node run.mjs SCENE_DIR [--min-psnr DB] [--viewers babylon,playcanvas,three]
// SCENE_DIR holds scene.glb and reference.png (build/examples/viewer_scene writes both).
import { createServer } from 'node:http';
import { readFileSync, writeFileSync, mkdtempSync, rmSync, existsSync } from 'node:fs';
import { join, extname, resolve, dirname } from 'node:path';
import { tmpdir } from 'node:os';
import { fileURLToPath } from 'node:url';
import puppeteer from 'puppeteer-core';
import { PNG } from 'pngjs';

const here = dirname(fileURLToPath(import.meta.url));
const args = process.argv.slice(2);
const option = (name, fallback) => {
  const i = args.indexOf(name);
  if (i < 0) return fallback;
  const value = args[i + 1];
  args.splice(i, 2);
  return value;
};
const minPsnr = Number(option("--min-psnr", "25"));
const viewers = option('--viewers', 'babylon,playcanvas,three').split(',');
const timeoutMs = Number(option('--timeout', '240')) * 1000;
if (args.length !== 1) {
  console.error('usage: node run.mjs SCENE_DIR [--min-psnr DB] [--viewers babylon,playcanvas,three] [--timeout S]');
  process.exit(2);
}
const sceneDir = resolve(args[0]);
const reference = PNG.sync.read(readFileSync(join(sceneDir, 'reference.png')));
const { width, height } = reference;

// The camera node of the glb, for viewers whose loader does not create glTF cameras.
function glbCamera(path) {
  const glb = readFileSync(path);
  const json = JSON.parse(glb.subarray(20, 20 + glb.readUInt32LE(12)).toString('utf8'));
  const node = json.nodes.find((n) => n.camera !== undefined);
  if (!node) throw new Error(`${path}: no camera node`);
  return { translation: node.translation, rotation: node.rotation, yfov: json.cameras[node.camera].perspective.yfov };
}
const camera = glbCamera(join(sceneDir, 'scene.glb'));

const types = { '.html': 'text/html', '.js': 'text/javascript', '.mjs': 'text/javascript', '.json': 'application/json',
                '.glb': 'model/gltf-binary', '.png': 'image/png', '.wasm': 'application/wasm', '.map': 'application/json' };
const server = createServer((req, res) => {
  const url = new URL(req.url, 'http://localhost');
  let path = decodeURIComponent(url.pathname);
  const root = path.startsWith('/scene/') ? sceneDir : here;
  if (path.startsWith('/scene/')) path = path.slice('/scene'.length);
  const file = resolve(join(root, path));
  if (!file.startsWith(root) || !existsSync(file)) {
    if (!path.endsWith('favicon.ico')) console.error(`404 ${req.url}`);
    res.writeHead(404);
    res.end();
    return;
  }
  res.writeHead(200, { 'Content-Type': types[extname(file)] || 'application/octet-stream' });
  res.end(readFileSync(file));
});
await new Promise((ok) => server.listen(0, '127.0.0.1', ok));
const port = server.address().port;

function psnr(a, b) {
  let sum = 0;
  for (let i = 0; i < width * height; ++i)
    for (let c = 0; c < 3; ++c) {
      const d = a.data[i * 4 + c] - b.data[i * 4 + c];
      sum += d * d;
    }
  const mse = sum / (width * height * 3);
  return mse === 0 ? Infinity : 10 * Math.log10((255 * 255) / mse);
}

const profile = mkdtempSync(join(tmpdir(), 'flexsplat-chromium-'));
const browser = await puppeteer.launch({
  executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
  headless: true,
  userDataDir: profile,
  args: ['--no-sandbox', '--disable-gpu', '--use-angle=swiftshader', '--enable-unsafe-swiftshader',
         '--disable-background-networking', '--disable-component-update', '--disable-sync', '--no-first-run',
         '--disable-dev-shm-usage', `--window-size=${width},${height}`],
});
let failures = 0;
const results = [];
try {
  for (const viewer of viewers) {
    const page = await browser.newPage();
    const log = [];
    page.on('console', (m) => log.push(`${m.type()}: ${m.text()}`));
    page.on('pageerror', (e) => log.push(`pageerror: ${e.message}`));
    await page.setViewport({ width, height, deviceScaleFactor: 1 });
    const query = new URLSearchParams({ viewer, glb: '/scene/scene.glb', w: width, h: height, camera: JSON.stringify(camera) });
    const started = Date.now();
    let row;
    try {
      await page.goto(`http://127.0.0.1:${port}/page.html?${query}`, { waitUntil: 'load', timeout: timeoutMs });
      await page.waitForFunction('window.__ready || window.__error', { timeout: timeoutMs, polling: 250 });
      const error = await page.evaluate('window.__error');
      if (error) throw new Error(error);
      const info = await page.evaluate('window.__viewerInfo');
      const shot = PNG.sync.read(await page.screenshot({ clip: { x: 0, y: 0, width, height }, omitBackground: false }));
      writeFileSync(join(sceneDir, `${viewer}.png`), PNG.sync.write(shot));
      const db = psnr(shot, reference);
      row = { viewer, info, psnr: db, seconds: (Date.now() - started) / 1000 };
      if (!(db >= minPsnr)) failures += 1;
    } catch (e) {
      failures += 1;
      row = { viewer, error: String(e.message || e).split('\n').slice(0, 6).join('\n'), log: log.slice(-15) };
    }
    results.push(row);
    await page.close();
  }
} finally {
  await browser.close();
  server.close();
  rmSync(profile, { recursive: true, force: true });
}
for (const r of results) {
  if (r.error) {
    console.log(`${r.viewer}: FAILED to render: ${r.error}`);
    for (const line of r.log) console.log(`    ${line}`);
  } else {
    console.log(`${r.viewer}: PSNR ${r.psnr.toFixed(2)} dB vs flexsplat (${r.seconds.toFixed(1)} s; ${r.info}); ` +
                `screenshot ${join(sceneDir, r.viewer + '.png')}`);
  }
}
console.log(failures === 0 ? `viewers: PASS (every PSNR >= ${minPsnr} dB)` : `viewers: FAIL (${failures} of ${viewers.length})`);
process.exit(failures === 0 ? 0 : 1);
