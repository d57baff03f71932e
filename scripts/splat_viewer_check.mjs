// A real-client check of `ti-fusion slam --splats`: PlayCanvas's splat-transform reads and converts the run's
// splats.ply, and the three.js viewer @mkkellogg/gaussian-splats-3d renders it in Debian's chromium, headless
// (SwiftShader WebGL), from a page served on localhost; the screenshot shows it from `--back` metres behind the
// run's first camera (trajectory.tum).
//
//   node scripts/splat_viewer_check.mjs RUN_DIR [--png docs/images/splats.png] [--client /tmp/splat-client]
//        [--chromium /usr/bin/chromium] [--back 1.0] [--seconds 20]
//
// Needs node >= 18, npm (the packages, pinned below, are installed into --client, outside the repository, on
// first use) and chromium (`apt-get install -y chromium`). Prints one JSON line: the Gaussians the viewer loaded,
// splat-transform's reading, the browser's errors. Exit status 0 when both read the file, 1 otherwise.
// docs/OUTPUTS.md shows the result.

import { execFileSync } from "node:child_process";
import fs from "node:fs";
import http from "node:http";
import { createRequire } from "node:module";
import path from "node:path";

const PACKAGES = { "@playcanvas/splat-transform": "3.7.0", "@mkkellogg/gaussian-splats-3d": "0.4.7", three: "0.170.0",
  "playwright-core": "1.49.1" };
const args = { png: "splats.png", client: "/tmp/splat-client", chromium: "/usr/bin/chromium", back: 1.0, seconds: 20 };
const argv = process.argv.slice(2);
const run = argv.shift();
for (let i = 0; i < argv.length; i += 2) args[argv[i].replace(/^--/, "")] = argv[i + 1];
if (!run) { console.error("usage: node scripts/splat_viewer_check.mjs RUN_DIR [--png OUT.png]"); process.exit(2); }
const splats = path.resolve(run, "splats.ply");

// the packages, once
fs.mkdirSync(args.client, { recursive: true });
const pkg = path.join(args.client, "package.json");
if (!fs.existsSync(pkg) || JSON.stringify(JSON.parse(fs.readFileSync(pkg)).dependencies) !== JSON.stringify(PACKAGES)) {
  fs.writeFileSync(pkg, JSON.stringify({ name: "splat-client", private: true, dependencies: PACKAGES }));
  execFileSync("npm", ["install", "--no-audit", "--no-fund"], { cwd: args.client, stdio: "inherit" });
}

// splat-transform: read (statistics) and convert
const tool = path.join(args.client, "node_modules", ".bin", "splat-transform");
const stats = execFileSync(tool, ["--no-tty", splats, "--stats", "json", "null"], { encoding: "utf8" });
const converted = path.join(args.client, "splats.compressed.ply");
execFileSync(tool, ["--no-tty", "-w", splats, converted], { encoding: "utf8" });

// the camera: --back metres behind the first pose of trajectory.tum (camera-to-world, x right, y down, z forward)
const first = fs.readFileSync(path.resolve(run, "trajectory.tum"), "utf8").split("\n").find((l) => l && l[0] !== "#");
const [, tx, ty, tz, qx, qy, qz, qw] = first.trim().split(/\s+/).map(Number);
const R = [[1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
  [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
  [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)]];
const forward = [R[0][2], R[1][2], R[2][2]], down = [R[0][1], R[1][1], R[2][1]], t = [tx, ty, tz];
const eye = t.map((v, i) => v - Number(args.back) * forward[i]);
const at = t.map((v, i) => v + forward[i]);
const up = down.map((v) => -v);

const page = `<!doctype html><html><head><meta charset="utf-8"><style>html,body{margin:0;height:100%;background:#000}</style>
<script type="importmap">{"imports": {"three": "/node_modules/three/build/three.module.js",
 "@mkkellogg/gaussian-splats-3d": "/node_modules/@mkkellogg/gaussian-splats-3d/build/gaussian-splats-3d.module.js"}}</script>
</head><body><script type="module">
import * as GS from "@mkkellogg/gaussian-splats-3d";
const viewer = new GS.Viewer({cameraUp: ${JSON.stringify(up)}, initialCameraPosition: ${JSON.stringify(eye)},
  initialCameraLookAt: ${JSON.stringify(at)}, sharedMemoryForWorkers: false, gpuAcceleratedSort: false,
  enableSIMDInSort: false, sceneRevealMode: GS.SceneRevealMode.Instant, renderMode: GS.RenderMode.OnChange});
viewer.addSplatScene("/splats.ply", {format: GS.SceneFormat.Ply, showLoadingUI: false, progressiveLoad: false})
  .then(() => { viewer.start(); window.loaded = viewer.getSplatMesh().getSplatCount(); })
  .catch((e) => { window.failed = String(e); });
</script></body></html>`;
const server = http.createServer((req, res) => {
  const url = decodeURIComponent(req.url.split("?")[0]);
  const file = url === "/splats.ply" ? splats : url.startsWith("/node_modules/") ? path.join(args.client, url) : null;
  if (url === "/") { res.writeHead(200, { "Content-Type": "text/html" }); res.end(page); return; }
  if (url === "/favicon.ico") { res.writeHead(204); res.end(); return; }
  if (!file || !fs.existsSync(file)) { res.writeHead(404); res.end(); return; }
  res.writeHead(200, { "Content-Type": file.endsWith(".js") ? "text/javascript" : "application/octet-stream" });
  fs.createReadStream(file).pipe(res);
}).listen(0, "127.0.0.1");
await new Promise((resolve) => server.on("listening", resolve));

const { chromium } = createRequire(path.join(args.client, "package.json"))("playwright-core");
const browser = await chromium.launch({ executablePath: args.chromium, args: ["--no-sandbox", "--use-angle=swiftshader",
  "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"] });
const tab = await browser.newPage({ viewport: { width: 960, height: 720 } });
const errors = [];
tab.on("console", (m) => { if (m.type() === "error" && !m.text().includes("favicon")) errors.push(m.text()); });
tab.on("requestfailed", (r) => errors.push(`${r.url()}: ${r.failure()?.errorText}`));
tab.on("pageerror", (e) => errors.push(String(e)));
await tab.goto(`http://127.0.0.1:${server.address().port}/`);
await tab.waitForFunction(() => window.loaded !== undefined || window.failed !== undefined, null, { timeout: 600000 });
const loaded = await tab.evaluate(() => window.loaded);
const failed = await tab.evaluate(() => window.failed);
await tab.waitForTimeout(1000 * Number(args.seconds));  // the viewer sorts in a worker: let it draw
await tab.screenshot({ path: args.png, timeout: 300000 });
await browser.close();
server.close();
const read = JSON.parse(stats.slice(stats.indexOf("{"), stats.lastIndexOf("}") + 1));
console.log(JSON.stringify({ viewer_gaussians: loaded ?? null, viewer_error: failed ?? null, browser_errors: errors,
  splat_transform: { gaussians: read.numGaussians, sh_bands: read.shBands, converted: converted,
    converted_bytes: fs.statSync(converted).size }, png: args.png }));
process.exit(loaded > 0 && !failed ? 0 : 1);
