// UI latency benchmark (issue 7: "a touch that changes the view shows a new picture within
// 150 ms, a smaller picture first, refined after"). Starts cortexfused (its simulators, a fresh
// state folder, as tests/ui/e2e.mjs does), imports the phantom case, uploads an fMRI map, runs a
// short registration and the plan job (so the fused view has its textured surface and layers),
// then drives the UI in Debian's chromium (playwright-core, headless, touch) with real touch
// events (CDP Input.dispatchTouchEvent) and measures, for each kind of view-changing touch,
// the time from the touch event (its timeStamp in the page) to
//   first:   the first picture of the touched view (or a newer one) drawn: its <img> src set,
//            decoded (img.decode()) and a requestAnimationFrame after that;
//   refined: the same for the first full-size picture of the view the gesture ended on.
// Pictures carry the number of the view they show (img data-seq, window.cfViewSeq in
// ui/src/main.ts), so an older picture still arriving is not counted.
// Prints one JSON object (stdout; --out FILE too): per viewport size and kind median/p90/max of
// first and refined, the sizes seen, the renderer, the daemon's peak RSS (VmHWM), the load
// average. Log lines go to stderr. No threshold is asserted here (see docs/performance.md).
//
// Usage: node bench/ui_latency.mjs --daemon BUILD/daemon/cortexfused --ui UI_DIR
//          [--repeats 10] [--sizes 1280x800,1920x1080] [--renderer auto|gl|cpu] [--quick]
//          [--kinds a,b,...] [--out FILE] [--shots DIR]
// Exit 0 done, 1 failed, 77 skipped (no chromium / playwright-core).
import { spawn } from "node:child_process";
import { createRequire } from "node:module";
import fs from "node:fs";
import os from "node:os";
import path from "node:path";
import { activationMap } from "../tests/ui/e2e_fused_modalities.mjs";

const args = { repeats: 10, sizes: "1280x800,1920x1080", renderer: "auto", quick: false, kinds: "", out: "", shots: "", daemon: "", ui: "" };
for (let i = 2; i < process.argv.length; i++) {
  const a = process.argv[i];
  if (a === "--quick") { args.quick = true; continue; }
  const m = /^--(\w+)$/.exec(a);
  if (!m || !(m[1] in args) || i + 1 >= process.argv.length) { console.error(`ui_latency: unknown or incomplete argument '${a}'`); process.exit(2); }
  args[m[1]] = process.argv[++i];
}
if (args.quick && !process.argv.includes("--repeats")) args.repeats = 2;
if (args.quick && !process.argv.includes("--sizes")) args.sizes = "1280x800";
const REPEATS = Number(args.repeats);
if (!args.daemon || !args.ui || !(REPEATS >= 1)) { console.error("usage: ui_latency.mjs --daemon CORTEXFUSED --ui UI_DIR [--repeats N] ..."); process.exit(2); }
if (!["auto", "gl", "cpu"].includes(args.renderer)) { console.error(`ui_latency --renderer: '${args.renderer}' is not auto, gl or cpu`); process.exit(2); }
const sizes = args.sizes.split(",").map((s) => { const m = /^(\d+)x(\d+)$/.exec(s.trim()); if (!m) { console.error(`ui_latency --sizes: '${s}' is not WxH`); process.exit(2); } return { width: +m[1], height: +m[2] }; });
const daemonBin = path.resolve(args.daemon), uiDir = path.resolve(args.ui);
const repoRoot = path.resolve(path.dirname(new URL(import.meta.url).pathname), "..");

const CHROMIUM = process.env.CF_CHROMIUM ?? "/usr/bin/chromium";
if (!fs.existsSync(CHROMIUM)) { console.log(`SKIP: no ${CHROMIUM}`); process.exit(77); }
if (!fs.existsSync(path.join(uiDir, "node_modules", "playwright-core"))) { console.log("SKIP: ui/node_modules missing (npm ci)"); process.exit(77); }
if (!fs.existsSync(path.join(uiDir, "dist", "index.html"))) { console.error("FAIL: ui/dist/index.html missing: build the UI (cd ui && npm ci && npm run build)"); process.exit(1); }
if (!fs.existsSync(daemonBin)) { console.error(`FAIL: ${daemonBin}: no such daemon binary`); process.exit(1); }
const { chromium } = createRequire(path.join(uiDir, "package.json"))("playwright-core");

const log = (s) => console.error(`[ui_latency] ${s}`);
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const loadavg = () => fs.readFileSync("/proc/loadavg", "utf8").split(" ").slice(0, 3).map(Number);
const statusKb = (pid, key) => { try { const m = new RegExp(`^${key}:\\s+(\\d+) kB`, "m").exec(fs.readFileSync(`/proc/${pid}/status`, "utf8")); return m ? Number(m[1]) : null; } catch { return null; } };

const tmp = fs.mkdtempSync(path.join(os.tmpdir(), "cf-ui-latency-"));
const config = path.join(tmp, "config.json");
fs.writeFileSync(config, JSON.stringify({
  http: { listen: "127.0.0.1:0", ui_dir: path.join(uiDir, "dist") },
  state_dir: path.join(tmp, "state"),
  renderer: { kind: args.renderer },
}));

let daemon = null, browser = null, daemonErr = "", peakKb = null;
const startDaemon = () => new Promise((resolve, reject) => {
  const proc = spawn(daemonBin, ["--config", config], { stdio: ["ignore", "pipe", "pipe"] });
  let out = "";
  proc.stderr.on("data", (d) => { daemonErr += d; if (daemonErr.length > 20000) daemonErr = daemonErr.slice(-10000); });
  const t = setTimeout(() => reject(new Error(`cortexfused did not start in 30 s: ${daemonErr.slice(-2000)}`)), 30000);
  proc.stdout.on("data", (d) => {
    out += d;
    const m = /listening on (http:\/\/[^\s]+)/.exec(out);
    if (m) { clearTimeout(t); resolve({ proc, base: m[1].replace(/\/$/, "") }); }
  });
  proc.on("exit", (c, sig) => { clearTimeout(t); if (!proc.stopping) reject(new Error(`cortexfused exited (code ${c}, signal ${sig}): ${daemonErr.slice(-2000)}`)); });
});
const stopDaemon = async () => {
  if (!daemon || daemon.exitCode !== null || daemon.signalCode !== null) return;
  daemon.stopping = true;
  daemon.kill("SIGTERM");
  await new Promise((r) => { const t = setTimeout(() => { daemon.kill("SIGKILL"); r(); }, 10000); daemon.on("exit", () => { clearTimeout(t); r(); }); });
};

/** JSON over HTTP from loopback (the daemon needs no login there); throws naming the request. */
const api = async (base, method, p, body, raw) => {
  const r = await fetch(`${base}${p}`, { method, body: raw ?? (body === undefined ? undefined : JSON.stringify(body)),
                                          headers: { "Content-Type": raw ? "application/octet-stream" : "application/json" } });
  const text = await r.text();
  if (!r.ok) throw new Error(`${method} ${p}: HTTP ${r.status}: ${text.slice(0, 300)}`);
  try { return JSON.parse(text); } catch { return text; }
};
const waitJob = async (base, id, what, limitS) => {
  const t0 = Date.now();
  for (;;) {
    const j = await api(base, "GET", `/api/jobs/${id}`);
    if (j.state === "succeeded") return j;
    if (["failed", "cancelled"].includes(j.state)) throw new Error(`${what} job ${id} ${j.state}: ${JSON.stringify(j.error ?? j).slice(0, 300)}`);
    if (Date.now() - t0 > limitS * 1000) throw new Error(`${what} job ${id} not done in ${limitS} s (state ${j.state})`);
    await sleep(250);
  }
};

// A short registration: one stage of a few evaluations at 96 px from the landmark pose. The
// benchmark needs a succeeded run to draw the fused view from, not a good one.
const QUICK_REGISTRATION = { starts: [[0, 0, 0, 0, 0, 0]], search_stages: [], search_keep: 0, keep_best: 1, estimate_light: false,
                             final_stages: [{ name: "bench", fwhm_mm: 4, step_mm: 1, step_deg: 1, render_width_px: 96, max_evaluations: 6 }], refine_stages: [] };

const stats = (xs) => {
  const v = xs.filter((x) => Number.isFinite(x)).sort((a, b) => a - b);
  if (!v.length) return { n: 0, median: null, p90: null, max: null, min: null };
  const q = (p) => { const k = (v.length - 1) * p, lo = Math.floor(k), hi = Math.ceil(k); return +(v[lo] + (v[hi] - v[lo]) * (k - lo)).toFixed(1); };
  return { n: v.length, median: q(0.5), p90: q(0.9), max: +v[v.length - 1].toFixed(1), min: +v[0].toFixed(1) };
};

// In the page, before its scripts: the touch events' times and every picture drawn (an <img>
// with data-seq whose src changed: decoded, then the next animation frame).
const RECORDER = () => {
  const lat = { touches: [], pics: [] };
  window.__lat = lat;
  window.addEventListener("click", (e) => lat.touches.push({ type: "click", t: e.timeStamp, on: e.target?.dataset?.testid ?? e.target?.tagName }), { capture: true });
  for (const type of ["touchstart", "touchmove", "touchend"])
    window.addEventListener(type, (e) => lat.touches.push({ type, t: e.timeStamp }), { capture: true, passive: true });
  const watch = () => new MutationObserver((muts) => {
    for (const m of muts) {
      const img = m.target;
      if (!(img instanceof HTMLImageElement) || img.dataset.seq === undefined || !img.src) continue;
      const seq = Number(img.dataset.seq), full = img.dataset.full, tSet = performance.now(), src = img.src, name = img.dataset.testid;
      img.decode().then(() => requestAnimationFrame(() => {
        if (img.src === src) lat.pics.push({ name, seq, full, tSet, t: performance.now(), w: img.naturalWidth, h: img.naturalHeight });
      }), () => undefined);
    }
  }).observe(document.documentElement, { subtree: true, attributes: true, attributeFilter: ["src"] });
  if (document.documentElement) watch(); else document.addEventListener("DOMContentLoaded", watch);
};

const result = { benchmark: "ui_latency", issue: 7, target_first_ms: 150, utc_start: new Date().toISOString(), quick: args.quick, repeats: REPEATS,
                 machine: { cores: os.cpus().length, cpu: os.cpus()[0]?.model ?? "", loadavg_start: loadavg() },
                 how: "time from the touch event (its timeStamp in the page) to the picture drawn: <img> src set, decoded, next animation frame; first = first picture of the touched view or a newer one, refined = first full-size picture of the view the gesture ended on",
                 sizes: [] };
let failed = false;
// Stopped by a signal: the browser and the daemon go too, and the scratch folder.
for (const sig of ["SIGINT", "SIGTERM"])
  process.on(sig, async () => {
    log(`${sig}: stopping the browser and the daemon`);
    if (browser) await browser.close().catch(() => undefined);
    await stopDaemon();
    fs.rmSync(tmp, { recursive: true, force: true });
    process.exit(130);
  });
try {
  const tSetup = Date.now();
  let base;
  ({ proc: daemon, base } = await startDaemon());
  log(`daemon at ${base} (pid ${daemon.pid})`);
  // The phantom case the daemon generates at start, imported into the store.
  for (let i = 0; ; i++) {
    const f = await api(base, "GET", "/api/case-folders");
    if ((f.folders ?? []).includes("phantom/case_0000")) break;
    if (i > 600) throw new Error("no phantom/case_0000 after 150 s");
    await sleep(250);
  }
  const imp = await api(base, "POST", "/api/cases/import", { folder: "phantom/case_0000" });
  const caseId = imp.id ?? imp.case_id ?? imp.case?.id;
  if (!(caseId > 0)) throw new Error(`import answered no case id: ${JSON.stringify(imp).slice(0, 200)}`);
  await api(base, "POST", `/api/cases/${caseId}/volumes?name=fmri_bench.nii.gz&modality=fMRI`, undefined,
            activationMap(path.join(repoRoot, "data", "brainmask_mne_ecog_binary.nii.gz")));
  const reg = await api(base, "POST", "/api/jobs", { kind: "register", params: { case_id: caseId, params: QUICK_REGISTRATION } });
  const plan = await api(base, "POST", "/api/jobs", { kind: "plan", params: { case_id: caseId } });
  await waitJob(base, reg.id, "register", 300);
  await waitJob(base, plan.id, "plan", 300);
  const st = await api(base, "GET", "/api/status");
  log(`case ${caseId} registered and planned in ${((Date.now() - tSetup) / 1000).toFixed(1)} s; renderer ${JSON.stringify(st.modules?.renderer?.backend)}`);
  result.setup_s = +((Date.now() - tSetup) / 1000).toFixed(1);
  result.case_id = caseId;

  browser = await chromium.launchPersistentContext(path.join(tmp, "chromium"), {
    executablePath: CHROMIUM, headless: true,
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
           "--disable-component-update", "--disable-sync"],
    viewport: sizes[0], hasTouch: true,
  });
  const page = browser.pages()[0] ?? await browser.newPage();
  const pageErrors = [];
  page.on("pageerror", (e) => pageErrors.push(String(e)));
  await page.addInitScript(RECORDER);
  const cdp = await browser.newCDPSession(page);
  const touch = (type, pts) => cdp.send("Input.dispatchTouchEvent", { type, touchPoints: pts.map((p, i) => ({ x: Math.round(p.x), y: Math.round(p.y), id: p.id ?? i + 1 })) });
  // A control's centre on the screen (scrolled into view first: the controls column scrolls).
  const boxOf = async (loc, what) => {
    await loc.scrollIntoViewIfNeeded({ timeout: 10000 });
    const b = await loc.boundingBox();
    if (!b) throw new Error(`${what} is not on the screen`);
    return { x: b.x + b.width / 2, y: b.y + b.height / 2, b };
  };
  const centre = (testid, nth = 0) => boxOf(page.getByTestId(testid).nth(nth), testid);
  const tapAt = async (p) => { await touch("touchStart", [p]); await touch("touchEnd", []); };
  const lat = () => page.evaluate(() => ({ seq: window.cfViewSeq(), nt: window.__lat.touches.length, np: window.__lat.pics.length }));

  /** One measured touch: `gesture(mark)` dispatches it and calls mark() right before the event
   *  that changes the view; waits for the refined picture; answers {first_ms, refined_ms, sizes}. */
  const measure = async (imgTestid, gesture, limitMs = 30000) => {
    let before = null;
    await gesture(async () => { before = await lat(); });
    if (!before) throw new Error("the gesture marked no touch");
    // The view changes with the touch, or once a request it makes is answered (Camera view asks
    // the daemon for the camera first).
    try {
      await page.waitForFunction((s) => window.cfViewSeq() > s, before.seq, { timeout: 10000, polling: 10 });
    } catch {
      if (process.env.CF_UI_LATENCY_DEBUG) log(JSON.stringify(await page.evaluate((n) => window.__lat.touches.slice(n), before.nt)));
      const banners = await page.evaluate(() => [...document.querySelectorAll('[data-testid="error-banner"]')].map((b) => b.textContent).join(" | "));
      throw new Error(`the touch did not change the view (view ${before.seq} -> ${await page.evaluate(() => window.cfViewSeq())})${banners ? `; banners: ${banners}` : ""}`);
    }
    const after = await lat();
    const r = await page.waitForFunction(([b, a, name]) => {
      const L = window.__lat, touch = L.touches[b.nt];
      if (!touch) return null;
      const pics = L.pics.slice(b.np).filter((p) => p.name === name);
      const first = pics.find((p) => p.seq > b.seq), refined = pics.find((p) => p.seq >= window.cfViewSeq() && p.full === "true" && p.seq >= a.seq);
      if (!first || !refined) return null;
      return { t0: touch.t, type: touch.type, first: first.t - touch.t, firstSize: `${first.w}x${first.h}`, refined: refined.t - touch.t,
               refinedSize: `${refined.w}x${refined.h}`, pics: pics.length };
    }, [before, after, imgTestid], { timeout: limitMs, polling: 20 });
    return r.jsonValue();
  };

  const kindsWanted = args.kinds ? new Set(args.kinds.split(",")) : null;
  for (const size of sizes) {
    await page.setViewportSize(size);
    const sz = { viewport: `${size.width}x${size.height}`, kinds: {} };
    result.sizes.push(sz);
    const run = async (kind, img, n, gesture, warmIndex = 1, between = 150) => {
      if (kindsWanted && !kindsWanted.has(kind)) return;
      const samples = [];
      // One touch first, not counted (its time is reported as warmup_ms): the first use of a
      // preset or layer prepares the daemon's renderer for it (seconds), which is not what
      // repeated touches cost.
      let warmup = null;
      try { warmup = await measure(img, (mark) => gesture(mark, warmIndex)); } catch (e) { log(`${sz.viewport} ${kind} warm-up: ${String(e.message ?? e).slice(0, 200)}`); }
      await sleep(between);
      for (let i = 0; i < n; i++) {
        try {
          samples.push(await measure(img, (mark) => gesture(mark, i)));
        } catch (e) {
          samples.push({ error: String(e.message ?? e).slice(0, 300) });
          log(`${sz.viewport} ${kind} #${i}: ${String(e.message ?? e).slice(0, 200)}`);
        }
        await sleep(between);
      }
      const ok = samples.filter((s) => !s.error);
      const k = { first_ms: stats(ok.map((s) => s.first)), refined_ms: stats(ok.map((s) => s.refined)),
                  first_size: [...new Set(ok.map((s) => s.firstSize))].join(","), refined_size: [...new Set(ok.map((s) => s.refinedSize))].join(","),
                  warmup_ms: warmup ? [+warmup.first.toFixed(1), +warmup.refined.toFixed(1)] : null,
                  errors: samples.length - ok.length, samples_ms: ok.map((s) => [+s.first.toFixed(1), +s.refined.toFixed(1)]) };
      sz.kinds[kind] = k;
      log(`${sz.viewport} ${kind}: first median ${k.first_ms.median} ms (p90 ${k.first_ms.p90}, max ${k.first_ms.max}) ${k.first_size}; refined median ${k.refined_ms.median} ms ${k.refined_size}${k.errors ? `; ${k.errors} errors` : ""}`);
      if (args.shots) await page.screenshot({ path: path.join(args.shots, `ui-latency-${sz.viewport}-${kind}.png`) });
    };
    if (args.shots) fs.mkdirSync(args.shots, { recursive: true });

    // ---- The case view (#/case/N): the case's T1 rendered by the daemon.
    await page.goto(`${base}/#/case/${caseId}`);
    await page.waitForFunction(() => document.querySelector('[data-testid="render-image"]')?.dataset.full === "true" &&
                                     document.querySelector('[data-testid="render-stage"]')?.dataset.orbit === "free", null, { timeout: 60000 });
    await page.getByTestId("presets").getByRole("button", { name: "cortex t1" }).waitFor({ timeout: 20000 });
    await sleep(500);
    // A one-finger drag step: finger down, 12 px sideways (4.8 degrees), lifted.
    await run("orbit_drag", "render-image", REPEATS, async (mark, i) => {
      const stage = await centre("render-stage");
      const dx = i % 2 ? -12 : 12;
      await touch("touchStart", [{ x: stage.x, y: stage.y }]);
      await mark();
      await touch("touchMove", [{ x: stage.x + dx, y: stage.y }]);
      await touch("touchEnd", []);
    });
    // A touch while the full-size picture of the previous step is being made (the finger moves
    // again 230 ms after the preview: the 200 ms rest has just sent the full size).
    await run("orbit_drag_during_refine", "render-image", REPEATS, async (mark, i) => {
      const stage = await centre("render-stage");
      const dx = i % 2 ? -10 : 10;
      await touch("touchStart", [{ x: stage.x, y: stage.y }]);
      const s0 = await lat();
      await touch("touchMove", [{ x: stage.x + dx, y: stage.y }]);
      await page.waitForFunction((s) => window.__lat.pics.slice(s.np).some((p) => p.seq > s.seq), s0, { timeout: 30000, polling: 10 });
      await sleep(230);
      await mark();
      await touch("touchMove", [{ x: stage.x + 2 * dx, y: stage.y }]);
      await touch("touchEnd", []);
    });
    // Two fingers spread (or closed) by 16 px each.
    await run("pinch_zoom", "render-image", REPEATS, async (mark, i) => {
      const stage = await centre("render-stage");
      const d0 = 60, d1 = i % 2 ? 44 : 76;
      await touch("touchStart", [{ x: stage.x - d0, y: stage.y, id: 1 }, { x: stage.x + d0, y: stage.y, id: 2 }]);
      await mark();
      await touch("touchMove", [{ x: stage.x - d1, y: stage.y, id: 1 }, { x: stage.x + d1, y: stage.y, id: 2 }]);
      await touch("touchEnd", []);
    });
    const presetNames = ["surface white", "skin", "cortex t1"];  // the warm-up (1) is the first skin
    await run("preset_button", "render-image", REPEATS, async (mark, i) => {
      const p = await boxOf(page.getByTestId("presets").getByRole("button", { name: presetNames[i % presetNames.length], exact: true }), "preset button");
      await touch("touchStart", [p]);
      await mark();
      await touch("touchEnd", []);
    });
    const viewNames = ["anterior", "left", "superior", "right", "posterior", "inferior"];
    await run("view_button", "render-image", REPEATS, async (mark, i) => {
      const p = await boxOf(page.locator(`.choices .btn[data-value="${viewNames[i % viewNames.length]}"]`), "view button");
      await touch("touchStart", [p]);
      await mark();
      await touch("touchEnd", []);
    });
    // The transfer function: the cortex preset's ramp point dragged down and up by touch.
    await page.getByTestId("presets").getByRole("button", { name: "cortex t1", exact: true }).tap();
    await page.waitForFunction(() => document.querySelector('[data-testid="render-image"]').dataset.tf === "cortex_t1" &&
                                     document.querySelector('[data-testid="render-image"]').dataset.full === "true", null, { timeout: 30000 });
    const presetsJson = await api(base, "GET", "/api/render/presets");
    const op = presetsJson.transfer_functions.cortex_t1.opacity;
    const mid = op.find((p) => p[1] > 0.2 && p[1] < 0.9) ?? op[op.length - 1];
    const PAD = 14;  // tf_editor.ts: the plot inside the canvas
    let tfOff = null;  // the point's place in the canvas (CSS px from its corner)
    await run("tf_point_drag", "render-image", REPEATS, async (mark, i) => {
      const tfBox = (await centre("tf-canvas")).b;
      tfOff ??= { x: PAD + mid[0] * (tfBox.width - 2 * PAD), y: PAD + (1 - mid[1]) * (tfBox.height - 2 * PAD) };
      const dy = i % 2 ? -6 : 6;
      await touch("touchStart", [{ x: tfBox.x + tfOff.x, y: tfBox.y + tfOff.y }]);
      await mark();
      await touch("touchMove", [{ x: tfBox.x + tfOff.x, y: tfBox.y + tfOff.y + dy }]);
      await touch("touchEnd", []);
      tfOff.y += dy;
    });
    // The opacity slider: the thumb dragged by a finger (5 % steps).
    const slide = async (testid, mark, i, thumbFrac) => {
      const b = (await centre(testid)).b;
      const x0 = b.x + 12 + (await thumbFrac()) * (b.width - 24), y = b.y + b.height / 2;
      const x1 = x0 + (i % 2 ? 1 : -1) * Math.max(0.12 * b.width, 20);
      await touch("touchStart", [{ x: x0, y }]);
      await mark();
      await touch("touchMove", [{ x: x1, y }]);
      await touch("touchEnd", []);
    };
    const sliderFrac = (testid) => async () => page.getByTestId(testid).evaluate((e) => (Number(e.value) - Number(e.min)) / (Number(e.max) - Number(e.min)));
    await run("opacity_slider", "render-image", REPEATS, async (mark, i) => slide("opacity", mark, i, await sliderFrac("opacity")), 0);
    // Back to a known view for the next size.
    await page.getByTestId("presets").getByRole("button", { name: "cortex t1", exact: true }).tap();
    await sleep(1500);

    // ---- The fused view (#/case/N/fused): the photo on the planned surface over the T1 and fMRI.
    await page.goto(`${base}/#/case/${caseId}/fused`);
    await page.waitForFunction(() => document.querySelector('[data-testid="fused-model"]')?.dataset.textured === "true" &&
                                     document.querySelector('[data-testid="fused-model"]')?.dataset.full === "true", null, { timeout: 90000 });
    await sleep(800);
    const hasLayers = await page.getByTestId("fused-modality-fmri").count() > 0;
    sz.fused_layers = hasLayers ? "t1,fmri" : "t1 (no GL: the daemon refuses the layers)";
    await run("fused_drag", "fused-model", REPEATS, async (mark, i) => {
      const fstage = await centre("fused-stage");
      const dx = i % 2 ? -40 : 40;
      await touch("touchStart", [{ x: fstage.x, y: fstage.y }]);
      await mark();
      await touch("touchMove", [{ x: fstage.x + dx / 2, y: fstage.y }]);
      await touch("touchMove", [{ x: fstage.x + dx, y: fstage.y }]);
      await touch("touchEnd", []);
    });
    await run("fused_pinch", "fused-model", REPEATS, async (mark, i) => {
      const fstage = await centre("fused-stage");
      const d0 = 60, d1 = i % 2 ? 50 : 72;
      await touch("touchStart", [{ x: fstage.x - d0, y: fstage.y, id: 1 }]);
      await touch("touchStart", [{ x: fstage.x - d0, y: fstage.y, id: 1 }, { x: fstage.x + d0, y: fstage.y, id: 2 }]);
      await mark();
      await touch("touchMove", [{ x: fstage.x - d1, y: fstage.y, id: 1 }, { x: fstage.x + d1, y: fstage.y, id: 2 }]);
      await touch("touchEnd", []);
    });
    await run("fused_camera_view", "fused-model", REPEATS, async (mark, i) => {
      const fstage = await centre("fused-stage");
      if (i > 0) {  // turned away first (not measured), then back to the camera by the button
        const s0 = await lat();
        await touch("touchStart", [{ x: fstage.x, y: fstage.y }]);
        await touch("touchMove", [{ x: fstage.x + 30, y: fstage.y }]);
        await sleep(120);  // the finger rests before it lifts: no fling (a tap during a fling makes no click)
        await touch("touchMove", [{ x: fstage.x + 30, y: fstage.y }]);
        await touch("touchEnd", []);
        await page.waitForFunction((s) => window.__lat.pics.slice(s.np).some((p) => p.seq > s.seq && p.full === "true" && p.seq === window.cfViewSeq()), s0, { timeout: 30000, polling: 20 });
        await sleep(400);  // apart from the drag (no double tap)
      }
      const p = await centre("fused-camera-view");
      await touch("touchStart", [p]);
      await mark();
      await touch("touchEnd", []);
    });
    await run("fused_opacity_slider", "fused-model", REPEATS, async (mark, i) => slide("fused-opacity", mark, i, await sliderFrac("fused-opacity")), 0);
    if (hasLayers) {
      await run("fused_modality_toggle", "fused-model", REPEATS, async (mark) => {
        const p = await centre("fused-modality-fmri");
        await touch("touchStart", [p]);
        await mark();
        await touch("touchEnd", []);
      });
      if (await page.getByTestId("fused-modality-fmri").getAttribute("data-visible") !== "true") {
        await page.getByTestId("fused-modality-fmri").tap();
        await sleep(2000);
      }
      await run("fused_modality_weight", "fused-model", REPEATS, async (mark, i) => slide("fused-weight-fmri", mark, i, await sliderFrac("fused-weight-fmri")), 0);
    }
  }
  if (pageErrors.length) throw new Error(`page errors: ${pageErrors.join("; ").slice(0, 500)}`);
  const st2 = await api(base, "GET", "/api/status");
  result.renderer = st2.modules?.renderer?.backend ?? null;
  result.renderer_reason = st2.modules?.renderer?.backend_reason ?? null;
  result.renderer_requested = args.renderer;
} catch (e) {
  failed = true;
  result.error = String(e?.stack ?? e).slice(0, 2000);
  log(`FAILED: ${result.error}`);
} finally {
  if (daemon) {
    peakKb = statusKb(daemon.pid, "VmHWM");
    result.daemon = { peak_rss_mb: peakKb === null ? null : +(peakKb / 1024).toFixed(1), rss_mb_end: +((statusKb(daemon.pid, "VmRSS") ?? 0) / 1024).toFixed(1) };
  }
  result.bench_process_peak_rss_mb = +(process.resourceUsage().maxRSS / 1024).toFixed(1);
  if (browser) await browser.close().catch(() => undefined);
  await stopDaemon();
  if (result.daemon) result.daemon.exit_code = daemon.exitCode;
  result.machine.loadavg_end = loadavg();
  result.utc_end = new Date().toISOString();
  // Interactions whose first picture takes over the target (median or p90).
  result.over_target = [];
  for (const s of result.sizes)
    for (const [k, v] of Object.entries(s.kinds))
      if ((v.first_ms.median ?? 0) > result.target_first_ms || (v.first_ms.p90 ?? 0) > result.target_first_ms)
        result.over_target.push(`${s.viewport} ${k}: first median ${v.first_ms.median} ms, p90 ${v.first_ms.p90} ms`);
  fs.rmSync(tmp, { recursive: true, force: true });
}
const json = JSON.stringify(result, null, 1);
if (args.out) fs.writeFileSync(args.out, json + "\n");
console.log(json);
process.exit(failed ? 1 : 0);
