// The UI when things go wrong around it (issue 7 "Checks": a tracker that drops out
// mid-registration, the daemon restarting, nothing entered lost) and whether its page ever
// freezes while work runs (7.34), in Debian's chromium against cortexfused (ctest
// ui_e2e_resilience; tests/ui/run_e2e.sh with CF_E2E_SCRIPT=e2e_resilience.mjs).
//
// The daemon's tracker is `tracker.source tcp` against an NDI simulator this test runs and stops
// (`cortexfuse sim tracker --tcp`, as a Vega; docs/tracker.md), playing a trajectory that rests
// the pointer on each suggested skin fiducial in turn. Steps:
//  1. Tracker screen: two fiducials recorded, the simulator stopped: the standing tracker line,
//     Record refused in the daemon's words, the two still recorded; the simulator back: the
//     line goes, two more recorded, the registration accepted.
//  2. Photo & marks of the imported phantom case: a landmark twin dragged and an ROI point added,
//     the page reloaded: the edits are back with a line saying they are not saved; the daemon
//     stopped: Save refused in words, the edits stay; the daemon back: Save stores them (the
//     revisions and the moved pixel read over the API), nothing kept in the tab any more.
//     Then as a logged-in technician: an edit (kept by the daemon as hers), the session revoked,
//     Save brings the login screen, logging in again gives the edit back, Save stores it.
//     Then a restart of chromium itself (the kiosk unit starts it with a fresh profile): the
//     kiosk's edit kept by the daemon (GET /api/cases/N/drafts/marks), the browser closed and a
//     new one started on a new profile folder: the edit is back with the words saying the
//     daemon kept it; Save stores it and the daemon's draft is gone.
//  3. A registration job, the simulator stopped while it runs: the UI says the tracker stopped
//     and that the registration goes on; no error; the job succeeds with evaluations after the stop.
//  4. The plan from the Preoperative screen and its quick check (the NIfTI mask parsed, the 256^3
//     loop, the PLY read and cut), 5. the brain mask read for picking on the 3D view: the page's
//     long tasks (PerformanceObserver 'longtask') while the registration runs, while the plan
//     runs, while the check is drawn and while the mask is read, each under CF_E2E_LONGTASK_MS
//     (200 ms; with the reading on the main thread the check was one task of 337 ms).
// Usage: node e2e_resilience.mjs CORTEXFUSED UI_DIR ARTEFACT_DIR [CORTEXFUSE_CLI]
//   (exit 0 pass, 1 fail, 77 skip). Without CORTEXFUSE_CLI: ../cli/cortexfuse beside the daemon's folder.
import { spawn } from "node:child_process";
import fs from "node:fs";
import os from "node:os";
import path from "node:path";
import { chromiumOrExit, Daemons, freePort, launchTouchBrowser } from "./e2e_lib.mjs";

const [daemonBin, uiDir, artDir] = process.argv.slice(2, 5).map((p) => path.resolve(p));
const cliBin = path.resolve(process.argv[5] ?? path.join(path.dirname(daemonBin), "..", "cli", "cortexfuse"));
const browserKit = chromiumOrExit(uiDir);
if (!fs.existsSync(cliBin)) { console.error(`FAIL: ${cliBin}: no cortexfuse (the tracker simulator)`); process.exit(1); }
const LONGTASK_MS = Number(process.env.CF_E2E_LONGTASK_MS ?? 200);
// The 200 ms holds on the VMs it was set on. A slower or busier machine stretches every task
// alike (a VM at half that speed, under ctest -j2, drew the check in one 221 ms task), so each
// phase's limit is scaled by the page's pace: a fixed main-thread workload timed right after the
// phase, against its time there (CF_E2E_PACE_REF_MS; never scaled below 200 ms). 10 ms: the
// eighteenth session's VM, which ray-casts at half the speed of those (VTK's mapper 62 against
// 31 ms), paced 15.6-20.5 ms with a build beside it. The regression the check is for, the NIfTI
// read on the main thread, was one task of 337 ms there: 1.7 times the limit at that pace or slower.
const PACE_REF_MS = Number(process.env.CF_E2E_PACE_REF_MS ?? 10);
const REGISTER_S = Number(process.env.CF_E2E_REGISTER_S ?? 240);
const PLAN_S = Number(process.env.CF_E2E_PLAN_S ?? 180);
// Under a sanitizer build (CF_E2E_SLOW) the daemon is many times slower: a short registration
// (one stage of 60 evaluations at 96 px; the default, ≈ 10 s in release, would take minutes),
// and a plan that does not finish in PLAN_S is a NOTE there (a failure in release).
const SLOW = !!process.env.CF_E2E_SLOW;
const REGISTER_PARAMS = SLOW ? { starts: [[0, 0, 0, 0, 0, 0]], search_stages: [], search_keep: 0, keep_best: 1, estimate_light: false, refine_stages: [],
                                  final_stages: [{ name: "slow", fwhm_mm: 4, step_mm: 1, step_deg: 1, render_width_px: 96, max_evaluations: 60 }] } : null;

fs.mkdirSync(artDir, { recursive: true });
const tmp = fs.mkdtempSync(path.join(os.tmpdir(), "cf-ui-resilience-"));
// The tools are named after their .rom files' stems, and the navigation endpoints and the
// Tracker screen look for `pointer` and `reference`: the test's synthetic ROMs are copied so.
const romDir = new URL("../drivers/data/roms/", import.meta.url).pathname;
const roms = { reference: path.join(tmp, "reference.rom"), pointer: path.join(tmp, "pointer.rom") };
fs.copyFileSync(path.join(romDir, "cf_reference.rom"), roms.reference);
fs.copyFileSync(path.join(romDir, "cf_pointer.rom"), roms.pointer);
const simPort = await freePort();
const configFile = path.join(tmp, "config.json");
const writeConfig = (listen) => fs.writeFileSync(configFile, JSON.stringify({
  http: { listen, ui_dir: path.join(uiDir, "dist") },
  state_dir: path.join(tmp, "state"),
  tracker: { source: "tcp", tcp: `127.0.0.1:${simPort}`, roms: [roms.reference, roms.pointer] },
}));
writeConfig("127.0.0.1:0");

const step = (s) => console.log(`[e2e-resilience] ${s}`);
const expect = (cond, what) => { if (!cond) throw new Error(`expected: ${what}`); };
const sleep = (ms) => new Promise((r) => setTimeout(r, ms));
const daemons = new Daemons(daemonBin);
let daemon, sim = null, browser, failed = false;
const t0 = Date.now();

// ---- the tracker simulator: the reference still, the pointer resting on each fiducial in turn
const SIM_HZ = 60, HOLD_S = 5, MOVE_S = 0.5; // each fiducial held HOLD_S - MOVE_S s, then 0.5 s to the next
const T_REF = [40, -25, -1450];               // the reference in the tracker's frame (no rotation)
let fids = [];                                // [{label, p_image_mm}]: p_reference = p_image (the "patient" lies so)
const trajectory = path.join(tmp, "trajectory.txt");
const writeTrajectory = () => {
  const at = (p) => `${T_REF[0] + p[0]} ${T_REF[1] + p[1]} ${T_REF[2] + p[2]} 1 0 0 0`;
  const lines = [`0 CF-REFERENCE ${T_REF.join(" ")} 1 0 0 0`];
  fids.forEach((f, k) => {
    lines.push(`${k * HOLD_S} CF-POINTER ${at(f.p_image_mm)}`, `${(k + 1) * HOLD_S - MOVE_S} CF-POINTER ${at(f.p_image_mm)}`);
  });
  lines.push(`${fids.length * HOLD_S} CF-POINTER ${at(fids[0].p_image_mm)}`); // the loop's end: back at the first
  fs.writeFileSync(trajectory, lines.join("\n") + "\n");
};
const startSim = () => new Promise((resolve, reject) => {
  const p = spawn(cliBin, ["sim", "tracker", "--tcp", `127.0.0.1:${simPort}`, "--rate", String(SIM_HZ), "--trajectory", trajectory], { stdio: ["ignore", "pipe", "pipe"] });
  let out = "", err = "";
  p.stderr.on("data", (d) => { err += d; });
  const t = setTimeout(() => reject(new Error(`the tracker simulator did not start: ${err.slice(-1000)}`)), 15000);
  p.stdout.on("data", (d) => { out += d; if (/^tcp /m.test(out)) { clearTimeout(t); resolve(p); } });
  p.on("exit", (c) => { clearTimeout(t); if (!p.stopping) reject(new Error(`the tracker simulator exited ${c}: ${err.slice(-1000)}`)); });
});
const stopSim = async () => {
  if (!sim || sim.exitCode !== null) return;
  sim.stopping = true;
  sim.kill("SIGTERM");
  await new Promise((r) => sim.on("exit", r));
  sim = null;
};

// ---- long tasks on the page's main thread (7.34), recorded from the page's first script on
const LONGTASKS = () => {
  window.__longtasks = [];
  try {
    new PerformanceObserver((l) => { for (const e of l.getEntries()) window.__longtasks.push({ start: e.startTime, ms: e.duration }); })
      .observe({ type: "longtask", buffered: true });
  } catch { window.__longtasks = null; }
};
const longTasks = {}; // phase -> { longest_ms, count, window_ms }

try {
  let base;
  ({ proc: daemon, base } = await daemons.start(configFile));
  const port = new URL(base).port;
  writeConfig(`127.0.0.1:${port}`); // the restart below comes back on the same address
  step(`daemon at ${base}, tracker source tcp 127.0.0.1:${simPort}`);
  const api = async (method, p, body, token) => {
    const headers = { "Content-Type": "application/json", ...(token ? { Authorization: `Bearer ${token}` } : {}) };
    const r = await fetch(`${base}${p}`, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    return { status: r.status, j: await r.json().catch(() => null) };
  };
  fids = (await api("GET", "/api/navigation/suggested-fiducials")).j.fiducials;
  expect(fids.length >= 4, `suggested fiducials on the daemon's MRI (${fids.length})`);
  writeTrajectory();
  sim = await startSim();
  step(`tracker simulator on 127.0.0.1:${simPort}: the pointer rests ${HOLD_S - MOVE_S} s on each of ${fids.map((f) => f.label).join(", ")}`);

  browser = await launchTouchBrowser(browserKit, path.join(tmp, "chromium"));
  await browser.addInitScript(LONGTASKS);
  let page = browser.pages()[0] ?? await browser.newPage(); // a new one after the chromium restart in step 2
  const pageErrors = [];
  page.on("pageerror", (e) => pageErrors.push(String(e)));
  const shot = (name) => page.screenshot({ path: path.join(artDir, `${name}.png`) });
  let cdp = await browser.newCDPSession(page);
  const touchDrag = async (pts) => {
    await cdp.send("Input.dispatchTouchEvent", { type: "touchStart", touchPoints: [pts[0]] });
    for (const p of pts.slice(1)) { await cdp.send("Input.dispatchTouchEvent", { type: "touchMove", touchPoints: [p] }); await page.waitForTimeout(16); }
    await cdp.send("Input.dispatchTouchEvent", { type: "touchEnd", touchPoints: [] });
  };
  const now = () => page.evaluate(() => performance.now());
  const measure = async (phase, from) => {
    const r = await page.evaluate(([a]) => {
      const t = window.__longtasks;
      if (t === null) return null;
      const inside = t.filter((e) => e.start + e.ms >= a);
      return { longest_ms: Math.round(Math.max(0, ...inside.map((e) => e.ms))), count: inside.length, window_ms: Math.round(performance.now() - a) };
    }, [from]);
    expect(r !== null, "chromium reports long tasks (PerformanceObserver 'longtask')");
    // The pace, timed after the phase's window: one task (9 x about 20 ms here) that ends before the
    // next phase's window opens, so it counts in none.
    r.pace_ms = await page.evaluate(() => {
      const a = new Float32Array(1 << 20), ts = [];
      let s = 0;
      for (let rep = 0; rep < 9; ++rep) {
        const t0 = performance.now();
        for (let k = 0; k < 4; ++k) for (let i = 0; i < a.length; ++i) { a[i] = Math.sqrt(a[i] + i * 0.5); s += a[i]; }
        ts.push(performance.now() - t0);
      }
      const warm = ts.slice(4).sort((x, y) => x - y); // after the JIT's warm-up
      return s < 0 ? -1 : Math.round(warm[2] * 10) / 10;
    });
    r.limit_ms = Math.round(LONGTASK_MS * Math.max(1, r.pace_ms / PACE_REF_MS));
    longTasks[phase] = r;
    step(`long tasks while ${phase}: ${r.count} over 50 ms in ${(r.window_ms / 1000).toFixed(1)} s, the longest ${r.longest_ms} ms (limit ${r.limit_ms} ms: ${LONGTASK_MS} ms at a pace of ${PACE_REF_MS} ms, ${r.pace_ms} ms now)`);
  };

  await page.goto(`${base}/`);
  await page.getByTestId("sb-link").filter({ hasText: "Live" }).waitFor({ timeout: 15000 });
  await page.getByTestId("sb-tracker").filter({ hasText: /Tracker \d+ Hz/ }).waitFor({ timeout: 30000 });

  // ---- 1. The tracker drops out while fiducials are being recorded (7.45) --------------------
  const tc = await api("POST", "/api/cases", { title: "Resilience tracker case" });
  expect(tc.status === 201, `tracker case created (${tc.status})`);
  const trackerCase = tc.j.id;
  await page.goto(`${base}/#/case/${trackerCase}/tracker`);
  await page.locator('[data-testid="tool-pointer"][data-level="ok"]').waitFor({ timeout: 20000 });
  await page.getByTestId("suggest-btn").tap();
  await page.locator('[data-testid^="fid-row-"]').nth(fids.length - 1).waitFor({ timeout: 15000 });
  const recordedNow = async () => (await api("GET", `/api/cases/${trackerCase}/navigation`)).j.patient_fiducials.fiducials.map((f) => f.label);
  // Waits until the pointer rests on a fiducial not yet recorded with at least 2 s of its hold
  // left (the trajectory's clock is the device's frame number), selects its row and records it.
  const recordResting = async () => {
    const until = Date.now() + 3 * fids.length * HOLD_S * 1000;
    while (Date.now() < until) {
      const a = (await api("GET", "/api/navigation/pointer")).j;
      const done = new Set(await recordedNow());
      if (a?.frame && a.p_reference_mm) {
        const u = (a.frame.frame / SIM_HZ) % (fids.length * HOLD_S), k = Math.floor(u / HOLD_S);
        const f = fids[k], left = (k + 1) * HOLD_S - MOVE_S - u;
        const off = Math.hypot(...a.p_reference_mm.map((v, i) => v - f.p_image_mm[i]));
        if (!done.has(f.label) && left > 2 && off < 1) {
          await page.getByTestId(`fid-row-${f.label}`).tap();
          await page.getByTestId("record-btn").filter({ hasText: f.label }).waitFor({ timeout: 3000 });
          await page.waitForTimeout(400); // a whole 0.3 s window of frames at rest
          await page.getByTestId("record-btn").tap();
          await page.locator(`[data-testid="fid-row-${f.label}"][data-recorded="true"]`).waitFor({ timeout: 10000 });
          return f.label;
        }
      }
      await sleep(150);
    }
    throw new Error("no fiducial could be recorded: the simulated pointer did not rest on one");
  };
  const firstTwo = [await recordResting(), await recordResting()];
  step(`recorded ${firstTwo.join(", ")} with the external simulator's pointer`);
  const tStop = Date.now();
  await stopSim();
  const trackerLineOn = (p) => p.getByTestId("tracker-banner").filter({ hasText: "The tracker stopped streaming" });
  let trackerLine = trackerLineOn(page); // again for the new page after the chromium restart (step 2)
  await trackerLine.waitFor({ timeout: 10000 });
  step(`simulator stopped: after ${((Date.now() - tStop) / 1000).toFixed(1)} s the screen says: ${await trackerLine.locator(".text").textContent()}`);
  await page.getByTestId("record-btn").tap();
  const refused = page.getByTestId("nav-msg").filter({ hasText: /not streaming|not tracked/ });
  await refused.waitFor({ timeout: 10000 });
  const kept = await page.locator('[data-testid^="fid-row-"][data-recorded="true"]').evaluateAll((els) => els.map((e) => e.dataset.testid.slice(8)));
  expect(kept.length === 2 && firstTwo.every((l) => kept.includes(l)), `the two recorded fiducials are still shown as recorded (${kept})`);
  expect((await recordedNow()).length === 2, "the daemon still has the two recorded fiducials");
  step(`Record while the tracker is gone: ${await refused.textContent()}`);
  await shot("resilience-01-tracker-lost");
  sim = await startSim();
  await trackerLine.waitFor({ state: "hidden", timeout: 20000 });
  await page.getByTestId("notice-banner").filter({ hasText: "The tracker is streaming again" }).waitFor({ timeout: 5000 });
  await page.locator('[data-testid="tool-pointer"][data-level="ok"]').waitFor({ timeout: 10000 });
  const nextTwo = [await recordResting(), await recordResting()];
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="fre-line"]')?.dataset.fre) >= 0, null, { timeout: 10000 });
  const fre = Number(await page.getByTestId("fre-line").getAttribute("data-fre"));
  expect(fre < 0.5, `FRE of the four recorded fiducials within the simulator's noise (${fre} mm)`);
  await page.getByTestId("accept-btn").tap();
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="accepted-line"]')?.dataset.revision) > 0, null, { timeout: 10000 });
  await shot("resilience-02-tracker-back");
  step(`simulator back: the line went, ${nextTwo.join(", ")} recorded, registration accepted (FRE ${fre.toFixed(3)} mm)`);

  // ---- 2. Unsaved marks across a reload, a daemon restart and a login screen (7.47) ----------
  const folders = async () => (await api("GET", "/api/case-folders")).j?.folders ?? [];
  for (let i = 0; i < 120 && !(await folders()).includes("phantom/case_0000"); i++) await sleep(500);
  const imp = await api("POST", "/api/cases/import", { folder: "phantom/case_0000" });
  expect(imp.status === 201, `phantom case imported (${imp.status} ${JSON.stringify(imp.j).slice(0, 200)})`);
  const caseId = imp.j.id;
  const marksShown = async (n) => page.waitForFunction((k) => Number(document.querySelector('[data-testid="photo-marks"]')?.dataset.landmarks) >= k &&
                                                       document.querySelector('[data-testid="photo-image"]')?.naturalWidth > 0, n, { timeout: 20000 });
  const marksNow = () => page.evaluate(() => {
    const svg = document.querySelector('[data-testid="photo-marks"]');
    return { lms: [...svg.querySelectorAll("circle.lm")].map((c) => [Number(c.getAttribute("cx")), Number(c.getAttribute("cy"))]),
             roi: Number(svg.dataset.roiPoints), mode: svg.dataset.mode };
  });
  const toScreen = (u, v) => page.evaluate(([u, v]) => {
    const p = new DOMPoint(u, v).matrixTransform(document.querySelector('[data-testid="photo-marks"]').getScreenCTM());
    return { x: Math.round(p.x), y: Math.round(p.y) };
  }, [u, v]);
  const dragLandmark = async (i, dx, dy) => {
    const m = await marksNow();
    const s = await toScreen(...m.lms[i]);
    await touchDrag(Array.from({ length: 6 }, (_, k) => ({ x: s.x + (dx * k) / 5, y: s.y + (dy * k) / 5 })));
    await page.waitForFunction(([i, p]) => { const c = document.querySelectorAll('[data-testid="photo-marks"] circle.lm')[i];
                                             return Math.hypot(Number(c.getAttribute("cx")) - p[0], Number(c.getAttribute("cy")) - p[1]) > 3; }, [i, m.lms[i]], { timeout: 5000 });
  };
  const stored = async () => (await api("GET", `/api/cases/${caseId}`)).j;
  /** Save landmarks, then Save ROI, each answered with its new revision. */
  const saveMarks = async (lmRevision, roiRevision) => {
    await page.getByTestId("mode-landmarks").tap();
    await page.getByTestId("save-landmarks").tap();
    await page.getByTestId("notice-banner").filter({ hasText: `Landmarks saved (revision ${lmRevision})` }).waitFor({ timeout: 10000 });
    await page.getByTestId("mode-roi").tap();
    await page.getByTestId("save-roi").tap();
    await page.getByTestId("notice-banner").filter({ hasText: `ROI saved (revision ${roiRevision})` }).waitFor({ timeout: 10000 });
  };
  const s0 = await stored();
  await page.goto(`${base}/#/case/${caseId}/photo`);
  await marksShown(4);
  await dragLandmark(0, 15, 10);
  await page.getByTestId("mode-roi").tap();
  const m0 = await marksNow();
  const roiPts = await page.evaluate(() => [...document.querySelectorAll('[data-testid="photo-marks"] circle.roi-point')].map((c) => [Number(c.getAttribute("cx")), Number(c.getAttribute("cy"))]));
  const mid = await toScreen((roiPts[0][0] + roiPts[1][0]) / 2, (roiPts[0][1] + roiPts[1][1]) / 2);
  await page.touchscreen.tap(mid.x, mid.y);
  await page.waitForFunction((n) => Number(document.querySelector('[data-testid="photo-marks"]').dataset.roiPoints) === n + 1, m0.roi, { timeout: 5000 });
  const edited = await marksNow();
  expect(await page.evaluate((id) => sessionStorage.getItem(`cortexfuse.marks.${id}`) !== null, caseId), "the unsaved marks are kept in the tab");
  await page.reload();
  await marksShown(4);
  let restoredLine = page.getByTestId("marks-restored");
  await restoredLine.filter({ hasText: "Restored your unsaved landmarks" }).filter({ hasText: "not saved yet" }).waitFor({ timeout: 5000 });
  const afterReload = await marksNow();
  expect(JSON.stringify(afterReload.lms) === JSON.stringify(edited.lms) && afterReload.roi === edited.roi,
    `the reload gives the edits back (${JSON.stringify(afterReload)} vs ${JSON.stringify(edited)})`);
  expect(!(await page.getByTestId("save-landmarks").isDisabled()), "Save landmarks is offered for the restored edit");
  step(`reload: ${await restoredLine.textContent()}`);
  await shot("resilience-03-marks-restored");

  // The daemon stops with the marks unsaved: Save is refused in words and the edits stay.
  await daemons.stop(daemon);
  await page.getByTestId("link-banner").filter({ hasText: "connection to the daemon was lost" }).waitFor({ timeout: 10000 });
  await page.getByTestId("save-landmarks").tap();
  const notSaved = page.getByTestId("error-banner").filter({ hasText: "The landmarks were not saved: the daemon cannot be reached" });
  await notSaved.waitFor({ timeout: 10000 });
  const whileDown = await marksNow();
  expect(JSON.stringify(whileDown.lms) === JSON.stringify(edited.lms) && whileDown.roi === edited.roi, "a failed Save keeps the edits on the screen");
  expect(!(await page.getByTestId("save-landmarks").isDisabled()), "Save landmarks is offered again after the failure");
  step(`Save while the daemon is down: ${await notSaved.locator(".text").textContent()}`);
  await shot("resilience-04-save-failed");
  ({ proc: daemon } = await daemons.start(configFile));
  await page.getByTestId("sb-link").filter({ hasText: "Live" }).waitFor({ timeout: 20000 });
  await notSaved.getByRole("button").tap();
  await saveMarks(s0.landmarks.revision + 1, s0.roi.revision + 1);
  const s1 = await stored();
  const px0 = s1.landmarks.points[0].pixel;
  expect(s1.landmarks.revision === s0.landmarks.revision + 1 && Math.hypot(px0[0] - edited.lms[0][0], px0[1] - edited.lms[0][1]) < 0.01,
    `the stored landmarks are the edit made before the reload and the restart (${JSON.stringify(px0)} vs ${JSON.stringify(edited.lms[0])})`);
  expect(s1.roi.revision === s0.roi.revision + 1 && s1.roi.roi.points.length === edited.roi, `the stored ROI has the added point (${s1.roi.roi.points.length})`);
  expect(await page.evaluate((id) => sessionStorage.getItem(`cortexfuse.marks.${id}`) === null, caseId), "nothing is kept in the tab once saved");
  expect(await restoredLine.isHidden(), "the restored line goes once everything is saved");
  step(`daemon restarted: Save stored landmarks revision ${s1.landmarks.revision} and ROI revision ${s1.roi.revision} (read back over the API)`);

  // As a logged-in user whose session ends: the login screen replaces the screen; after logging
  // in again the edit is back and Save stores it.
  expect((await api("POST", "/api/users", { name: "tina", password: "tech-pass-1", role: "technician" })).status === 201, "a technician is created");
  const logIn = async () => {
    await page.getByTestId("login-form").waitFor({ timeout: 10000 });
    await page.getByTestId("login-name").fill("tina");
    await page.getByTestId("login-password").fill("tech-pass-1");
    await page.getByTestId("login-submit").tap();
    await page.getByTestId("sb-role").filter({ hasText: "tina (technician)" }).waitFor({ timeout: 10000 });
  };
  await page.getByTestId("auth-button").filter({ hasText: "Log in" }).tap();
  await logIn();
  expect(/\/photo$/.test(page.url()), `after the login the photo screen again (${page.url()})`);
  await marksShown(4);
  await page.getByTestId("mode-landmarks").tap();
  await dragLandmark(1, -12, 8);
  const editedTina = await marksNow();
  const token = await page.evaluate(() => JSON.parse(sessionStorage.getItem("cortexfuse.session")).token);
  // The daemon keeps the edit as tina's (500 ms after it), not the kiosk's.
  const draftOf = async (tok) => (await api("GET", `/api/cases/${caseId}/drafts/marks`, undefined, tok)).j?.draft ?? null;
  const near = (a, b) => Math.hypot(a[0] - b[0], a[1] - b[1]) < 0.01;
  const waitDraft = async (tok, ok, what) => {
    for (const until = Date.now() + 10000; Date.now() < until; await sleep(100)) { const d = await draftOf(tok); if (ok(d)) return d; }
    throw new Error(`the daemon did not come to hold ${what}: ${JSON.stringify(await draftOf(tok)).slice(0, 300)}`);
  };
  const tinaDraft = await waitDraft(token, (d) => d?.landmarks && near(d.landmarks.points[1].pixel, editedTina.lms[1]), "tina's dragged landmark");
  expect(tinaDraft.owner.startsWith("user:") && (await draftOf()) === null, `the draft is tina's (${tinaDraft.owner}), the kiosk has none`);
  expect((await api("POST", "/api/logout", undefined, token)).status < 300, "tina's session is revoked behind her back");
  await page.getByTestId("save-landmarks").tap();
  await page.getByTestId("login-note").filter({ hasText: "session has ended" }).waitFor({ timeout: 10000 });
  await logIn();
  // The refused Save's own words stay until dismissed (the login screen said why first).
  const expired = page.getByTestId("error-banner").filter({ hasText: "expired" });
  if (await expired.count()) await expired.first().getByRole("button").tap();
  await marksShown(4);
  await restoredLine.filter({ hasText: "Restored your unsaved landmarks" }).waitFor({ timeout: 5000 });
  const back = await marksNow();
  expect(JSON.stringify(back.lms) === JSON.stringify(editedTina.lms), "after logging in again the edit is back");
  await page.getByTestId("save-landmarks").tap();
  await page.getByTestId("notice-banner").filter({ hasText: `Landmarks saved (revision ${s1.landmarks.revision + 1})` }).waitFor({ timeout: 10000 });
  const s2 = await stored();
  expect(s2.landmarks.revision === s1.landmarks.revision + 1 && Math.hypot(s2.landmarks.points[1].pixel[0] - editedTina.lms[1][0], s2.landmarks.points[1].pixel[1] - editedTina.lms[1][1]) < 0.01,
    "the edit made before the session ended is stored");
  step(`session ended with an unsaved edit: login screen, logged in again, edit restored and saved (revision ${s2.landmarks.revision})`);
  await page.getByTestId("auth-button").filter({ hasText: "Log out" }).tap();
  await page.getByTestId("sb-role").filter({ hasText: "Kiosk" }).waitFor({ timeout: 10000 });

  // A restart of chromium itself: the kiosk's unsaved edit is kept by the daemon; the browser is
  // closed and a new one starts with a fresh profile (as the kiosk unit does): it comes back.
  await page.goto(`${base}/#/cases`);
  await page.goto(`${base}/#/case/${caseId}/photo`);
  await marksShown(4);
  await page.getByTestId("mode-landmarks").tap();
  await dragLandmark(2, 14, -9);
  await page.getByTestId("mode-roi").tap();
  const rp = await page.evaluate(() => [...document.querySelectorAll('[data-testid="photo-marks"] circle.roi-point')].map((c) => [Number(c.getAttribute("cx")), Number(c.getAttribute("cy"))]));
  const e2 = rp.map((p, i) => [i, Math.hypot(...p.map((v, k) => v - rp[(i + 1) % rp.length][k]))]).sort((a, b) => b[1] - a[1])[0][0]; // the longest edge
  const mid2 = await toScreen((rp[e2][0] + rp[(e2 + 1) % rp.length][0]) / 2, (rp[e2][1] + rp[(e2 + 1) % rp.length][1]) / 2);
  await page.touchscreen.tap(mid2.x, mid2.y);
  await page.waitForFunction((n) => Number(document.querySelector('[data-testid="photo-marks"]').dataset.roiPoints) === n + 1, rp.length, { timeout: 5000 });
  const editedKiosk = await marksNow();
  const kioskDraft = await waitDraft(undefined, (d) => d?.landmarks && d.roi && near(d.landmarks.points[2].pixel, editedKiosk.lms[2]) && d.roi.points.length === editedKiosk.roi,
                                     "the kiosk's dragged landmark and added ROI point");
  step(`the daemon keeps the kiosk's unsaved edit (owner ${kioskDraft.owner}, edited ${kioskDraft.saved_utc})`);
  await browser.close();
  browser = await launchTouchBrowser(browserKit, path.join(tmp, "chromium-after-restart"));
  await browser.addInitScript(LONGTASKS);
  page = browser.pages()[0] ?? await browser.newPage();
  page.on("pageerror", (e) => pageErrors.push(String(e)));
  cdp = await browser.newCDPSession(page);
  restoredLine = page.getByTestId("marks-restored");
  trackerLine = trackerLineOn(page);
  await page.goto(`${base}/#/case/${caseId}/photo`);
  await page.getByTestId("sb-link").filter({ hasText: "Live" }).waitFor({ timeout: 15000 });
  await marksShown(4);
  const fromDaemonLine = restoredLine.filter({ hasText: "kept by the cart's daemon" }).filter({ hasText: "not saved yet" });
  await fromDaemonLine.waitFor({ timeout: 10000 });
  expect(await restoredLine.getAttribute("data-source") === "daemon", "the restored edit came from the daemon");
  const afterRestart = await marksNow();
  expect(JSON.stringify(afterRestart.lms) === JSON.stringify(editedKiosk.lms), `the new browser shows the kiosk's edit (${JSON.stringify(afterRestart.lms)} vs ${JSON.stringify(editedKiosk.lms)})`);
  await page.getByTestId("mode-roi").tap();
  expect((await marksNow()).roi === editedKiosk.roi, "and the added ROI point");
  step(`chromium restarted on a fresh profile: ${await restoredLine.textContent()}`);
  await shot("resilience-03b-marks-from-daemon");
  await saveMarks(s2.landmarks.revision + 1, s1.roi.revision + 1);
  const s3 = await stored();
  expect(near(s3.landmarks.points[2].pixel, editedKiosk.lms[2]) && s3.roi.roi.points.length === editedKiosk.roi,
    `the edit made before chromium restarted is stored (${JSON.stringify(s3.landmarks.points[2].pixel)} vs ${JSON.stringify(editedKiosk.lms[2])})`);
  await waitDraft(undefined, (d) => d === null, "no draft once saved");
  const drops = (await api("GET", `/api/cases/${caseId}/audit`)).j.audit.filter((e) => e.action.startsWith("draft."));
  expect(drops.some((e) => e.action === "draft.drop" && e.actor === "kiosk" && e.details.reason === "saved"), `the audit trail says the kiosk's draft was dropped when saved (${JSON.stringify(drops)})`);
  step(`Save stored landmarks revision ${s3.landmarks.revision} and ROI revision ${s3.roi.revision}; the daemon's draft is gone (audit: ${drops.map((e) => `${e.action} ${e.actor} ${e.details.reason ?? ""}`.trim()).join(", ")})`);

  // ---- 3. A registration job while the tracker stops; long tasks meanwhile (7.45, 7.34) -------
  await page.goto(`${base}/#/jobs`);
  await page.getByTestId("sb-link").filter({ hasText: "Live" }).waitFor({ timeout: 15000 });
  let from = await now();
  const tJob = Date.now();
  const job = await api("POST", "/api/jobs", { kind: "register", params: { case_id: caseId, ...(REGISTER_PARAMS ? { params: REGISTER_PARAMS } : {}) } });
  expect(job.status === 201 || job.status === 202, `registration job started (${job.status})`);
  const jobId = job.j.id;
  const card = page.locator(`[data-testid="job-card"][data-job-id="${jobId}"]`);
  await card.waitFor({ timeout: 10000 });
  // The simulator stopped at once (the default registration runs ≈ 7-10 s here, the short one
  // under a sanitizer build longer than its stop): the job is queued or running then.
  await stopSim();
  const atStop = (await api("GET", `/api/jobs/${jobId}`)).j;
  const evalsAtStop = atStop.figures?.evaluation ?? 0;
  expect(["queued", "running"].includes(atStop.state), `the registration is under way when the tracker stops (${atStop.state})`);
  await trackerLine.waitFor({ timeout: 10000 });
  const lineText = await trackerLine.locator(".text").textContent();
  expect(lineText.includes("a registration that is running goes on"), `the line says the registration goes on (${lineText})`);
  await page.waitForTimeout(1500);
  const stateLater = await card.getAttribute("data-state");
  expect(stateLater === "running" || (SLOW && stateLater === "succeeded"), `the registration still runs after the tracker stopped (${stateLater})`);
  expect(await page.getByTestId("error-banner").count() === 0, `no error shown (${await page.getByTestId("error-banner").allTextContents()})`);
  await shot("resilience-05-job-tracker-lost");
  step(`registration job ${jobId} ${atStop.state} (evaluation ${evalsAtStop}) when the simulator stopped: ${lineText}`);
  const done = card.and(page.locator('[data-state="succeeded"], [data-state="failed"], [data-state="cancelled"]'));
  await done.waitFor({ timeout: REGISTER_S * 1000 });
  const jEnd = (await api("GET", `/api/jobs/${jobId}`)).j;
  expect(jEnd.state === "succeeded", `the registration succeeded without the tracker (${jEnd.state}: ${jEnd.error ?? ""})`);
  expect((jEnd.figures?.evaluation ?? jEnd.result?.evaluations ?? 0) > evalsAtStop, `evaluations went on after the stop (${evalsAtStop} -> ${jEnd.figures?.evaluation ?? jEnd.result?.evaluations})`);
  expect(await page.getByTestId("error-banner").count() === 0, "no error shown while the tracker was gone");
  await measure("a registration job runs (Jobs screen, live NMI plot)", from);
  step(`registration succeeded in ${((Date.now() - tJob) / 1000).toFixed(1)} s without the tracker; ${jEnd.figures?.evaluation ?? "?"} evaluations`);
  sim = await startSim();
  await trackerLine.waitFor({ state: "hidden", timeout: 20000 });

  // ---- 4. The plan from the Preoperative screen, then its quick check (7.34, 7.5) ------------
  await page.goto(`${base}/#/case/${caseId}/plan`);
  await page.getByTestId("plan-volumes").filter({ hasText: "T1" }).waitFor({ timeout: 15000 });
  from = await now();
  await page.getByTestId("plan-start").tap();
  const bars = [];
  for (const until = Date.now() + PLAN_S * 1000; Date.now() < until;) {
    const s = await page.evaluate(() => ({ state: document.querySelector('[data-testid="plan-progress"]').dataset.state,
                                          w: document.querySelector('[data-testid="plan-progress"] .bar').style.width }));
    if (s.state) bars.push(`${s.state} ${s.w}`);
    if (["succeeded", "failed", "cancelled"].includes(s.state)) break;
    await sleep(100);
  }
  if (SLOW && !bars.at(-1)?.startsWith("succeeded")) {
    step(`NOTE: CF_E2E_SLOW: the plan did not finish in ${PLAN_S} s (${bars.at(-1)}): its long tasks and the quick check are not measured`);
    await page.getByTestId("plan-cancel").tap().catch(() => {});
  } else {
    expect(bars.at(-1)?.startsWith("succeeded"), `the plan succeeded (${bars.at(-1)})`);
    expect(bars.some((b) => b.startsWith("running") && b !== "running 100%"), `the bar was seen running below 100 % (${[...new Set(bars)].join(", ")})`);
    await measure("the plan runs (Preoperative screen, progress bar)", from);
    from = await now();
    await page.waitForFunction(() => Number(document.querySelector('[data-testid="plan-check"]')?.dataset.surfaceSegments) > 100, null, { timeout: 60000 });
    await measure("the quick check is drawn (mask NIfTI parsed, 3 slices, PLY read and cut)", from);
    step(`plan: ${[...new Set(bars)].slice(0, 6).join(", ")} …; check: ${await page.getByTestId("plan-check-text").textContent()}`);
    await shot("resilience-06-plan-check");

    // ---- 5. The brain mask read for picking a landmark on the 3D view (nifti.ts, 7.34) ---------
    await page.getByTestId("case-tab-view").tap();
    await page.waitForFunction(() => document.querySelector('[data-testid="render-image"]')?.dataset.full === "true" &&
                                     document.querySelector('[data-testid="render-stage"]')?.dataset.orbit === "free", null, { timeout: 60000 });
    from = await now();
    await page.getByTestId("pick-landmark").tap();
    await page.getByTestId("pick-note").filter({ hasText: "Tap the model" }).waitFor({ timeout: 30000 });
    await measure("the brain mask is read for picking (3D view, Pick landmark)", from);
  }

  for (const [phase, r] of Object.entries(longTasks))
    expect(r.longest_ms <= r.limit_ms, `no long task over ${r.limit_ms} ms while ${phase} (longest ${r.longest_ms} ms, pace ${r.pace_ms} ms)`);
  expect(pageErrors.length === 0, `no page errors (${pageErrors.join("; ")})`);
  step(`PASS in ${((Date.now() - t0) / 1000).toFixed(0)} s; long tasks: ${JSON.stringify(longTasks)}`);
} catch (e) {
  failed = true;
  console.error(`[e2e-resilience] FAIL: ${e?.stack ?? e}`);
  for (const d of daemons.deaths) console.error(`[e2e-resilience] ${d}`);
  if (Object.keys(longTasks).length) console.error(`[e2e-resilience] long tasks so far: ${JSON.stringify(longTasks)}`);
  try { const p = browser?.pages()[0]; if (p) await p.screenshot({ path: path.join(artDir, "resilience-failure.png") }); } catch {}
} finally {
  try { await browser?.close(); } catch {}
  await daemons.stopAll();
  await stopSim();
  fs.rmSync(tmp, { recursive: true, force: true });
}
process.exit(failed ? 1 : 0);
