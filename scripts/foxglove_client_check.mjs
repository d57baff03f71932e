// A real-client check of ti-fusion's logs and live view: Foxglove Studio 1.48 (@foxglove/studio-base, the last
// release of the Foxglove app published as a package) runs in Debian's chromium, headless, driven by
// playwright-core; it opens a recorded log.mcap (or connects to a live run), imports the shipped layout
// through its own "Import layout" path, plays the log, and saves screenshots, the Problems list and the
// browser console's errors.
//
//   node scripts/foxglove_client_check.mjs --log RUN/log.mcap [--layout docs/foxglove-layout.json]
//        [--out logs/foxglove-check] [--chromium /usr/bin/chromium] [--seconds 60] [--zoom-out CLICKS]
//   node scripts/foxglove_client_check.mjs --live ws://127.0.0.1:8765 [--relay yes] ...
//   node scripts/foxglove_client_check.mjs --live-frames 300 ...   (starts ti-fusion slam --live itself)
//
// Live: Studio 1.48 offers only the sub-protocol foxglove.websocket.v1, which the Foxglove SDK's server refuses
// (it takes foxglove.sdk.v1, the same protocol renamed). With --relay yes (the default) the browser connects to
// a relay in this script that offers the new name to the server and passes every frame through unchanged, so
// Studio shows the run as a current client would; --relay no connects it directly, to see the refusal.
//
// Needs node >= 18, npm (the client's packages are installed into logs/foxglove-client on first use, pinned
// below) and chromium (`apt-get install -y chromium`). Exit status 0 when the client shows no problem, 1 when
// it lists problems, 2 when it could not run. See docs/LOGS.md, "Checking in a real client".

import { execFileSync, spawn } from "node:child_process";
import fs from "node:fs";
import http from "node:http";
import { createRequire } from "node:module";
import path from "node:path";
import { fileURLToPath } from "node:url";

const ROOT = path.resolve(path.dirname(fileURLToPath(import.meta.url)), "..");
const PACKAGES = { "@foxglove/studio-base": "1.48.0", react: "17.0.2", "react-dom": "17.0.2", "playwright-core": "1.49.1",
  ws: "8.18.0" };
// the brief's flags, and WebGL on the CPU (SwiftShader): the 3D and image panels draw with WebGL
const CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
  "--disable-component-update", "--disable-sync", "--no-first-run", "--use-angle=swiftshader",
  "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"];

function parseArgs(argv) {
  const args = { layout: path.join(ROOT, "docs", "foxglove-layout.json"), out: path.join(ROOT, "logs", "foxglove-check"),
    client: path.join(ROOT, "logs", "foxglove-client"), chromium: "/usr/bin/chromium", log: undefined, live: undefined,
    seconds: 60, width: 1600, height: 1000, relay: "yes", "live-frames": undefined, "zoom-out": 0 };
  for (let i = 0; i < argv.length; i += 2) {
    const key = argv[i].replace(/^--/, "");
    if (!(key in args) || argv[i + 1] == undefined) {
      fail(`unknown option or missing value: ${argv[i]} (options: ${Object.keys(args).map((k) => "--" + k).join(" ")})`);
    }
    args[key] = ["seconds", "width", "height", "live-frames", "zoom-out"].includes(key) ? Number(argv[i + 1]) : argv[i + 1];
  }
  if ([args.log, args.live, args["live-frames"]].filter((a) => a != undefined).length !== 1) {
    fail("give one of --log RUN/log.mcap, --live ws://HOST:PORT, --live-frames N");
  }
  if (args.log != undefined && !fs.existsSync(args.log)) fail(`--log ${args.log}: no such file`);
  if (!fs.existsSync(args.layout)) fail(`--layout ${args.layout}: no such file`);
  if (!fs.existsSync(args.chromium)) fail(`--chromium ${args.chromium}: no such file (apt-get install -y chromium)`);
  return args;
}

function fail(message) {
  console.error(`foxglove_client_check: ${message}`);
  process.exit(2);
}

function installClient(dir) {
  const manifest = { name: "ti-fusion-foxglove-client", private: true, dependencies: PACKAGES };
  const file = path.join(dir, "package.json");
  const wanted = JSON.stringify(manifest, null, 1);
  const have = fs.existsSync(file) ? fs.readFileSync(file, "utf8") : "";
  if (have === wanted && fs.existsSync(path.join(dir, "node_modules", "@foxglove", "studio-base", "assets", "index.js"))) {
    return;
  }
  fs.mkdirSync(dir, { recursive: true });
  fs.writeFileSync(file, wanted);
  console.log(`installing ${Object.entries(PACKAGES).map(([n, v]) => `${n}@${v}`).join(", ")} into ${dir}`);
  execFileSync("npm", ["install", "--no-audit", "--no-fund", "--ignore-scripts"], { cwd: dir, stdio: "inherit" });
}

// The page: React 17 as the bundle's externals, then Studio's App with an in-memory layout storage and app
// configuration, the data sources of Studio's web build, and the URL as its deep link (ds=remote-file or
// ds=foxglove-websocket). showOpenFilePicker hands the import the layout file the server serves.
const PAGE = `<!doctype html>
<html><head><meta charset="utf-8"><title>ti-fusion: Foxglove Studio check</title>
<style>html, body, #root { height: 100%; margin: 0; }</style></head>
<body><div id="root"></div>
<script src="/react.js"></script><script src="/react-dom.js"></script>
<script>window.react = window.React; window["react-dom"] = window.ReactDOM;</script>
<script src="/assets/index.js"></script>
<script>
window.showOpenFilePicker = async () => {
  const text = await (await fetch("/layout.json")).text();
  return [{ getFile: async () => new File([text], window.__layoutName, { type: "application/json" }) }];
};
const layouts = new Map();
const layoutStorage = {
  list: async (ns) => [...layouts.values()].filter((l) => l.ns === ns).map((l) => l.layout),
  get: async (ns, id) => layouts.get(ns + "/" + id)?.layout,
  put: async (ns, layout) => { layouts.set(ns + "/" + layout.id, { ns, layout }); return layout; },
  delete: async (ns, id) => { layouts.delete(ns + "/" + id); },
  importLayouts: async () => {},
  migrateUnnamespacedLayouts: async () => {},
};
const settings = new Map([["telemetry.telemetryEnabled", false], ["telemetry.crashReportingEnabled", false],
                          ["colorScheme", "dark"], ["timezone", "UTC"], ["launchDefault", "web"]]);
const listeners = new Map();
const appConfiguration = {
  get: (key) => settings.get(key),
  set: async (key, value) => { settings.set(key, value); (listeners.get(key) ?? []).forEach((cb) => cb(value)); },
  addChangeListener: (key, cb) => listeners.set(key, [...(listeners.get(key) ?? []), cb]),
  removeChangeListener: (key, cb) => listeners.set(key, (listeners.get(key) ?? []).filter((c) => c !== cb)),
};
(async () => {
  await initI18n();
  const dataSources = [new FoxgloveWebSocketDataSourceFactory(), new RemoteDataSourceFactory(),
                       new McapLocalDataSourceFactory()];
  ReactDOM.render(React.createElement(App, { deepLinks: [window.location.href], appConfiguration, dataSources,
    layoutStorage, extensionLoaders: [], enableLaunchPreferenceScreen: false, enableGlobalCss: true }),
    document.getElementById("root"));
})();
</script></body></html>`;

const notFound = [];
function report404(pathname) {
  notFound.push(pathname);
}

function serve(args) {
  const studio = path.join(args.client, "node_modules", "@foxglove", "studio-base");
  const files = {
    "/index.html": { body: PAGE, type: "text/html" },
    "/react.js": { file: path.join(args.client, "node_modules", "react", "umd", "react.production.min.js") },
    "/react-dom.js": { file: path.join(args.client, "node_modules", "react-dom", "umd", "react-dom.production.min.js") },
    "/layout.json": { file: args.layout, type: "application/json" },
  };
  if (args.log) files["/log.mcap"] = { file: args.log, type: "application/octet-stream" };
  const types = { ".js": "text/javascript", ".wasm": "application/wasm", ".png": "image/png", ".ttf": "font/ttf" };
  const server = http.createServer((req, res) => {
    const url = new URL(req.url, "http://x");
    let entry = files[url.pathname];
    if (!entry && url.pathname.startsWith("/assets/")) {
      const file = path.join(studio, "assets", path.basename(url.pathname));
      if (fs.existsSync(file)) entry = { file };
    }
    if (url.pathname === "/favicon.ico") {  // the browser asks for one: not a problem of the client
      res.writeHead(204).end();
      return;
    }
    if (!entry) {
      report404(url.pathname);
      res.writeHead(404).end();
      return;
    }
    const body = entry.body != undefined ? Buffer.from(entry.body) : fs.readFileSync(entry.file);
    const headers = { "Content-Type": entry.type ?? types[path.extname(entry.file ?? "")] ?? "application/octet-stream",
      "Accept-Ranges": "bytes", "Access-Control-Allow-Origin": "*", "Cache-Control": "no-store" };
    const range = /bytes=(\d+)-(\d*)/.exec(req.headers.range ?? "");
    if (range) {  // the remote-file source reads the log by byte ranges
      const start = Number(range[1]);
      const end = range[2] ? Math.min(Number(range[2]), body.length - 1) : body.length - 1;
      res.writeHead(206, { ...headers, "Content-Range": `bytes ${start}-${end}/${body.length}`, "Content-Length": end - start + 1 });
      res.end(req.method === "HEAD" ? undefined : body.subarray(start, end + 1));
      return;
    }
    res.writeHead(200, { ...headers, "Content-Length": body.length });
    res.end(req.method === "HEAD" ? undefined : body);
  });
  return new Promise((resolve) => server.listen(0, "127.0.0.1", () => resolve(server)));
}

// ti-fusion slam --live on the synthetic sequence, until it prints its URL.
function startRun(args) {
  const out = path.join(args.out, "run");
  const exe = fs.existsSync(path.join(ROOT, ".venv", "bin", "ti-fusion")) ? path.join(ROOT, ".venv", "bin", "ti-fusion") : "ti-fusion";
  const cli = ["slam", "--live", "127.0.0.1:0", "--frames", String(args["live-frames"]), "--downsample", "2", "--out", out];
  console.log(`running ${exe} ${cli.join(" ")}`);
  const proc = spawn(exe, cli, { cwd: ROOT, stdio: ["ignore", "pipe", "pipe"] });
  let output = "";
  return new Promise((resolve, reject) => {
    const onData = (chunk) => {
      output += chunk;
      const match = /live: (ws:\/\/\S+)/.exec(output);
      if (match) resolve({ proc, url: match[1], output: () => output });
    };
    proc.stdout.on("data", onData);
    proc.stderr.on("data", onData);
    proc.on("exit", (code) => reject(new Error(`the run ended (${code}) before serving: ${output}`)));
  });
}

// A WebSocket relay: takes the browser's foxglove.websocket.v1 connection and opens foxglove.sdk.v1 to ``url``.
function relay(args, url) {
  const { WebSocketServer, WebSocket } = createRequire(path.join(args.client, "package.json"))("ws");
  const server = new WebSocketServer({ host: "127.0.0.1", port: 0, handleProtocols: (offered) => [...offered][0] });
  server.on("connection", (client) => {
    const upstream = new WebSocket(url, ["foxglove.sdk.v1"]);
    const queued = [];
    upstream.on("open", () => queued.splice(0).forEach(([data, binary]) => upstream.send(data, { binary })));
    upstream.on("message", (data, binary) => client.send(data, { binary }));
    client.on("message", (data, binary) => (upstream.readyState === WebSocket.OPEN ? upstream.send(data, { binary })
      : queued.push([data, binary])));
    upstream.on("close", () => client.close());
    client.on("close", () => upstream.close());
    upstream.on("error", () => client.close());
  });
  return new Promise((resolve) => server.on("listening", () => resolve(server)));
}

async function main() {
  const args = parseArgs(process.argv.slice(2));
  installClient(args.client);
  const { chromium } = createRequire(path.join(args.client, "package.json"))("playwright-core");
  fs.mkdirSync(args.out, { recursive: true });
  const run = args["live-frames"] != undefined ? await startRun(args) : undefined;
  if (run) args.live = run.url;
  const relayServer = args.live != undefined && args.relay === "yes" ? await relay(args, args.live) : undefined;
  const server = await serve(args);
  const base = `http://127.0.0.1:${server.address().port}`;
  const wsUrl = relayServer ? `ws://127.0.0.1:${relayServer.address().port}` : args.live;
  const source = args.log ? `ds=remote-file&ds.url=${encodeURIComponent(base + "/log.mcap")}`
    : `ds=foxglove-websocket&ds.url=${encodeURIComponent(wsUrl)}`;
  const browser = await chromium.launch({ executablePath: args.chromium, args: CHROMIUM_FLAGS, headless: true });
  const report = { client: "Foxglove Studio 1.48.0 (@foxglove/studio-base)", chromium: browser.version(),
    source: args.log ?? args.live, layout: args.layout, console_errors: [], page_errors: [], alerts: [], problems: [], screenshots: [] };
  try {
    const page = await browser.newPage({ viewport: { width: args.width, height: args.height } });
    page.on("console", (msg) => { if (msg.type() === "error") report.console_errors.push(msg.text().slice(0, 500)); });
    page.on("pageerror", (err) => report.page_errors.push(String(err).slice(0, 500)));
    page.on("response", (res) => { if (res.status() >= 400) report.console_errors.push(`HTTP ${res.status()} ${res.url()}`); });
    await page.addInitScript((name) => { window.__layoutName = name; }, path.basename(args.layout));
    await page.goto(`${base}/index.html?${source}`, { waitUntil: "domcontentloaded", timeout: 180000 });
    const shot = async (name) => {
      const file = path.join(args.out, `${name}.png`);
      await page.screenshot({ path: file });
      report.screenshots.push(file);
      console.log(`screenshot ${file}`);
    };
    await page.locator('[data-sidebar-key="layouts"]').waitFor({ timeout: 180000 });  // the app is up
    await page.waitForTimeout(5000);  // the source opens
    await shot("0-opened");
    await importLayout(page);
    await page.waitForTimeout(3000);
    report.alerts = await page.locator('[role="alert"]').allInnerTexts();  // e.g. "The layout could not be loaded"
    const hint = page.getByText("Open settings to configure topics and layers.");  // a first-run tip over the 3D panel
    if (await hint.count()) await hint.locator("xpath=..").getByRole("button").first().click().catch(() => {});
    await shot("1-layout");
    if (args.log) {
      report.played_to_end = await playToEnd(page, args.seconds);
    } else {
      await page.waitForTimeout(args.seconds * 1000);
    }
    await shot("2-played");
    if (args["zoom-out"] > 0) {
      // a scene larger than the layout's view (a loop of several metres): the mouse wheel over the 3D panel, as a user zooms,
      // at the log's last moment (a long log can be left playing from its start again): paused, the scrubber's right end
      if (await page.locator('[title="Pause"]').count()) await page.locator('[title="Pause"]').first().click();
      const controls = await page.locator('[title="Seek backward"]').first().boundingBox();
      await page.mouse.click(args.width - 3, controls.y - 14);
      await page.waitForTimeout(8000);
      const title = await page.getByText("map and poses", { exact: true }).first().boundingBox();
      await page.mouse.move(title.x + 250, title.y + 250);
      for (let i = 0; i < args["zoom-out"]; i++) {
        await page.mouse.wheel(0, 100);
        await page.waitForTimeout(100);
      }
      await page.waitForTimeout(2000);
      await shot("2-zoomed-out");
    }
    report.panels = await panelsShown(page, JSON.parse(fs.readFileSync(args.layout, "utf8")));
    report.problems = await problems(page);
    await shot("3-problems");
    await page.getByRole("tab", { name: "Topics" }).click();
    await page.waitForTimeout(500);
    report.topics = await page.evaluate(() => document.body.innerText.match(/^\/[a-z_/]+$/gm) ?? []);
    await shot("4-topics");
  } finally {
    await browser.close();
    server.close();
    relayServer?.close();
    if (run) {
      run.proc.kill("SIGTERM");
      await new Promise((resolve) => run.proc.on("exit", resolve));
      report.run_output = run.output().split("\n").filter((l) => /warning|refused|Dropping|live:|frames/.test(l));
    }
  }
  report.topics = [...new Set(report.topics ?? [])].sort();
  report.not_found = notFound;
  report.relay = relayServer != undefined;
  for (const line of report.run_output ?? []) console.log(`run: ${line}`);
  fs.writeFileSync(path.join(args.out, "report.json"), JSON.stringify(report, null, 1) + "\n");
  console.log(`topics: ${report.topics.join(" ")}`);
  console.log(`panels shown: ${report.panels.shown.length} of ${report.panels.shown.length + report.panels.missing.length}` +
    (report.panels.missing.length ? ` (missing: ${report.panels.missing.join(", ")})` : "") +
    (report.panels.unknown_panel_type ? "; an unknown panel type" : ""));
  for (const alert of report.alerts) console.log(`alert: ${alert}`);
  console.log(`problems: ${report.problems.length}`);
  for (const p of report.problems) console.log(`  ${p}`);
  console.log(`console errors: ${report.console_errors.length}; page errors: ${report.page_errors.length}`);
  console.log(`report ${path.join(args.out, "report.json")}`);
  if (report.played_to_end === false) console.log(`the log did not play to its end within ${args.seconds} s`);
  const clean = report.played_to_end !== false && report.problems.length === 0 && report.alerts.length === 0 && report.panels.missing.length === 0 &&
    !report.panels.unknown_panel_type;
  process.exit(clean ? 0 : 1);
}

// The layout menu's import, as a user does it: the layouts sidebar, then its "Import layout" button.
async function importLayout(page) {
  await page.locator('[data-sidebar-key="layouts"]').click();
  await page.waitForTimeout(1000);
  await page.locator('[title="Import layout"]').first().click({ timeout: 60000 });
  await page.waitForTimeout(2000);
}

// Plays the log from its start at Studio's fastest speed (5x) until its end, as a user does, so that every
// message reaches the panels and the 3D panel ends on the last map; gives up after ``seconds``.
async function playToEnd(page, seconds) {
  await page.locator('[data-testid="PlaybackSpeedControls-Dropdown"]').click();
  await page.getByRole("menuitem", { name: "5×", exact: true }).click();
  await page.locator('[title="Play"]').first().click();
  const deadline = Date.now() + seconds * 1000;
  while (Date.now() < deadline && (await page.locator('[title="Pause"]').count())) {
    await page.waitForTimeout(500);
  }
  return (await page.locator('[title="Pause"]').count()) === 0;
}

// The data source sidebar's Problems tab: each problem's message, or none ("No problems found").
async function problems(page) {
  await page.locator('[data-sidebar-key="connection"]').click();
  await page.waitForTimeout(500);
  await page.getByRole("tab", { name: /Problems/ }).click();
  await page.waitForTimeout(1000);
  if (await page.getByText("No problems found").count()) return [];
  return await page.locator(".MuiListItemText-primary").allInnerTexts();
}

// The title of every panel of the layout, and whether the page shows it (a panel type a client lacks shows
// "Unknown panel type" instead of its panel).
async function panelsShown(page, layout) {
  const text = await page.evaluate(() => document.body.innerText);
  if (layout.configById == undefined) {
    return { shown: [], missing: ["(every panel: the layout has no configById, not the classic form)"], unknown_panel_type: false };
  }
  const titles = Object.values(layout.configById).map((c) => c.foxglovePanelTitle).filter(Boolean);
  return { shown: titles.filter((t) => text.includes(t.slice(0, 20))), missing: titles.filter((t) => !text.includes(t.slice(0, 20))),
    unknown_panel_type: text.includes("Unknown panel type") };
}

main().catch((err) => fail(err.stack ?? String(err)));
