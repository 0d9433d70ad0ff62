// The fused view's modality toggles in the end-to-end test (called by e2e.mjs): an fMRI map
// uploaded into the case before its plan (so the plan stores plan_fmri_on_t1), then in the
// textured fused view the fMRI layer turned off by touch: the daemon draws a different picture
// (compared pixel by pixel in the page), and on again. Screenshots fused-modalities-01-fmri-on.png,
// fused-modalities-02-fmri-off.png. With a CPU-only daemon the view says why the layers are not
// drawn (fused-modalities-01-cpu-note.png).
import fs from "node:fs";
import zlib from "node:zlib";

/** An fMRI statistic map on the grid of `maskPath` (a uint8 NIfTI-1 brain mask, gzip): the
 *  mask's voxels in the upper half of its slices (third voxel index) as activation z 4..10
 *  rising towards the last slice, 0 elsewhere; float32 NIfTI-1, gzip. (Half the brain
 *  "active": part of it shows from the phantom's camera, the photo lies on the rest.) */
export function activationMap(maskPath) {
  const m = zlib.gunzipSync(fs.readFileSync(maskPath));
  const dims = [m.readInt16LE(42), m.readInt16LE(44), m.readInt16LE(46)];
  const datatype = m.readInt16LE(70), off = Math.round(m.readFloatLE(108));
  if (m.readInt32LE(0) !== 348 || datatype !== 2) throw new Error(`${maskPath}: not a little-endian uint8 NIfTI-1 mask (datatype ${datatype})`);
  const n = dims[0] * dims[1] * dims[2], slab = dims[0] * dims[1];
  const out = Buffer.alloc(352 + 4 * n);
  m.copy(out, 0, 0, 348);          // the header: dims, spacing, qform/sform kept
  out.writeInt16LE(16, 70);        // datatype float32
  out.writeInt16LE(32, 72);        // bitpix
  out.writeFloatLE(352, 108);      // vox_offset
  out.writeFloatLE(1, 112);        // scl_slope
  out.writeFloatLE(0, 116);        // scl_inter
  out.writeFloatLE(0, 124);        // cal_max
  out.writeFloatLE(0, 128);        // cal_min
  let k0 = dims[2], k1 = -1;
  for (let i = 0; i < n; i++) if (m[off + i]) { const k = Math.floor(i / slab); k0 = Math.min(k0, k); k1 = Math.max(k1, k); }
  const kMid = (k0 + k1) / 2;
  for (let i = 0; i < n; i++) {
    const k = Math.floor(i / slab);
    if (m[off + i] && k >= kMid) out.writeFloatLE(4 + (6 * k) / dims[2], 352 + 4 * i);
  }
  return zlib.gzipSync(out, { level: 1 });
}

/** Uploads the activation map into case `caseId` as its fMRI (before the plan job runs). */
export async function uploadActivation({ base, caseId, maskPath, step, expect }) {
  const bytes = activationMap(maskPath);
  const r = await fetch(`${base}/api/cases/${caseId}/volumes?name=fmri_e2e.nii.gz&modality=fMRI`,
    { method: "POST", body: bytes, headers: { "Content-Type": "application/octet-stream" } });
  expect(r.status === 201, `fMRI map uploaded (${r.status} ${r.status === 201 ? "" : await r.text()})`);
  step(`fMRI activation map (${(bytes.length / 1024).toFixed(0)} KiB) uploaded into case ${caseId} before its plan`);
}

/** In the textured fused view of a case planned with the fMRI map: the modality toggles (only
 *  the plan's: T1 and fMRI), fMRI off changes the picture, on again gives it back. */
export async function fusedModalitiesE2E({ page, step, expect, shot, checkTargets, caseId }) {
  const model = page.getByTestId("fused-model");
  await page.locator('[data-testid="fused-modality-fmri"], [data-testid="fused-modality-note"]').first().waitFor({ timeout: 60000 });
  await page.waitForFunction(() => document.querySelector('[data-testid="fused-model"]')?.dataset.textured === "true", null, { timeout: 60000 });
  if (await page.getByTestId("fused-modality-note").count()) {
    step(`fused view on a CPU-only daemon: ${await page.getByTestId("fused-modality-note").textContent()}`);
    await shot("fused-modalities-01-cpu-note");
    return;
  }
  const offered = await page.locator('[data-testid^="fused-modality-"][data-visible]').evaluateAll((els) => els.map((e) => e.dataset.testid.replace("fused-modality-", "")));
  expect(JSON.stringify(offered) === JSON.stringify(["t1", "fmri"]), `only the plan's modalities are offered (${offered})`);
  for (const id of ["fused-modality-fmri", "fused-weight-fmri", "fused-modality-t1"]) {
    const b = await page.getByTestId(id).boundingBox();
    expect(b && b.height >= 48 && b.width >= 48, `${id} is a touch target of at least 48 px (${b?.width.toFixed(0)}x${b?.height.toFixed(0)})`);
  }
  await page.waitForFunction(() => { const i = document.querySelector('[data-testid="fused-model"]'); return i?.dataset.layers === "t1,fmri" && i.dataset.full === "true" && i.complete; }, null, { timeout: 60000 });
  const srcOn = await model.getAttribute("src");
  await shot("fused-modalities-01-fmri-on");
  await checkTargets("fused-modalities");
  const t0 = Date.now();
  await page.getByTestId("fused-modality-fmri").tap();
  await page.waitForFunction((old) => { const i = document.querySelector('[data-testid="fused-model"]'); return i?.dataset.layers === "t1" && i.dataset.full === "true" && i.getAttribute("src") !== old && i.complete && i.naturalWidth > 300; },
    srcOn, { timeout: 60000 });
  const srcOff = await model.getAttribute("src");
  const tOff = (Date.now() - t0) / 1000;
  expect(await page.getByTestId("fused-modality-fmri").getAttribute("data-visible") === "false", "the fMRI button shows it off");
  await shot("fused-modalities-02-fmri-off");
  // The two pictures, pixel by pixel in the page: mean |difference| over RGB (0..255).
  const diff = await page.evaluate(async ([a, b]) => {
    const load = (u) => new Promise((res, rej) => { const i = new Image(); i.onload = () => res(i); i.onerror = rej; i.src = u; });
    const [ia, ib] = await Promise.all([load(a), load(b)]);
    const c = document.createElement("canvas");
    c.width = ia.naturalWidth; c.height = ia.naturalHeight;
    const g = c.getContext("2d");
    g.drawImage(ia, 0, 0);
    const da = g.getImageData(0, 0, c.width, c.height).data;
    g.clearRect(0, 0, c.width, c.height);
    g.drawImage(ib, 0, 0);
    const db = g.getImageData(0, 0, c.width, c.height).data;
    let s = 0, changed = 0;
    for (let i = 0; i < da.length; i += 4) {
      const d = Math.abs(da[i] - db[i]) + Math.abs(da[i + 1] - db[i + 1]) + Math.abs(da[i + 2] - db[i + 2]);
      s += d;
      changed += d > 30 ? 1 : 0;
    }
    return { mean: s / (3 * da.length / 4), changedFraction: changed / (da.length / 4), w: c.width, h: c.height };
  }, [srcOn, srcOff]);
  expect(diff.mean > 1 && diff.changedFraction > 0.01, `fMRI off changes the fused picture (mean |diff| ${diff.mean.toFixed(2)}, ${(100 * diff.changedFraction).toFixed(1)} % of pixels)`);
  step(`fused view fMRI off by touch: new picture in ${tOff.toFixed(1)} s, ${diff.w}x${diff.h}, mean |diff| ${diff.mean.toFixed(2)} grey levels, ${(100 * diff.changedFraction).toFixed(1)} % of pixels changed by > 30`);
  // And on again: the layers say so (the picture is the fMRI's again).
  await page.getByTestId("fused-modality-fmri").tap();
  await page.waitForFunction(() => document.querySelector('[data-testid="fused-model"]')?.dataset.layers === "t1,fmri", null, { timeout: 60000 });
  // The case's Tracker screen cuts its slices from the case's own T1 (not the bundled MRI),
  // then back to the fused view at the camera.
  await page.evaluate((id) => { location.hash = `#/case/${id}/tracker`; }, caseId);
  await page.waitForFunction(() => /^case \d+ volume \d+$/.test(document.querySelector('[data-testid="suggest-btn"]')?.dataset.volume ?? ""), null, { timeout: 20000 });
  const vol = await page.getByTestId("suggest-btn").getAttribute("data-volume");
  expect(vol.startsWith(`case ${caseId} `), `the Tracker's slices are of the case's volume (${vol})`);
  step(`Tracker screen of case ${caseId}: slices and suggested fiducials from ${vol}`);
  await page.evaluate((id) => { location.hash = `#/case/${id}/fused`; }, caseId);
  await page.waitForFunction(() => document.querySelector('[data-testid="fused-model"]')?.dataset.textured === "true" &&
                                   document.querySelector('[data-testid="fused-stage"]')?.dataset.atCamera === "true", null, { timeout: 60000 });
}
