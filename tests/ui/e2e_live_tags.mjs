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
  await page.getByTestId("live-capture").tap();
  await page.waitForFunction(async ([id, n]) => (await (await fetch(`/api/cases/${id}`)).json()).photos.length === n + 1, [caseId, before], { timeout: 60000, polling: 500 });
  step(`Capture stored photo ${before + 1} of the case`);
  // Live again on the reloaded screen, then leave it: the polling stops and the daemon stops the
  // stream 2 s after the last request.
  await page.getByTestId("photo-image").waitFor({ timeout: 30000 });
  await page.getByTestId("live-toggle").tap();
  await page.waitForFunction(() => Number(document.querySelector('[data-testid="live-frame"]')?.dataset.seq) >= 1, null, { timeout: 30000 });
  expect((await api("GET", "/api/camera")).j.live === true, "live again after the capture");
  await page.evaluate((id) => { location.hash = `#/case/${id}/contents`; }, caseId);
  const t0 = Date.now();
  await page.waitForFunction(async () => (await (await fetch("/api/camera")).json()).live === false, null, { timeout: 10000, polling: 200 });
  const stoppedS = (Date.now() - t0) / 1000;
  expect(stoppedS > 1, `the stream ran on until the idle time (${stoppedS.toFixed(1)} s), so it was live when the screen was left`);
  step(`live view stopped ${stoppedS.toFixed(1)} s after the Photo screen was left`);
}

/** Tags in the fused view of `caseId` (textured, at the registered camera): Place tag, a tap on
 *  the brain, the marker where the finger was, stored with its point on the surface; the marker
 *  follows a turn of the view; a reviewer cannot place one (the daemon's 403 too). */
export async function tagsE2E({ page, step, expect, shot, checkTargets, caseId, touchDrag }) {
  const api = apiOf(page);
  const n0 = (await api("GET", `/api/cases/${caseId}/tags`)).j.tags.length;
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
  step(`Preoperative: ${await page.getByTestId("plan-check-text").textContent()}`);
  await shot("plan-01-check");
  await checkTargets("preoperative");
}
