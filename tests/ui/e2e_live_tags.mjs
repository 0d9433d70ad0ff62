// The camera's live view on the Photo screen and stimulation tags in the fused view, in the
// end-to-end test (called by e2e.mjs). Screenshots photo-live-01.png, fused-tags-01.png,
// fused-tags-02-turned.png.

const apiOf = (page) => (method, p, body) => page.evaluate(async ([m, u, b]) => {
  const r = await fetch(u, { method: m, headers: { "Content-Type": "application/json" }, body: b === null ? undefined : JSON.stringify(b) });
  return { status: r.status, j: await r.json().catch(() => null) };
}, [method, p, body ?? null]);

/** Live view of the (simulated) camera on case `caseId`'s Photo screen: frames arrive, Capture
 *  stores a photo, leaving the screen stops the stream. */
export async function liveViewE2E({ page, base, step, expect, shot, checkTargets, caseId }) {
  const api = apiOf(page);
  const before = (await api("GET", `/api/cases/${caseId}`)).j.photos.length;
  await page.evaluate((id) => { location.hash = `#/case/${id}/photo`; }, caseId);
  await page.getByTestId("live-toggle").tap();
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="live-frame"]')?.dataset.seq) >= 1 &&
                                   document.querySelector('[data-testid="live-frame"]').naturalWidth > 100, null, { timeout: 60000 });
  const s0 = Number(await page.getByTestId("live-frame").getAttribute("data-seq"));
  await page.waitForFunction((s) => Number(document.querySelector('[data-testid="live-frame"]')?.dataset.seq) >= s + 3, s0, { timeout: 30000 });
  const s1 = Number(await page.getByTestId("live-frame").getAttribute("data-seq"));
  expect(s1 >= s0 + 3, `live frames advance (${s0} -> ${s1})`);
  const cam = (await api("GET", "/api/camera")).j;
  expect(cam.live === true, `the camera streams while the Photo screen polls (live ${cam.live})`);
  step(`live view: frames ${s0} -> ${s1}; ${await page.getByTestId("live-status").textContent()}`);
  await shot("photo-live-01");
  await checkTargets("photo-live");
  const cb = await page.getByTestId("live-capture").boundingBox();
  expect(cb.height >= 79, `Capture is a big button (${cb.width.toFixed(0)}x${cb.height.toFixed(0)} px)`);
  const oldPhoto = await page.evaluate(() => document.querySelector('[data-testid="photo-image"]')?.getAttribute("src") ?? "");
  await page.getByTestId("live-capture").tap();
  // Polled here (a waitForFunction predicate that returns a promise counts as true at once).
  const until = async (what, cond, ms) => {
    const t = Date.now();
    while (!(await cond())) {
      if (Date.now() - t > ms) throw new Error(`${what}: not within ${ms / 1000} s`);
      await page.waitForTimeout(200);
    }
    return (Date.now() - t) / 1000;
  };
  await until("the captured photo stored", async () => (await api("GET", `/api/cases/${caseId}`)).j.photos.length === before + 1, 60000);
  step(`Capture stored photo ${before + 1} of the case`);
  // Live again on the reloaded screen, then leave it: the polling stops and the daemon stops the
  // stream 2 s after the last request.
  // The screen reloads with the new photo (a new picture, not the one shown before the capture).
  await page.waitForFunction((old) => { const i = document.querySelector('[data-testid="photo-image"]'); return !!i && i.getAttribute("src") !== old; }, oldPhoto, { timeout: 30000 });
  await page.getByTestId("live-toggle").tap();
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="live-frame"]')?.dataset.seq) >= 1, null, { timeout: 30000 });
  const s2 = Number(await page.getByTestId("live-frame").getAttribute("data-seq"));
  await page.waitForFunction((s) => Number(document.querySelector('[data-testid="live-frame"]')?.dataset.seq) > s, s2, { timeout: 30000 }); // a frame of the new stream
  expect((await api("GET", "/api/camera")).j.live === true, "live again after the capture");
  await page.evaluate((id) => { location.hash = `#/case/${id}/contents`; }, caseId);
  const stoppedS = await until("the stream stopped after the screen was left", async () => (await api("GET", "/api/camera")).j.live === false, 10000);
  expect(stoppedS > 1, `the stream ran on until the idle time (${stoppedS.toFixed(1)} s), so it was live when the screen was left`);
  step(`live view stopped ${stoppedS.toFixed(1)} s after the Photo screen was left`);
}

/** Tags in the fused view of `caseId` (textured, at the registered camera): Place tag, a tap on
 *  the brain, the marker where the finger was, stored with its point on the surface; the marker
 *  follows a turn of the view; a reviewer cannot place one (the daemon's 403 too). */
export async function tagsE2E({ page, step, expect, shot, checkTargets, caseId, touchDrag }) {
  const api = apiOf(page);
  const n0 = (await api("GET", `/api/cases/${caseId}/tags`)).j.tags.length;
  // The view's full-size picture first (the screenshots below are of it, not of a preview).
  await page.waitForFunction(() => { const i = document.querySelector('[data-testid="fused-model"]'); return i?.dataset.full === "true" && i.complete && Number(i.dataset.seq) === window.cfViewSeq(); }, null, { timeout: 60000 });
  await page.getByTestId("tags-status").filter({ hasText: /tag|No tags/ }).waitFor({ timeout: 10000 });
  await page.getByTestId("tag-note").fill("hand motor (e2e)");
  await page.getByTestId("tag-place").tap();
  const sb = await page.getByTestId("fused-stage").boundingBox();
  const tx = Math.round(sb.x + sb.width / 2 + 10), ty = Math.round(sb.y + sb.height / 2 + 5);
  await page.touchscreen.tap(tx, ty);
  await page.locator('[data-testid="tag-marker"]').nth(n0).waitFor({ timeout: 30000 });
  const t = (await api("GET", `/api/cases/${caseId}/tags`)).j;
  expect(t.tags.length === n0 + 1, `one tag more stored (${t.tags.length})`);
  const tag = t.tags[t.tags.length - 1];
  expect(Array.isArray(tag.world_mm) && tag.world_mm.length === 3 && tag.note === "hand motor (e2e)", `the tag has its point on the surface and its note (${JSON.stringify(tag)})`);
  // The marker is drawn where the finger touched (within 3 CSS px).
  const mb = await page.locator(`[data-testid="tag-marker"][data-label="${tag.label}"] circle`).boundingBox();
  const dx = mb.x + mb.width / 2 - tx, dy = mb.y + mb.height / 2 - ty;
  expect(Math.hypot(dx, dy) < 3, `the marker is where the finger was (${dx.toFixed(1)}, ${dy.toFixed(1)} px off)`);
  expect(mb.width >= 20, `the marker is big enough to see (${mb.width.toFixed(0)} px)`);
  step(`tag ${tag.label} at photo pixel (${tag.pixel.map((v) => v.toFixed(1)).join(", ")}) -> (${tag.world_mm.map((v) => v.toFixed(1)).join(", ")}) mm LPS`);
  await shot("fused-tags-01");
  await checkTargets("fused-tags");
  // Stop placing, turn the view: the marker moves with the brain.
  await page.getByTestId("tag-place").tap();
  const x0 = Number(await page.locator(`[data-testid="tag-marker"][data-label="${tag.label}"]`).getAttribute("data-x"));
  const fx = Math.round(sb.x + sb.width / 2 - 60), fy = Math.round(sb.y + sb.height / 2);
  await touchDrag(Array.from({ length: 9 }, (_, i) => ({ x: fx + 15 * i, y: fy })));
  await page.waitForFunction(() => document.querySelector('[data-testid="fused-stage"]')?.dataset.atCamera === "false", null, { timeout: 30000 });
  // The turned view's full-size picture (previews while the finger moved), and no fling left
  // from the drag: a tap during a fling makes no click in chromium.
  await page.waitForFunction(() => { const i = document.querySelector('[data-testid="fused-model"]'); return i?.dataset.full === "true" && Number(i.dataset.seq) === window.cfViewSeq(); }, null, { timeout: 30000 });
  await page.waitForTimeout(400);
  await page.waitForFunction(([l, x]) => Math.abs(Number(document.querySelector(`[data-testid="tag-marker"][data-label="${l}"]`)?.dataset.x) - x) > 5, [tag.label, x0], { timeout: 30000 });
  const x1 = Number(await page.locator(`[data-testid="tag-marker"][data-label="${tag.label}"]`).getAttribute("data-x"));
  step(`the view turned: marker ${tag.label} moved from x ${x0.toFixed(1)} to ${x1.toFixed(1)} view px`);
  await shot("fused-tags-02-turned");
  await page.getByTestId("fused-camera-view").tap();
  await page.waitForFunction(() => document.querySelector('[data-testid="fused-stage"]')?.dataset.atCamera === "true", null, { timeout: 30000 });
  return tag;
}

/** The Preoperative step of a planned case: the plan job shown succeeded (full bar) and the quick
 *  check picture of its brain mask drawn. Screenshot plan-01-check.png. */
export async function planCheckE2E({ page, step, expect, shot, checkTargets, caseId }) {
  await page.evaluate((id) => { location.hash = `#/case/${id}/plan`; }, caseId);
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="plan-check"]')?.dataset.voxels) > 1000, null, { timeout: 60000 });
  await page.getByTestId("plan-stage").filter({ hasText: "succeeded" }).waitFor({ timeout: 10000 });
  const w = await page.evaluate(() => document.querySelector('[data-testid="plan-progress"] .bar').style.width);
  expect(w === "100%", `the plan's progress bar is full (${w})`);
  // The brain surface (7.6b): cut by the same slices, drawn over the mask, inside the mask.
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="plan-check"]')?.dataset.surfaceSegments) > 100, null, { timeout: 30000 });
  const inMask = Number(await page.getByTestId("plan-check").getAttribute("data-surface-in-mask"));
  expect(inMask >= 0.9, `the plan's surface outline lies inside its brain mask (${(100 * inMask).toFixed(1)} % within 2 voxels)`);
  step(`Preoperative: ${await page.getByTestId("plan-check-text").textContent()}`);
  await shot("plan-01-check");
  await checkTargets("preoperative");
}

/** An image fiducial placed by a tap on the Tracker screen's slices (a case of its own): the
 *  new fiducial lands at the point the tapped slice shows (within a slice pixel). */
export async function trackerPlaceE2E({ page, base, step, expect, shot }) {
  const api = apiOf(page);
  const c = await api("POST", "/api/cases", { title: "E2E tracker fiducial by touch" });
  expect(c.status === 201, `case created (${c.status})`);
  await page.goto(`${base}/#/case/${c.j.id}/tracker`);
  await page.getByTestId("suggest-btn").tap();
  await page.locator('[data-testid^="fid-row-"]').nth(5).waitFor({ timeout: 15000 });
  await page.waitForFunction(() => !!document.querySelector('[data-testid="tracker-slices"]')?.dataset.point &&
                                   document.querySelector('[data-testid="tracker-slices"]').naturalWidth > 0, null, { timeout: 15000 });
  const centre = (await page.getByTestId("tracker-slices").getAttribute("data-point")).split(",").map(Number);
  await page.getByTestId("place-fid-btn").tap();
  // A tap on the coronal panel, 30 slice pixels right of and 20 above its centre: +x and +z.
  const b = await page.getByTestId("tracker-slices").boundingBox();
  const k = b.width / 720; // 3 panels of 240 px
  await page.touchscreen.tap(b.x + (240 + 120 + 30) * k, b.y + (120 - 20) * k);
  await page.getByTestId("fid-row-F1").waitFor({ timeout: 15000 });
  const nav = (await api("GET", `/api/cases/${c.j.id}/navigation`)).j;
  const f = nav.image_fiducials.fiducials.find((x) => x.label === "F1");
  const want = [centre[0] + 30 * 220 / 240, centre[1], centre[2] + 20 * 220 / 240];
  const err = Math.hypot(...f.p_image_mm.map((v, i) => v - want[i]));
  expect(err < 2, `F1 at (${f.p_image_mm.map((v) => v.toFixed(1)).join(", ")}) mm, expected (${want.map((v) => v.toFixed(1)).join(", ")}) (${err.toFixed(2)} mm off)`);
  step(`fiducial F1 placed by a tap on the coronal slice, ${err.toFixed(2)} mm from the tapped point`);
  await shot("tracker-04-fiducial-by-touch");
}
