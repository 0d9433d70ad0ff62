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
 *  "active": part of it shows from the phantom's camera, the photo lies on the rest.)
 *  With `blob` ({centre_lps_mm, radius_mm}) instead one cluster, as the daemon's FusedModalities
 *  test makes, but inside the mask only: z 10 at the centre falling to 4 at the radius (world from
 *  the header's sform). */
export function activationMap(maskPath, blob = null) {
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
  if (blob) {
    if (m.readInt16LE(254) <= 0) throw new Error(`${maskPath}: no sform to place the fMRI blob`);
    const S = [0, 1, 2].map((r) => [0, 1, 2, 3].map((c) => m.readFloatLE(280 + 16 * r + 4 * c)));  // RAS mm from ijk
    const [cx, cy, cz] = blob.centre_lps_mm, r = blob.radius_mm;
    // Only the voxels of the ball's bounding box (the inverse of the sform's 3x3 for its centre).
    const A = S.map((row) => row.slice(0, 3)), b = [-cx - S[0][3], -cy - S[1][3], cz - S[2][3]];
    const det = (M) => M[0][0] * (M[1][1] * M[2][2] - M[1][2] * M[2][1]) - M[0][1] * (M[1][0] * M[2][2] - M[1][2] * M[2][0]) + M[0][2] * (M[1][0] * M[2][1] - M[1][1] * M[2][0]);
    const c0 = [0, 1, 2].map((a) => det(A.map((row, ri) => row.map((v, ci) => (ci === a ? b[ri] : v)))) / det(A));  // Cramer
    const reach = Math.ceil(r / Math.min(...[0, 1, 2].map((a) => Math.hypot(A[0][a], A[1][a], A[2][a])))) + 1;
    const lo = c0.map((c, a) => Math.max(0, Math.floor(c) - reach)), hi = c0.map((c, a) => Math.min(dims[a] - 1, Math.ceil(c) + reach));
    for (let k = lo[2]; k <= hi[2]; k++) for (let j = lo[1]; j <= hi[1]; j++) for (let i = lo[0]; i <= hi[0]; i++) {
      const x = -(S[0][0] * i + S[0][1] * j + S[0][2] * k + S[0][3]), y = -(S[1][0] * i + S[1][1] * j + S[1][2] * k + S[1][3]);
      const z = S[2][0] * i + S[2][1] * j + S[2][2] * k + S[2][3];
      const d = Math.hypot(x - cx, y - cy, z - cz);
      const v = i + dims[0] * (j + dims[1] * k);
      if (d < r && m[off + v]) out.writeFloatLE(4 + 6 * (1 - d / r), 352 + 4 * v);  // in the brain only
    }
    return zlib.gzipSync(out, { level: 1 });
  }
  let k0 = dims[2], k1 = -1;
  for (let i = 0; i < n; i++) if (m[off + i]) { const k = Math.floor(i / slab); k0 = Math.min(k0, k); k1 = Math.max(k1, k); }
  const kMid = (k0 + k1) / 2;
  for (let i = 0; i < n; i++) {
    const k = Math.floor(i / slab);
    if (m[off + i] && k >= kMid) out.writeFloatLE(4 + (6 * k) / dims[2], 352 + 4 * i);
  }
  return zlib.gzipSync(out, { level: 1 });
}

/** A CT-like volume made from a uint8 NIfTI-1 T1 and its brain mask on the same grid (as the
 *  daemon's FusedModalities test does): soft tissue (40 HU) in the brain, bone (900 HU) where the
 *  head outside it is brighter than the T1's median over the head, air (-1000 HU) elsewhere;
 *  every `step`-th voxel (a coarser grid over the same field, like a real CT's other grid), int16
 *  NIfTI-1, gzip. There is no CT in the repository's data; this one makes the plan's CT layer. */
export function ctLikeMap(t1Path, maskPath, step = 2) {
  const t = zlib.gunzipSync(fs.readFileSync(t1Path)), m = zlib.gunzipSync(fs.readFileSync(maskPath));
  const dims = [t.readInt16LE(42), t.readInt16LE(44), t.readInt16LE(46)];
  const offT = Math.round(t.readFloatLE(108)), offM = Math.round(m.readFloatLE(108));
  if (t.readInt32LE(0) !== 348 || t.readInt16LE(70) !== 2 || m.readInt16LE(70) !== 2) throw new Error(`${t1Path}, ${maskPath}: not uint8 NIfTI-1 volumes`);
  if ([0, 1, 2].some((a) => m.readInt16LE(42 + 2 * a) !== dims[a])) throw new Error(`${maskPath}: not on the grid of ${t1Path}`);
  const n = dims[0] * dims[1] * dims[2];
  const hist = new Float64Array(256);
  let head = 0;
  for (let i = 0; i < n; i++) if (t[offT + i] > 0) { hist[t[offT + i]]++; head++; }
  let p50 = 0;
  for (let acc = 0; p50 < 255 && acc + hist[p50] < head / 2; p50++) acc += hist[p50];
  const d = dims.map((x) => Math.floor((x - 1) / step) + 1);
  const out = Buffer.alloc(352 + 2 * d[0] * d[1] * d[2]);
  t.copy(out, 0, 0, 348);
  for (let a = 0; a < 3; a++) out.writeInt16LE(d[a], 42 + 2 * a);
  for (let a = 0; a < 3; a++) out.writeFloatLE(t.readFloatLE(80 + 4 * a) * step, 80 + 4 * a); // pixdim
  for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) out.writeFloatLE(t.readFloatLE(280 + 16 * r + 4 * c) * step, 280 + 16 * r + 4 * c); // srow
  out.writeInt16LE(4, 70);      // datatype int16
  out.writeInt16LE(16, 72);     // bitpix
  out.writeFloatLE(352, 108);   // vox_offset
  out.writeFloatLE(1, 112);     // scl_slope
  out.writeFloatLE(0, 116);     // scl_inter
  out.writeFloatLE(0, 124);     // cal_max
  out.writeFloatLE(0, 128);     // cal_min
  let o = 352;
  for (let k = 0; k < dims[2]; k += step) for (let j = 0; j < dims[1]; j += step) for (let i = 0; i < dims[0]; i += step) {
    const v = i + dims[0] * (j + dims[1] * k);
    out.writeInt16LE(m[offM + v] ? 40 : t[offT + v] > p50 ? 900 : -1000, o);
    o += 2;
  }
  return zlib.gzipSync(out, { level: 1 });
}

/** In the textured fused view of a case planned with the fMRI map: the modality toggles (only
 *  the plan's: `modalities`, T1 and fMRI by default), fMRI off changes the picture, on again
 *  gives it back. */
export async function fusedModalitiesE2E({ page, step, expect, shot, checkTargets, caseId, modalities = ["t1", "fmri"] }) {
  const model = page.getByTestId("fused-model");
  await page.locator('[data-testid="fused-modality-fmri"], [data-testid="fused-modality-note"]').first().waitFor({ timeout: 60000 });
  await page.waitForFunction(() => document.querySelector('[data-testid="fused-model"]')?.dataset.textured === "true", null, { timeout: 60000 });
  if (await page.getByTestId("fused-modality-note").count()) {
    step(`fused view on a CPU-only daemon: ${await page.getByTestId("fused-modality-note").textContent()}`);
    await shot("fused-modalities-01-cpu-note");
    return;
  }
  const offered = await page.locator('[data-testid^="fused-modality-"][data-visible]').evaluateAll((els) => els.map((e) => e.dataset.testid.replace("fused-modality-", "")));
  expect(JSON.stringify(offered) === JSON.stringify(modalities), `only the plan's modalities are offered (${offered}; expected ${modalities})`);
  for (const id of ["fused-modality-fmri", "fused-weight-fmri", "fused-modality-t1"]) {
    const b = await page.getByTestId(id).boundingBox();
    expect(b && b.height >= 48 && b.width >= 48, `${id} is a touch target of at least 48 px (${b?.width.toFixed(0)}x${b?.height.toFixed(0)})`);
  }
  const all = modalities.join(","), noFmri = modalities.filter((m) => m !== "fmri").join(",");
  // The full-size picture of the newest view (seq): after Camera view the picture shown first is
  // the turned view's full one, then the new view's preview.
  await page.waitForFunction((l) => { const i = document.querySelector('[data-testid="fused-model"]'); return i?.dataset.layers === l && i.dataset.full === "true" && i.complete && Number(i.dataset.seq) === window.cfViewSeq(); }, all, { timeout: 60000 });
  const srcOn = await model.getAttribute("src");
  await shot("fused-modalities-01-fmri-on");
  await checkTargets("fused-modalities");
  const t0 = Date.now();
  await page.getByTestId("fused-modality-fmri").tap();
  await page.waitForFunction(([old, l]) => { const i = document.querySelector('[data-testid="fused-model"]'); return i?.dataset.layers === l && i.dataset.full === "true" && i.getAttribute("src") !== old && i.complete && i.naturalWidth > 300 && Number(i.dataset.seq) === window.cfViewSeq(); },
    [srcOn, noFmri], { timeout: 60000 });
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
    return { mean: s / (3 * da.length / 4), changedFraction: changed / (da.length / 4), w: c.width, h: c.height, same: ia.naturalWidth === ib.naturalWidth && ia.naturalHeight === ib.naturalHeight };
  }, [srcOn, srcOff]);
  expect(diff.same, "the pictures with and without the fMRI are the same size (both full size)");
  expect(diff.mean > 1 && diff.changedFraction > 0.01, `fMRI off changes the fused picture (mean |diff| ${diff.mean.toFixed(2)}, ${(100 * diff.changedFraction).toFixed(1)} % of pixels)`);
  step(`fused view fMRI off by touch: new picture in ${tOff.toFixed(1)} s, ${diff.w}x${diff.h}, mean |diff| ${diff.mean.toFixed(2)} grey levels, ${(100 * diff.changedFraction).toFixed(1)} % of pixels changed by > 30`);
  // And on again: the layers say so (the picture is the fMRI's again).
  await page.getByTestId("fused-modality-fmri").tap();
  await page.waitForFunction((l) => document.querySelector('[data-testid="fused-model"]')?.dataset.layers === l, all, { timeout: 60000 });
  // The case's Tracker screen cuts its slices from the case's own T1 (not the bundled MRI),
  // then back to the fused view at the camera.
  await page.getByTestId("case-tab-tracker").tap();
  await page.waitForFunction(() => /^case \d+ volume \d+$/.test(document.querySelector('[data-testid="suggest-btn"]')?.dataset.volume ?? ""), null, { timeout: 20000 });
  const vol = await page.getByTestId("suggest-btn").getAttribute("data-volume");
  expect(vol.startsWith(`case ${caseId} `), `the Tracker's slices are of the case's volume (${vol})`);
  step(`Tracker screen of case ${caseId}: slices and suggested fiducials from ${vol}`);
  await page.getByTestId("case-tab-fused").tap();
  await page.waitForFunction(() => document.querySelector('[data-testid="fused-model"]')?.dataset.textured === "true" &&
                                   document.querySelector('[data-testid="fused-stage"]')?.dataset.atCamera === "true", null, { timeout: 60000 });
}
