// One case by touch from "new case" to the fused view, in the end-to-end test (called by e2e.mjs;
// issue 7: 7.3, 7.40 and the controls of 7.5, 7.7, 7.10, 7.14, 7.18, 7.20): created by a tap;
// its T1, brain mask, fMRI map and a CT-like volume and the phantom's photo uploaded through
// Contents -> Add data with the file inputs (the browser's file chooser); planning started on the
// Preoperative screen (cancelled once while it runs, then run to the end with the bar seen below
// 100 %); the patient registration on its Tracker screen (e2e_tracker.mjs, with Redo); landmark
// pairs picked on the model in the 3D view and their twins tapped on the photo (at the pixels the
// phantom's true camera sees the picked points at), one renamed and one deleted; the ROI drawn by
// taps at the phantom's ROI points, one point dragged, one added and deleted; registered from
// Contents; the fused view, its modalities and tags; the case view's T1 / CT / fMRI tabs with
// their histograms drawn and a tf point added by a tap. The phantom folder (the daemon's
// phantom/case_0000) gives the photo, the camera, its true pose, landmarks and ROI.
// Screenshots 20-* (this case) and plan-00-running.
import fs from "node:fs";
import path from "node:path";
import { activationMap, ctLikeMap, fusedModalitiesE2E } from "./e2e_fused_modalities.mjs";
import { planCheckE2E, tagsE2E } from "./e2e_live_tags.mjs";
import { trackerE2E } from "./e2e_tracker.mjs";

const DATA = new URL("../../data/", import.meta.url).pathname;
const T1 = path.join(DATA, "t1_head_mne_ecog.nii.gz"), MASK = path.join(DATA, "brainmask_mne_ecog_binary.nii.gz");

// The 3D view's camera, as ui/src/orbit.ts and render_scheduler.ts build it (to aim taps at points).
const D2R = Math.PI / 180;
const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const unit = (a) => { const l = Math.hypot(...a); return [a[0] / l, a[1] / l, a[2] / l]; };
function orbitPose(o, target) {
  const a = o.azimuthDeg * D2R, e = o.elevationDeg * D2R;
  const eye = [target[0] + o.distanceMm * Math.cos(e) * Math.cos(a), target[1] + o.distanceMm * Math.cos(e) * Math.sin(a), target[2] + o.distanceMm * Math.sin(e)];
  const up = [-Math.sin(e) * Math.cos(a), -Math.sin(e) * Math.sin(a), Math.cos(e)];
  const z = unit(sub(target, eye)), x = unit(cross([-up[0], -up[1], -up[2]], z)), y = cross(z, x);
  return [[...x, -dot(x, eye)], [...y, -dot(y, eye)], [...z, -dot(z, eye)]];
}
/** A world point's pixel (OpenCV's model, with K.distortion [k1, k2, p1, p2, k3] when given). */
const project = (T, K, X) => {
  const c = [0, 1, 2].map((r) => T[r][0] * X[0] + T[r][1] * X[1] + T[r][2] * X[2] + T[r][3]);
  if (c[2] <= 1e-9) return null;
  let x = c[0] / c[2], y = c[1] / c[2];
  if (K.distortion) {
    const [k1, k2, p1, p2, k3] = K.distortion, r2 = x * x + y * y, rad = 1 + r2 * (k1 + r2 * (k2 + r2 * k3));
    [x, y] = [x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y];
  }
  return [K.fx * x + K.cx, K.fy * y + K.cy];
};

/** The whole case. Returns { id, registered, planned }. */
export async function wholeCaseE2E(ctx) {
  const { page, base, step, expect, shot, checkTargets, checkChrome, touchDrag, phantomDir, slow } = ctx;
  // Only a slow build (the ASan+UBSan half sets CF_E2E_SLOW) may leave the plan or the
  // registration unfinished, with a NOTE; in the release build that is a failure.
  const lenient = !!process.env.CF_E2E_SLOW;
  const api = async (p) => page.evaluate(async (u) => (await fetch(u)).json(), p);
  const folder = JSON.parse(fs.readFileSync(path.join(phantomDir, "case.json"), "utf8"));
  const truth = JSON.parse(fs.readFileSync(path.join(phantomDir, "truth.json"), "utf8"));
  const K = folder.camera;
  const Ttrue = truth.T_camera_from_world;
  /** Waits for `loc`; an error banner meanwhile fails the test with its words. */
  const waitOrBanner = async (loc, ms, what) => {
    const banner = page.getByTestId("error-banner");
    await loc.or(banner).first().waitFor({ timeout: ms });
    if (await banner.count() && await banner.first().isVisible() && !(await loc.count()))
      throw new Error(`${what}: ${await banner.first().locator(".text").textContent()}`);
  };
  const t0 = Date.now();

  // ---- New case by tap.
  await page.getByRole("link", { name: "Cases" }).first().tap();
  await page.getByTestId("new-case-title").fill("E2E whole case");
  await page.getByTestId("create-case").tap();
  await page.waitForURL(/#\/case\/\d+$/, { timeout: 20000 });
  const id = Number(/case\/(\d+)/.exec(page.url())[1]);
  step(`whole case: case ${id} created by tap`);

  // ---- Add data through Contents (the file inputs are the browser's file chooser).
  await page.getByTestId("case-tab-contents").tap();
  const upload = async (file, modality, name) => {
    await page.getByTestId("upload-volume-modality").selectOption(modality);
    await page.getByTestId("upload-volume-file").setInputFiles(file);
    await page.getByTestId("upload-volume").tap();
    await waitOrBanner(page.getByTestId("case-volumes").filter({ hasText: name }), 60000 * slow, `upload of ${name} as ${modality}`);
  };
  await upload(T1, "T1", "t1_head_mne_ecog.nii.gz");
  await upload(MASK, "mask", "brainmask_mne_ecog_binary.nii.gz");
  // The fMRI map: one cluster (radius 15 mm) about the middle of the phantom's landmarks, on the
  // cortex the camera sees (the photo lies on the rest of the craniotomy).
  const lmMean = [0, 1, 2].map((a) => truth.landmarks_true.reduce((t, l) => t + l.world_mm[a], 0) / truth.landmarks_true.length);
  await upload({ name: "fmri_e2e.nii.gz", mimeType: "application/gzip", buffer: activationMap(MASK, { centre_lps_mm: lmMean, radius_mm: 15 }) }, "fMRI", "fmri_e2e.nii.gz");
  await upload({ name: "ct_e2e.nii.gz", mimeType: "application/gzip", buffer: ctLikeMap(T1, MASK, 2) }, "CT", "ct_e2e.nii.gz");
  await page.getByTestId("upload-photo-focal").fill(String(K.fx));
  await page.getByTestId("upload-photo-file").setInputFiles(path.join(phantomDir, folder.photo));
  await page.getByTestId("upload-photo").tap();
  await waitOrBanner(page.getByTestId("case-holdings").filter({ hasText: "1 photo" }), 20000 * slow, "photo upload");
  const rec0 = await api(`/api/cases/${id}`);
  const mods = rec0.volumes.map((v) => v.modality).sort().join(",");
  expect(mods === "CT,T1,fMRI,mask" && rec0.photos.length === 1 && rec0.photos[0].intrinsics.fx === K.fx,
    `the case holds what was uploaded by touch (${mods}; ${rec0.photos.length} photo, fx ${rec0.photos[0]?.intrinsics?.fx})`);
  await page.screenshot({ path: ctx.shotPath("20-whole-contents"), fullPage: true }); // what it holds (top) and Add data (bottom)
  step(`whole case: T1, mask, fMRI, CT and the photo (${K.width}x${K.height}, fx ${K.fx}) added through Contents`);

  // ---- Planning from the Preoperative screen: cancelled once while it runs, then to the end.
  await page.getByTestId("case-tab-plan").tap();
  await page.waitForFunction(() => { const b = document.querySelector('[data-testid="plan-start"]'); return b && !b.disabled; }, null, { timeout: 20000 });
  // Every state and width the bar shows, recorded in the page as it changes.
  await page.evaluate(() => {
    const box = document.querySelector('[data-testid="plan-progress"]');
    window.cfPlanBar = [];
    const rec = () => window.cfPlanBar.push({ state: box.dataset.state ?? "", width: parseFloat(box.querySelector(".bar").style.width), t: performance.now() });
    new MutationObserver(rec).observe(box, { attributes: true, subtree: true, attributeFilter: ["style", "data-state"] });
  });
  await page.getByTestId("plan-start").tap();
  await page.locator('[data-testid="plan-progress"][data-state="running"]').waitFor({ timeout: 30000 * slow });
  await page.getByTestId("plan-cancel").tap();
  await page.locator('[data-testid="plan-progress"][data-state="cancelled"]').waitFor({ timeout: 60000 * slow });
  await page.getByTestId("plan-stage").filter({ hasText: "cancelled" }).waitFor({ timeout: 5000 });
  expect(await page.getByTestId("plan-cancel").isHidden(), "Cancel planning goes once the plan is cancelled");
  step(`Preoperative: ${await page.getByTestId("plan-stage").textContent()}`);
  const nBar = await page.evaluate(() => window.cfPlanBar.length);
  await page.waitForFunction(() => { const b = document.querySelector('[data-testid="plan-start"]'); return b && !b.disabled; }, null, { timeout: 10000 });
  await page.getByTestId("plan-start").tap();
  const tPlan = Date.now();
  // The bar part-way (a screenshot of it), then the end.
  const partWay = await page.waitForFunction((n) => window.cfPlanBar.slice(n).some((r) => r.state === "running" && r.width > 0 && r.width < 100),
    nBar, { timeout: 60000 * slow, polling: 50 }).then(() => true, () => false);
  if (partWay) await shot("plan-00-running");
  const planBudgetMs = Number(process.env.CF_E2E_PLAN_S ?? (lenient ? 60 : 180)) * 1000;
  const planned = await page.locator('[data-testid="plan-progress"][data-state="succeeded"], [data-testid="plan-progress"][data-state="failed"]')
    .waitFor({ timeout: planBudgetMs }).then(() => true, () => false);
  if (!planned) {
    if (!lenient) throw new Error(`expected: the plan finishes within CF_E2E_PLAN_S = ${planBudgetMs / 1000} s in the release build (set CF_E2E_SLOW=1 for a slow build)`);
    await page.getByTestId("plan-cancel").tap().catch(() => {});
    step(`NOTE: CF_E2E_SLOW: the plan did not finish in ${planBudgetMs / 1000} s: cancelled; the textured fused view, the modalities and tags are not checked`);
  } else {
    expect(await page.locator('[data-testid="plan-progress"]').getAttribute("data-state") === "succeeded", `the plan succeeded (${await page.getByTestId("plan-stage").textContent()})`);
    const seen = await page.evaluate((n) => window.cfPlanBar.slice(n), nBar);
    const mid = seen.filter((r) => r.state === "running" && r.width > 0 && r.width < 100).map((r) => r.width);
    expect(partWay && mid.length > 0, `the progress bar was seen part-way while the plan ran (${JSON.stringify(seen.map((r) => `${r.state} ${r.width}`))})`);
    step(`plan of case ${id} from the Preoperative screen succeeded in ${((Date.now() - tPlan) / 1000).toFixed(1)} s; the bar showed ${[...new Set(mid)].join(", ")} % on the way`);
    await planCheckE2E({ page, step, expect, shot, checkTargets, caseId: id });
  }

  // ---- Patient registration on this case's Tracker screen (with Redo).
  await page.getByTestId("case-tab-tracker").tap();
  await trackerE2E({ page, base, step, expect, shot, checkTargets, caseId: id });

  // ---- Landmark pairs: picked on the model in the 3D view, twins tapped on the photo.
  await page.getByTestId("case-tab-view").tap();
  const geo = await page.evaluate(async (cid) => { for (let i = 0; i < 60; i++) { const r = await fetch(`/api/render/volume?case_id=${cid}`); if (r.ok) return r.json(); await new Promise((s) => setTimeout(s, 500)); } return null; }, id);
  expect(geo?.brain?.center_lps_mm, `the case volume's geometry (${JSON.stringify(geo)})`);
  const target = geo.brain.center_lps_mm;
  await page.waitForFunction(() => document.querySelector('[data-testid="render-image"]')?.dataset.full === "true" &&
                                   document.querySelector('[data-testid="render-stage"]')?.dataset.orbit === "free", null, { timeout: 30000 * slow });
  // Turn the head by touch to look from the photo camera's side: the named view nearest in
  // azimuth, then a finger drag for the rest (0.4 degrees a pixel).
  const R = Ttrue.slice(0, 3).map((r) => r.slice(0, 3)), tt = Ttrue.slice(0, 3).map((r) => r[3]);
  const C = [0, 1, 2].map((j) => -(R[0][j] * tt[0] + R[1][j] * tt[1] + R[2][j] * tt[2]));
  const dir = unit(sub(C, target));
  const azWant = Math.atan2(dir[1], dir[0]) / D2R, elWant = Math.max(-80, Math.min(80, Math.asin(dir[2]) / D2R));
  const named = [["left", 0], ["anterior", -90], ["right", 180], ["posterior", 90]];
  const wrap = (d) => ((((d + 180) % 360) + 360) % 360) - 180;
  const [vname, vaz] = named.sort((a, b) => Math.abs(wrap(azWant - a[1])) - Math.abs(wrap(azWant - b[1])))[0];
  await page.locator(`.choices .btn[data-value="${vname}"]`).tap();
  const dx = -Math.round(wrap(azWant - vaz) / 0.4), dy = Math.round(elWant / 0.4);
  const sb = await page.getByTestId("render-stage").boundingBox();
  const sx = Math.round(sb.x + sb.width / 2 - dx / 2), sy = Math.round(sb.y + sb.height / 2 - dy / 2);
  await touchDrag(Array.from({ length: 13 }, (_, i) => ({ x: sx + Math.round((dx * i) / 12), y: sy + Math.round((dy * i) / 12) })));
  await page.waitForFunction(() => { const i = document.querySelector('[data-testid="render-image"]'); return i?.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq(); }, null, { timeout: 30000 * slow });
  const orbit = await page.evaluate(() => { const s = document.querySelector('[data-testid="render-stage"]').dataset; return { azimuthDeg: Number(s.azimuth), elevationDeg: Number(s.elevation), distanceMm: Number(s.distance) }; });
  step(`3D view turned by touch to azimuth ${orbit.azimuthDeg}°, elevation ${orbit.elevationDeg}° (the photo camera's side: ${azWant.toFixed(1)}°, ${elWant.toFixed(1)}°)`);
  // The plan's CT and fMRI layers hidden by touch (they cover the cortex the landmarks are on).
  if (planned) {
    for (const [tabId, label] of [["modality-ct", "CT"], ["modality-fmri", "fMRI"]]) {
      await page.getByTestId(tabId).tap();
      await page.getByTestId("modality-visible").filter({ hasText: `${label} shown` }).tap();
      await page.getByTestId("modality-visible").filter({ hasText: `${label} hidden` }).waitFor({ timeout: 5000 });
    }
    await page.getByTestId("modality-t1").tap();
    await page.waitForFunction(() => { const i = document.querySelector('[data-testid="render-image"]'); return i?.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq(); }, null, { timeout: 30000 * slow });
  }
  await page.getByTestId("pick-landmark").tap();
  await page.getByTestId("pick-note").filter({ hasText: "Tap the model" }).waitFor({ timeout: 30000 * slow });
  // The view's camera: the picture shown (its size) contained in the stage.
  const view = await page.evaluate(() => {
    const r = document.querySelector('[data-testid="render-stage"]').getBoundingClientRect();
    const [w, h] = document.querySelector('[data-testid="render-image"]').dataset.size.split("x").map(Number);
    return { left: r.left, top: r.top, width: r.width, height: r.height, w, h };
  });
  const fView = (0.5 * Math.min(view.w, view.h) * 450) / 95;
  const Kview = { fx: fView, fy: fView, cx: (view.w - 1) / 2, cy: (view.h - 1) / 2 };
  const Tview = orbitPose(orbit, target);
  const kv = Math.min(view.width / view.w, view.height / view.h);
  const toView = (X) => { const p = project(Tview, Kview, X); return p && { x: view.left + (view.width - view.w * kv) / 2 + (p[0] + 0.5) * kv, y: view.top + (view.height - view.h * kv) / 2 + (p[1] + 0.5) * kv }; };
  // The phantom's landmarks (on the brain, seen by the camera), then points half way between two
  // of them (a tap there lands on the surface in front): five far enough apart on the photo that
  // a tap on one twin is not taken for the mark of another.
  const lt = truth.landmarks_true;
  const mids = lt.flatMap((a, i) => lt.slice(i + 1).map((b) => ({ label: `${a.label}-${b.label}`, world_mm: a.world_mm.map((v, k) => (v + b.world_mm[k]) / 2) })));
  const cand = [...lt, ...mids].map((l) => ({ label: l.label, w: l.world_mm, px: project(Ttrue, K, l.world_mm) }))
    .filter((c) => c.px && c.px[0] > 20 && c.px[1] > 20 && c.px[0] < K.width - 20 && c.px[1] < K.height - 20);
  const chosen = [];
  for (const c of cand) if (chosen.length < 5 && chosen.every((o) => Math.hypot(o.px[0] - c.px[0], o.px[1] - c.px[1]) > 45)) chosen.push(c);
  expect(chosen.length >= 5, `five phantom landmarks apart on the photo (${cand.length} in view, ${chosen.length} chosen)`);
  const picked = [];
  for (const [i, c] of chosen.entries()) {
    // A midpoint lies inside the brain: the pick lands on the surface in front of it.
    const s = toView(c.w);
    expect(s && s.x > view.left && s.y > view.top && s.x < view.left + view.width && s.y < view.top + view.height, `landmark ${c.label} in the 3D view (${JSON.stringify(s)})`);
    await page.touchscreen.tap(s.x, s.y);
    await waitOrBanner(page.locator(`[data-testid="render-stage"][data-picked="${i + 1}"]`), 15000 * slow, `pick ${i + 1} at ${c.label}`);
    const note = await page.getByTestId("notice-banner").filter({ hasText: "Model point picked" }).last().locator(".text").textContent();
    const m = /at \((-?[\d.]+), (-?[\d.]+), (-?[\d.]+)\) mm/.exec(note);
    expect(m, `the pick names its point (${note})`);
    const w = [Number(m[1]), Number(m[2]), Number(m[3])];
    picked.push({ label: c.label, w, off: Math.hypot(...sub(w, c.w)), px: project(Ttrue, K, w) });
    expect(picked.every((p, j) => j === i || Math.hypot(p.px[0] - picked[i].px[0], p.px[1] - picked[i].px[1]) > 40), `the picked point ${i + 1}'s twin is apart from the others on the photo`);
  }
  step(`5 model points picked by taps on the model: ${picked.map((p) => `${p.label} ${p.off.toFixed(1)} mm from the phantom's`).join(", ")}`);
  await shot("20-whole-picked");
  await page.getByTestId("case-tab-photo").tap();
  await page.waitForFunction(() => document.querySelector('[data-testid="photo-image"]')?.naturalWidth > 0 &&
                                   document.querySelector('[data-testid="photo-marks"]')?.dataset.landmarks === "0", null, { timeout: 20000 });
  const toScreen = (u, v) => page.evaluate(([u, v]) => {
    const p = new DOMPoint(u, v).matrixTransform(document.querySelector('[data-testid="photo-marks"]').getScreenCTM());
    return { x: p.x, y: p.y };
  }, [u, v]);
  for (const [i, p] of picked.entries()) {
    expect(p.px && p.px[0] >= 0 && p.px[1] >= 0 && p.px[0] < K.width && p.px[1] < K.height, `the picked point ${i + 1} is in the photo (${p.px})`);
    const s = await toScreen(p.px[0], p.px[1]);
    await page.touchscreen.tap(s.x, s.y);
    await page.waitForFunction((n) => document.querySelector('[data-testid="photo-marks"]').dataset.landmarks === String(n), i + 1, { timeout: 5000 });
  }
  await page.waitForFunction(() => document.querySelector('[data-testid="alignment"]')?.dataset.state === "ok" &&
                                   document.querySelectorAll('[data-testid="lm-projected"]').length === 5, null, { timeout: 15000 });
  const al = await page.evaluate(() => ({ rms: Number(document.querySelector('[data-testid="alignment"]').dataset.rmsPx), text: document.querySelector('[data-testid="alignment"]').textContent }));
  // The photo's intrinsics typed on upload are its size and focal length only (the phantom's
  // camera has a shifted principal point and lens distortion): a few pixels of RMS.
  expect(al.rms < 8, `the twins tapped at the true camera's pixels align (${al.text})`);
  await page.getByTestId("save-landmarks").tap();
  await page.getByTestId("notice-banner").filter({ hasText: "Landmarks saved (revision 1)" }).waitFor({ timeout: 10000 });
  step(`5 twins tapped on the photo, saved (revision 1): ${al.text}`);
  // Rename the first pair, delete the fifth; the saved revision through the API.
  const lmBefore = (await api(`/api/cases/${id}`)).landmarks;
  expect(lmBefore.revision === 1 && lmBefore.points.length === 5, `revision 1 holds 5 pairs (${JSON.stringify(lmBefore).slice(0, 200)})`);
  await page.getByTestId("landmark-name").first().fill("precentral");
  await page.getByTestId("landmark-delete").nth(4).tap();
  await page.waitForFunction(() => document.querySelector('[data-testid="photo-marks"]').dataset.landmarks === "4", null, { timeout: 5000 });
  await page.getByTestId("save-landmarks").tap();
  await page.getByTestId("notice-banner").filter({ hasText: "Landmarks saved (revision 2)" }).waitFor({ timeout: 10000 });
  const lmAfter = (await api(`/api/cases/${id}`)).landmarks;
  const names = lmAfter.points.map((p) => p.name);
  const gone = lmBefore.points[4];
  expect(lmAfter.revision === 2 && lmAfter.points.length === 4 && names[0] === "precentral" &&
         JSON.stringify(names.slice(1)) === JSON.stringify(lmBefore.points.slice(1, 4).map((p) => p.name)) &&
         !lmAfter.points.some((p) => Math.hypot(p.pixel[0] - gone.pixel[0], p.pixel[1] - gone.pixel[1]) < 0.01),
         `revision 2: the first pair renamed, the fifth deleted (${names.join(", ")})`);
  step(`landmarks renamed and deleted by touch: revision 2 holds ${names.join(", ")} (${gone.name} gone)`);

  // ---- The ROI by taps at the phantom's ROI points; one dragged, one added and deleted.
  const roiTrue = JSON.parse(fs.readFileSync(path.join(phantomDir, folder.roi), "utf8")).points;
  await page.getByTestId("mode-roi").tap();
  for (const [i, q] of roiTrue.entries()) {
    const s = await toScreen(q[0], q[1]);
    await page.touchscreen.tap(s.x, s.y);
    await page.waitForFunction((n) => document.querySelector('[data-testid="photo-marks"]').dataset.roiPoints === String(n), i + 1, { timeout: 5000 });
  }
  const roiPts = () => page.evaluate(() => [...document.querySelectorAll('[data-testid="photo-marks"] circle.roi-point')].map((c) => [Number(c.getAttribute("cx")), Number(c.getAttribute("cy"))]));
  const tapped = await roiPts();
  const sameSet = roiTrue.every((q) => tapped.some((p) => Math.hypot(p[0] - q[0], p[1] - q[1]) < 1.5));
  expect(tapped.length === roiTrue.length && sameSet, `the ROI holds the ${roiTrue.length} tapped points (${JSON.stringify(tapped)})`);
  // Drag point 1 by touch (12, 8) screen px.
  const a = await toScreen(tapped[0][0], tapped[0][1]);
  await touchDrag(Array.from({ length: 6 }, (_, i) => ({ x: Math.round(a.x) + Math.round(2.4 * i), y: Math.round(a.y) + Math.round(1.6 * i) })));
  const dragged = await roiPts();
  const moved = Math.hypot(dragged[0][0] - tapped[0][0], dragged[0][1] - tapped[0][1]);
  expect(dragged.length === tapped.length && moved > 5, `ROI point 1 dragged by touch (${moved.toFixed(1)} px; ${dragged.length} points)`);
  // A point added at the middle of the longest edge (selected as it is added), then deleted.
  let li = 0, ll = 0;
  dragged.forEach((p, i) => { const q = dragged[(i + 1) % dragged.length]; const l = Math.hypot(q[0] - p[0], q[1] - p[1]); if (l > ll) { ll = l; li = i; } });
  const mp = [(dragged[li][0] + dragged[(li + 1) % dragged.length][0]) / 2, (dragged[li][1] + dragged[(li + 1) % dragged.length][1]) / 2];
  const ms = await toScreen(mp[0], mp[1]);
  await page.touchscreen.tap(ms.x, ms.y);
  await page.waitForFunction((n) => document.querySelector('[data-testid="photo-marks"]').dataset.roiPoints === String(n), dragged.length + 1, { timeout: 5000 });
  await page.getByTestId("roi-delete").tap();
  await page.waitForFunction((n) => document.querySelector('[data-testid="photo-marks"]').dataset.roiPoints === String(n), dragged.length, { timeout: 5000 });
  expect(JSON.stringify(await roiPts()) === JSON.stringify(dragged), "Delete point removed the added point and only it");
  await page.getByTestId("save-roi").tap();
  await page.getByTestId("notice-banner").filter({ hasText: "ROI saved (revision 1)" }).waitFor({ timeout: 10000 });
  const roiSaved = (await api(`/api/cases/${id}`)).roi;
  expect(roiSaved.revision === 1 && roiSaved.roi.points.length === dragged.length &&
         roiSaved.roi.points.every((p, i) => Math.hypot(p[0] - dragged[i][0], p[1] - dragged[i][1]) < 0.01),
         `the saved ROI is the one on the screen, the dragged point included (${JSON.stringify(roiSaved.roi.points[0])})`);
  await page.getByTestId("mode-landmarks").tap();
  await shot("20-whole-photo-marks");
  await checkTargets("photo & marks (whole case)");
  step(`ROI drawn by ${roiTrue.length} taps, point 1 dragged ${moved.toFixed(1)} px, a point added and deleted (Delete point), saved (revision 1)`);

  // ---- Registration from Contents, to the end.
  // From the Jobs screen back to this case by touch: Cases, its row, then one of its tabs.
  const openByTouch = async (tab) => {
    await page.getByRole("link", { name: "Cases" }).first().tap();
    await page.getByTestId("case-row").filter({ hasText: "E2E whole case" }).first().tap();
    await page.waitForURL(new RegExp(`#/case/${id}$`), { timeout: 10000 });
    await page.getByTestId(`case-tab-${tab}`).tap();
  };
  await page.getByTestId("case-tab-contents").tap();
  await page.getByTestId("case-register").tap();
  await page.waitForURL(/#\/jobs$/, { timeout: 10000 });
  const tReg = Date.now();
  const regBudgetMs = Number(process.env.CF_E2E_REGISTER_S ?? 240) * 1000;
  const doneCard = page.locator(`[data-testid="job-card"][data-case-id="${id}"]`).filter({ hasText: /#\d+ register/ }).and(page.locator('[data-state="succeeded"], [data-state="failed"]'));
  const registered = await doneCard.waitFor({ timeout: regBudgetMs }).then(() => true, () => false);
  if (!registered) {
    if (!lenient) throw new Error(`expected: the registration finishes within CF_E2E_REGISTER_S = ${regBudgetMs / 1000} s in the release build (set CF_E2E_SLOW=1 for a slow build)`);
    await page.locator(`[data-testid="job-card"][data-case-id="${id}"]`).filter({ hasText: /#\d+ register/ })
      .and(page.locator('[data-state="running"], [data-state="queued"]')).getByTestId("cancel-job").tap();
    await page.locator(`[data-testid="job-card"][data-state="cancelled"][data-case-id="${id}"]`).filter({ hasText: /#\d+ register/ }).waitFor({ timeout: 60000 * slow });
    step(`NOTE: CF_E2E_SLOW: the registration did not finish in ${regBudgetMs / 1000} s: cancelled; the fused view is checked empty`);
    await openByTouch("fused");
    await page.getByTestId("no-result").waitFor({ timeout: 20000 });
    return { id, registered, planned };
  }
  expect(await doneCard.getAttribute("data-state") === "succeeded", `the case's registration succeeded (${await doneCard.textContent()})`);
  step(`registration of case ${id} succeeded in ${((Date.now() - tReg) / 1000).toFixed(1)} s`);
  await openByTouch("contents");
  await page.getByTestId("case-registrations").filter({ hasText: "succeeded" }).waitFor({ timeout: 20000 });

  // ---- The fused view: at full size (not the preview), textured when planned.
  await page.getByTestId("case-tab-fused").tap();
  const tTex = Date.now();
  await page.waitForFunction((tex) => { const m = document.querySelector('[data-testid="fused-model"]');
    // The picture of the view now wanted (data-seq), with or without a brain surface: without
    // one the screen once showed a full picture that carried no number, and the 1920 visit
    // below waited for it in vain (CI, ASan half, 5 Dec 2026).
    return m?.dataset.full === "true" && m.complete && m.naturalWidth > 300 && (!tex || m.dataset.textured === "true") &&
           Number(m.dataset.seq) === window.cfViewSeq() &&
           document.querySelector('[data-testid="fused-photo"]')?.naturalWidth > 100; }, planned, { timeout: 60000 * slow });
  step(`fused view${planned ? " with the photo on the model" : ""} at full size after ${((Date.now() - tTex) / 1000).toFixed(1)} s: ${await page.getByTestId("fused-info").textContent()}`);
  await shot(planned ? "12c-fused-textured" : "12-fused");
  await checkTargets("fused");
  await checkChrome("fused");
  if (planned) {
    await checkTargets("fused-textured");
    const fb = await page.getByTestId("fused-stage").boundingBox();
    const fx = Math.round(fb.x + fb.width / 2 - 60), fy = Math.round(fb.y + fb.height / 2);
    await touchDrag(Array.from({ length: 9 }, (_, i) => ({ x: fx + 15 * i, y: fy })));
    await page.waitForFunction(() => document.querySelector('[data-testid="fused-stage"]')?.dataset.atCamera === "false", null, { timeout: 30000 });
    // The turned view's full-size picture, and no fling left from the drag (a tap during a fling makes no click).
    await page.waitForFunction(() => { const i = document.querySelector('[data-testid="fused-model"]'); return i?.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq(); }, null, { timeout: 30000 });
    await page.waitForTimeout(400);
    await shot("12d-fused-turned");
    await page.getByTestId("fused-camera-view").tap();
    await page.waitForFunction(() => document.querySelector('[data-testid="fused-stage"]')?.dataset.atCamera === "true", null, { timeout: 30000 });
    step("fused view turned by a drag and back to the camera's view");
    await fusedModalitiesE2E({ page, step, expect, shot, checkTargets, caseId: id, modalities: ["t1", "ct", "fmri"] });
    await tagsE2E({ page, step, expect, shot, checkTargets, caseId: id, touchDrag });
    await caseViewLayersE2E({ page, step, expect, shot, checkTargets, caseId: id, slow });
  }
  step(`whole case ${id} by touch from new case to ${planned ? "the fused view with its layers and tags" : "the fused view"} in ${((Date.now() - t0) / 1000).toFixed(0)} s`);
  return { id, registered, planned };
}

/** The case view of a case whose plan has a CT and an fMRI map (7.10) and the histogram under the
 *  transfer-function editor (7.7): tabs T1 / CT / fMRI, each tab's histogram drawn (pixels of the
 *  bar colour counted in the canvas), CT hidden and shown (a new picture each time), a tf point
 *  added by a tap on the plot. Screenshots 08b-case-view-ct-tab, 08c-case-view-tf-point-added. */
export async function caseViewLayersE2E({ page, step, expect, shot, checkTargets, caseId, slow }) {
  await page.getByTestId("case-tab-view").tap();
  await page.getByTestId("modality-tabs").waitFor({ timeout: 20000 });
  const tabs = await page.locator('[data-testid="modality-tabs"] [data-testid^="modality-"][data-value]').evaluateAll((els) => els.map((e) => e.dataset.value));
  expect(JSON.stringify(tabs) === JSON.stringify(["t1", "ct", "fmri"]), `the case view offers the plan's modalities as tabs (${tabs})`);
  const fullNow = () => page.waitForFunction(() => { const i = document.querySelector('[data-testid="render-image"]'); return i?.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq() && i.complete; }, null, { timeout: 60000 * slow });
  await fullNow();
  // The histogram's bars: pixels of their colour (#3b4b5c) in the canvas, and the bins it holds.
  const bars = () => page.evaluate(() => {
    const c = document.querySelector('[data-testid="tf-canvas"]');
    const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    let n = 0;
    for (let i = 0; i < d.length; i += 4) if (Math.abs(d[i] - 59) <= 2 && Math.abs(d[i + 1] - 75) <= 2 && Math.abs(d[i + 2] - 92) <= 2) n++;
    return { n, bins: Number(c.dataset.histogramBins), share: n / (c.width * c.height) };
  });
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="tf-canvas"]')?.dataset.histogramBins) > 0, null, { timeout: 20000 });
  const hT1 = await bars();
  expect(hT1.bins > 0 && hT1.share > 0.02, `the T1's histogram is drawn under the tf (${hT1.bins} bins, ${(100 * hT1.share).toFixed(1)} % of the canvas in bar colour)`);
  const srcT1 = await page.getByTestId("render-image").getAttribute("src");
  await page.getByTestId("modality-ct").tap();
  await page.waitForFunction(() => document.querySelector('[data-testid="modality-ct"]')?.classList.contains("active") &&
                                   Number(document.querySelector('[data-testid="tf-canvas"]')?.dataset.histogramBins) > 0, null, { timeout: 20000 });
  await page.waitForTimeout(300);
  const hCt = await bars();
  expect(hCt.share > 0.005 && hCt.n !== hT1.n, `the CT tab draws the CT's histogram (${hCt.bins} bins, ${(100 * hCt.share).toFixed(1)} % bar colour; T1 ${(100 * hT1.share).toFixed(1)} %)`);
  await checkTargets("case view (CT tab)");
  // CT hidden, then shown: a new picture each time.
  await page.getByTestId("modality-visible").tap();
  await page.getByTestId("modality-visible").filter({ hasText: "CT hidden" }).waitFor({ timeout: 5000 });
  await page.waitForFunction((old) => { const i = document.querySelector('[data-testid="render-image"]'); return i.getAttribute("src") !== old && i.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq(); }, srcT1, { timeout: 60000 * slow });
  const srcOff = await page.getByTestId("render-image").getAttribute("src");
  await page.getByTestId("modality-visible").tap();
  await page.getByTestId("modality-visible").filter({ hasText: "CT shown" }).waitFor({ timeout: 5000 });
  await page.waitForFunction((old) => { const i = document.querySelector('[data-testid="render-image"]'); return i.getAttribute("src") !== old && i.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq(); }, srcOff, { timeout: 60000 * slow });
  await page.getByTestId("tf-canvas").scrollIntoViewIfNeeded();
  await shot("08b-case-view-ct-tab");
  await page.getByTestId("modality-fmri").tap();
  await page.waitForFunction(() => document.querySelector('[data-testid="modality-fmri"]')?.classList.contains("active"), null, { timeout: 5000 });
  // The fMRI's histogram is asked for when its tab is first shown: wait until it replaced the CT's.
  await page.waitForFunction((n) => {
    const c = document.querySelector('[data-testid="tf-canvas"]'), d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
    let k = 0;
    for (let i = 0; i < d.length; i += 4) if (Math.abs(d[i] - 59) <= 2 && Math.abs(d[i + 1] - 75) <= 2 && Math.abs(d[i + 2] - 92) <= 2) k++;
    return k > 0 && k !== n;
  }, hCt.n, { timeout: 20000 });
  const hF = await bars();
  step(`case view tabs ${tabs.join("/")}: T1 histogram ${hT1.bins} bins (${(100 * hT1.share).toFixed(1)} % of the canvas), CT ${(100 * hCt.share).toFixed(1)} %, fMRI ${(100 * hF.share).toFixed(1)} %; CT hidden and shown by touch, a new picture each`);
  // A tf point added by a tap on an empty part of the plot (T1 tab: high opacity at low intensity).
  await page.getByTestId("modality-t1").tap();
  await page.waitForTimeout(200);
  const tb = await page.getByTestId("tf-canvas").boundingBox();
  const n0 = Number(await page.getByTestId("tf-canvas").getAttribute("data-points"));
  const PAD = 14;
  await page.touchscreen.tap(tb.x + PAD + 0.12 * (tb.width - 2 * PAD), tb.y + PAD + 0.1 * (tb.height - 2 * PAD));
  await page.waitForFunction((n) => Number(document.querySelector('[data-testid="tf-canvas"]').dataset.points) === n + 1, n0, { timeout: 5000 });
  await page.waitForFunction(() => { const i = document.querySelector('[data-testid="render-image"]'); return i.dataset.tf === "custom" && i.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq(); }, null, { timeout: 60000 * slow });
  const info = await page.getByTestId("tf-info").textContent();
  expect(/intensity 1\d %, opacity 9\d %/.test(info), `the added point is where the finger tapped (${info})`);
  await page.getByTestId("tf-canvas").scrollIntoViewIfNeeded();
  await shot("08c-case-view-tf-point-added");
  step(`tf point added by a tap: ${n0} -> ${n0 + 1} points (${info}), the view re-rendered with the custom tf`);
}

/** Each main screen once at 1920x1080 (7.30): touch targets and the chrome checked, a screenshot
 *  each (19-1920-*). Back to 1280x800 at the end. */
export async function screens1920E2E({ page, step, expect, shot, checkTargets, checkChrome, caseId, registered, planned, slow }) {
  await page.setViewportSize({ width: 1920, height: 1080 });
  const visit = async (name, go, ready) => {
    await go();
    await ready();
    await page.waitForTimeout(300);
    await checkTargets(`${name} 1920`);
    await checkChrome(`${name} 1920`);
    await shot(`19-1920-${name}`);
  };
  const tab = (key) => () => page.getByTestId(`case-tab-${key}`).tap();
  await visit("cases", () => page.getByRole("link", { name: "Cases" }).first().tap(),
    () => page.getByTestId("case-row").first().waitFor({ timeout: 15000 }));
  await visit("case-view", () => page.getByTestId("case-row").filter({ hasText: "E2E whole case" }).first().tap(),
    () => page.waitForFunction(() => { const i = document.querySelector('[data-testid="render-image"]'); return i?.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq() && i.naturalWidth > 1000; }, null, { timeout: 60000 * slow }));
  expect(/#\/case\/\d+$/.test(page.url()) && page.url().endsWith(`/${caseId}`), `the whole case opened from the list (${page.url()})`);
  await visit("contents", tab("contents"), () => page.getByTestId("case-holdings").waitFor({ timeout: 15000 }));
  await visit("preoperative", tab("plan"), planned
    ? () => page.waitForFunction(() => Number(document.querySelector('[data-testid="plan-check"]')?.dataset.voxels) > 1000, null, { timeout: 60000 })
    : () => page.getByTestId("plan-stage").filter({ hasText: "Plan job" }).waitFor({ timeout: 20000 }));
  await visit("tracker", tab("tracker"), () => page.waitForFunction(() => document.querySelector('[data-testid="tracker-slices"]')?.naturalWidth > 0, null, { timeout: 20000 }));
  await visit("photo-marks", tab("photo"), () => page.waitForFunction(() => document.querySelector('[data-testid="photo-image"]')?.naturalWidth > 0 &&
    document.querySelector('[data-testid="alignment"]')?.dataset.state === "ok", null, { timeout: 20000 }));
  await visit("fused", tab("fused"), registered
    ? () => page.waitForFunction(() => { const m = document.querySelector('[data-testid="fused-model"]'); return m?.dataset.full === "true" && m.complete && m.naturalWidth > 600 && Number(m.dataset.seq) === window.cfViewSeq(); }, null, { timeout: 60000 * slow })
    : () => page.getByTestId("no-result").waitFor({ timeout: 20000 }));
  await visit("jobs", () => page.getByRole("link", { name: "Jobs" }).tap(), () => page.getByTestId("job-card").first().waitFor({ timeout: 15000 }));
  await page.setViewportSize({ width: 1280, height: 800 });
  step("1920x1080: cases, case view, contents, preoperative, tracker, photo & marks, fused and jobs opened; targets and chrome checked");
}
