// End-to-end test of the web UI in Debian's chromium (playwright-core, no downloaded browser)
// against cortexfused started here on a free port with a temporary state folder.
// Usage: node e2e.mjs CORTEXFUSED UI_DIR ARTEFACT_DIR   (exit 0 pass, 1 fail, 77 skip)
import { spawn } from "node:child_process";
import { createRequire } from "node:module";
import fs from "node:fs";
import os from "node:os";
import path from "node:path";

const [daemonBin, uiDir, artDir] = process.argv.slice(2).map((p) => path.resolve(p));
const CHROMIUM = process.env.CF_CHROMIUM ?? "/usr/bin/chromium";
if (!fs.existsSync(CHROMIUM)) { console.log(`SKIP: no ${CHROMIUM}`); process.exit(77); }
if (!fs.existsSync(path.join(uiDir, "node_modules", "playwright-core"))) { console.log("SKIP: ui/node_modules missing (npm ci)"); process.exit(77); }
if (!fs.existsSync(path.join(uiDir, "dist", "index.html"))) { console.error("FAIL: ui/dist/index.html missing: the UI build failed"); process.exit(1); }
const { chromium } = createRequire(path.join(uiDir, "package.json"))("playwright-core");

fs.mkdirSync(artDir, { recursive: true });
const tmp = fs.mkdtempSync(path.join(os.tmpdir(), "cf-ui-e2e-"));
const config = path.join(tmp, "config.json");
fs.writeFileSync(config, JSON.stringify({
  http: { listen: "127.0.0.1:0", ui_dir: path.join(uiDir, "dist") },
  state_dir: path.join(tmp, "state"),
}));

let daemon, browser, failed = false;
const step = (s) => console.log(`[e2e] ${s}`);
const expect = (cond, what) => { if (!cond) throw new Error(`expected: ${what}`); };

try {
  daemon = spawn(daemonBin, ["--config", config], { stdio: ["ignore", "pipe", "pipe"] });
  let daemonErr = "";
  daemon.stderr.on("data", (d) => { daemonErr += d; if (daemonErr.length > 20000) daemonErr = daemonErr.slice(-10000); });
  const base = await new Promise((resolve, reject) => {
    let out = "";
    const t = setTimeout(() => reject(new Error(`daemon did not start in 30 s: ${daemonErr.slice(-2000)}`)), 30000);
    daemon.stdout.on("data", (d) => {
      out += d;
      const m = /listening on (http:\/\/[^\s]+)/.exec(out);
      if (m) { clearTimeout(t); resolve(m[1].replace(/\/$/, "")); }
    });
    daemon.on("exit", (c) => { clearTimeout(t); reject(new Error(`daemon exited ${c}: ${daemonErr.slice(-2000)}`)); });
  });
  step(`daemon at ${base}`);

  // A fresh profile folder each run (playwright passes it as --user-data-dir).
  browser = await chromium.launchPersistentContext(path.join(tmp, "chromium"), {
    executablePath: CHROMIUM, headless: true,
    args: ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
           "--disable-component-update", "--disable-sync"],
    viewport: { width: 1280, height: 800 }, hasTouch: true,
  });
  const page = browser.pages()[0] ?? await browser.newPage();
  const pageErrors = [];
  page.on("pageerror", (e) => pageErrors.push(String(e)));
  const shot = (name) => page.screenshot({ path: path.join(artDir, `${name}.png`) });

  // Cases screen, status bar live from the push channel.
  await page.goto(`${base}/`);
  await page.getByTestId("sb-link").filter({ hasText: "Live" }).waitFor({ timeout: 15000 });
  await page.getByTestId("sb-tracker").filter({ hasText: /streaming \d+ Hz/ }).waitFor({ timeout: 20000 });
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="sb-tools"]')?.dataset.seq) > 0, null, { timeout: 15000 });
  const seq1 = Number(await page.getByTestId("sb-tools").getAttribute("data-seq"));
  await page.waitForTimeout(600);
  const seq2 = Number(await page.getByTestId("sb-tools").getAttribute("data-seq"));
  expect(seq2 > seq1 && seq1 > 0, `tracker frames advancing in the status bar (${seq1} -> ${seq2})`);
  step(`tracker streaming, frames ${seq1} -> ${seq2}`);

  // Bad input: creating a case without a title is refused in plain words.
  await page.getByTestId("create-case").tap();
  await page.getByTestId("error-banner").filter({ hasText: "Type a title" }).waitFor({ timeout: 5000 });
  await page.getByTestId("error-banner").getByRole("button").tap();

  await page.getByTestId("new-case-title").fill("E2E phantom case");
  await shot("01-cases");
  await page.getByTestId("create-case").tap();
  await page.waitForURL(/#\/case\/\d+$/, { timeout: 20000 });
  step(`case created: ${page.url()}`);

  // Case view: a rendered picture at full size.
  const img = page.getByTestId("render-image");
  await page.waitForFunction(() => document.querySelector('[data-testid="render-image"]')?.dataset.full === "true" &&
                                   document.querySelector('[data-testid="render-image"]').naturalWidth > 100, null, { timeout: 30000 });
  const size1 = await img.getAttribute("data-size");
  await shot("02-case-view");
  step(`rendered ${size1}`);

  // Preset and a drag: the picture changes to another view, preview first then full.
  const n0 = await page.evaluate(() => window.cfRenderTimeline.length);
  await page.getByTestId("presets").getByRole("button", { name: "skin" }).tap();
  await page.waitForFunction((n) => window.cfRenderTimeline.slice(n).some((e) => e.what === "full"), n0, { timeout: 30000 });
  const box = await page.getByTestId("render-stage").boundingBox();
  // A finger drag, as real touch events (CDP Input.dispatchTouchEvent), 70 px to the right.
  const cdp = await browser.newCDPSession(page);
  const x0 = box.x + box.width / 2, y0 = box.y + box.height / 2;
  await cdp.send("Input.dispatchTouchEvent", { type: "touchStart", touchPoints: [{ x: x0, y: y0 }] });
  for (let i = 1; i <= 7; i++) {
    await cdp.send("Input.dispatchTouchEvent", { type: "touchMove", touchPoints: [{ x: x0 + 10 * i, y: y0 }] });
    await page.waitForTimeout(16);
  }
  await cdp.send("Input.dispatchTouchEvent", { type: "touchEnd", touchPoints: [] });
  await page.waitForFunction(() => document.querySelector('.choices .btn.active[data-value="anterior"]') !== null, null, { timeout: 5000 });
  await page.waitForFunction(() => document.querySelector('[data-testid="render-image"]')?.dataset.full === "true" &&
                                   /anterior/.test(document.querySelector('.choices .btn.active[data-value="anterior"]')?.dataset.value ?? ""), null, { timeout: 30000 });
  await page.waitForTimeout(1500); // the full-size render after the preview
  await shot("03-case-view-dragged");
  // Two-step sizing: after the view changed, a small picture first, then the full one.
  const tl = await page.evaluate(() => window.cfRenderTimeline);
  const ci = tl.findIndex((e) => e.what === "change");
  expect(ci >= 0, "the drag changed the view");
  const after = tl.slice(ci + 1);
  const pi = after.findIndex((e) => e.what === "preview");
  const fi = after.findIndex((e, i) => i > pi && e.what === "full");
  expect(pi >= 0 && fi > pi, `a preview, then the full picture after the drag (${JSON.stringify(after)})`);
  const [pw] = after[pi].size.split("x").map(Number), [fw] = after[fi].size.split("x").map(Number);
  expect(pw < fw, `the preview (${after[pi].size}) is smaller than the full picture (${after[fi].size})`);
  step(`drag -> preview ${after[pi].size} after ${(after[pi].t - tl[ci].t).toFixed(0)} ms, full ${after[fi].size} after ${(after[fi].t - tl[ci].t).toFixed(0)} ms`);

  // Back to the cases list: the new case is listed; search filters.
  await page.getByRole("link", { name: "Cases" }).first().tap();
  await page.getByTestId("case-row").filter({ hasText: "E2E phantom case" }).waitFor({ timeout: 20000 });
  await page.getByTestId("case-search").fill("no-such-case-xyz");
  await page.getByText("No case matches this search.").waitFor({ timeout: 15000 });

  // A failed request (a case that does not exist): the daemon's own words in a banner.
  await page.evaluate(() => { location.hash = "#/case/99999"; });
  const banner = page.getByTestId("error-banner").filter({ hasText: "99999" });
  await banner.waitFor({ timeout: 10000 });
  await page.getByTestId("case-missing").waitFor({ timeout: 5000 });
  step(`banner: ${await banner.locator(".text").textContent()}`);
  await shot("04-error-banner");
  await banner.getByRole("button", { name: "Dismiss" }).tap();
  await banner.waitFor({ state: "detached", timeout: 5000 });

  // Jobs: start a registration on the phantom folder, see progress with NMI, cancel.
  await page.getByRole("link", { name: "Jobs" }).tap();
  await page.waitForFunction(() => [...document.querySelectorAll('[data-testid="case-folder"] option')].some((o) => o.value.startsWith("phantom/")), null, { timeout: 60000 });
  await page.getByTestId("start-register").tap();
  const running = page.locator('[data-testid="job-card"][data-state="running"]');
  await running.filter({ hasText: /NMI \d\.\d{4}/ }).waitFor({ timeout: 60000 });
  await page.waitForTimeout(2500); // a few plot points
  await shot("05-jobs-running");
  await running.getByTestId("cancel-job").tap();
  await page.locator('[data-testid="job-card"][data-state="cancelled"]').first().waitFor({ timeout: 30000 });
  await page.getByTestId("sb-jobs").filter({ hasText: "0 running" }).waitFor({ timeout: 15000 });
  await shot("06-jobs-cancelled");
  step("register job started and cancelled");

  // The same at 1920x1080.
  await page.setViewportSize({ width: 1920, height: 1080 });
  await page.getByRole("link", { name: "Cases" }).first().tap();
  await page.getByTestId("case-search").fill("");
  await page.getByTestId("case-row").first().waitFor();
  await shot("07-cases-1920");
  const n1 = await page.evaluate(() => window.cfRenderTimeline.length);
  await page.getByTestId("case-row").first().tap();
  await page.waitForFunction((n) => window.cfRenderTimeline.slice(n).some((e) => e.what === "full"), n1, { timeout: 30000 });
  await shot("08-case-view-1920");

  expect(pageErrors.length === 0, `no page errors (${pageErrors.join("; ")})`);
  step("PASS");
} catch (e) {
  failed = true;
  console.error(`[e2e] FAIL: ${e?.stack ?? e}`);
  try { const p = browser?.pages()[0]; if (p) await p.screenshot({ path: path.join(artDir, "failure.png") }); } catch {}
} finally {
  try { await browser?.close(); } catch {}
  if (daemon && daemon.exitCode === null) {
    daemon.kill("SIGTERM");
    await new Promise((r) => { const t = setTimeout(() => { daemon.kill("SIGKILL"); r(); }, 10000); daemon.on("exit", () => { clearTimeout(t); r(); }); });
  }
  fs.rmSync(tmp, { recursive: true, force: true });
}
process.exit(failed ? 1 : 0);
