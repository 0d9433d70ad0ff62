// The Preoperative step of a case (issue 7): the case's volumes, `Start planning` (the plan
// job: brain mask, surface, CT/fMRI on the T1) with its progress bar from the push channel's
// notify_job (and a 2 s poll in case one is dropped), Cancel, and when the plan is there a quick
// check picture of its brain mask: three orthogonal slices through the mask's centroid, drawn
// here from the stored plan_brain_mask (NIfTI, read by nifti.ts).
import { apiBlob, apiJson } from "./api";
import { h } from "./dom";
import { gunzipIfNeeded, parseNifti, type Volume } from "./nifti";
import { parsePly, surfaceOutline } from "./surface_outline";
import "./plan_screen.css";

export interface PlanJob { id: number; kind: string; state: string; stage: string; fraction: number; error?: string; params?: Record<string, unknown> }
interface CaseLite { volumes?: { id: number; modality: string; original_name: string }[]; results?: { id: number; kind: string; name: string }[] }

/** The newest plan job of the case (any state), or null. */
export function planJobOf(jobs: PlanJob[], caseId: number): PlanJob | null {
  let best: PlanJob | null = null;
  for (const j of jobs) if (j.kind === "plan" && Number(j.params?.case_id) === caseId && (!best || j.id > best.id)) best = j;
  return best;
}

/** Three orthogonal slices (axial, coronal, sagittal in voxel index order) through the mask's
 *  centroid, side by side, as 8-bit grey (255 inside). `n`: each slice's side in the output
 *  (nearest neighbour). Null for an empty mask. */
export function maskQuickCheck(vol: Volume, n = 160): { width: number; height: number; grey: Uint8ClampedArray; centroid: [number, number, number]; voxels: number } | null {
  const [X, Y, Z] = vol.dims;
  let sx = 0, sy = 0, sz = 0, cnt = 0;
  for (let k = 0; k < Z; k++) for (let j = 0; j < Y; j++) for (let i = 0; i < X; i++)
    if (vol.data[i + X * (j + Y * k)] > 0) { sx += i; sy += j; sz += k; cnt++; }
  if (!cnt) return null;
  const c: [number, number, number] = [Math.round(sx / cnt), Math.round(sy / cnt), Math.round(sz / cnt)];
  const grey = new Uint8ClampedArray(3 * n * n);
  const at = (i: number, j: number, k: number) => (vol.data[i + X * (j + Y * k)] > 0 ? 255 : 0);
  // Panel p: (u, v) over the two axes other than its normal; v flipped so superior/anterior is up.
  const panels: ((u: number, v: number) => number)[] = [
    (u, v) => at(Math.floor(u * X), Math.floor((1 - v) * Y), c[2]) , // axial: i across, j up
    (u, v) => at(Math.floor(u * X), c[1], Math.floor((1 - v) * Z)), // coronal: i across, k up
    (u, v) => at(c[0], Math.floor(u * Y), Math.floor((1 - v) * Z)), // sagittal: j across, k up
  ];
  for (let p = 0; p < 3; p++)
    for (let r = 0; r < n; r++)
      for (let q = 0; q < n; q++) grey[r * 3 * n + p * n + q] = panels[p]((q + 0.5) / n, (r + 0.5) / n);
  return { width: 3 * n, height: n, grey, centroid: c, voxels: cnt };
}

export interface PlanDeps {
  alive: () => boolean;
  writable: boolean;
  showError: (e: unknown) => void;
  onLeave: (f: () => void) => void;
  /** Hear every notify_job; returns the unsubscribe. */
  onJob: (f: (j: PlanJob) => void) => () => void;
}

export function planScreen(caseId: number, body: HTMLElement, deps: PlanDeps): void {
  const vols = h("p", { class: "muted", "data-testid": "plan-volumes" }, "Loading…");
  const start = h("button", { class: "btn primary big", "data-testid": "plan-start", "data-write": "" }, "Start planning");
  const cancel = h("button", { class: "btn danger", "data-testid": "plan-cancel", "data-write": "", hidden: true }, "Cancel planning");
  const bar = h("div", { class: "bar", style: "width:0%" });
  const progress = h("div", { class: "progress", "data-testid": "plan-progress" }, bar);
  const stage = h("p", { class: "muted", "data-testid": "plan-stage" }, "");
  const canvas = h("canvas", { class: "plan-check", "data-testid": "plan-check", hidden: true });
  const checkText = h("p", { class: "muted", "data-testid": "plan-check-text" }, "");
  body.replaceChildren(h("div", { class: "case-layout" },
    h("section", { class: "panel" }, h("h2", {}, "Quick check: brain mask and surface (axial, coronal, sagittal)"), canvas, checkText),
    h("aside", { class: "controls" }, h("h2", {}, "Preoperative data"), vols, ...(deps.writable ? [start] : []), progress, stage, cancel)));
  let job: PlanJob | null = null;
  let shownMask = -1;
  const showJob = () => {
    if (!job) { stage.textContent = "No planning run yet."; cancel.hidden = true; return; }
    const running = job.state === "queued" || job.state === "running";
    bar.style.width = `${Math.round((job.state === "succeeded" ? 1 : job.fraction) * 100)}%`;
    progress.dataset.state = job.state;
    stage.textContent = `Plan job ${job.id}: ${job.state}${running && job.stage ? `, ${job.stage}` : ""} (${Math.round((job.state === "succeeded" ? 1 : job.fraction) * 100)} %)${job.error ? `: ${job.error}` : ""}`;
    cancel.hidden = !deps.writable || !running;
    start.disabled = running;
  };
  const loadCase = async () => {
    const c = await apiJson<CaseLite>("GET", `/api/cases/${caseId}`);
    if (!deps.alive()) return;
    const v = c.volumes ?? [];
    vols.textContent = v.length ? v.map((x) => `${x.modality}: ${x.original_name}`).join("; ") : "No volumes yet: upload a T1 in Contents.";
    start.disabled = !v.some((x) => x.modality === "T1") || (!!job && (job.state === "queued" || job.state === "running"));
    const newest = (kind: string) => (c.results ?? []).filter((r) => r.kind === kind).sort((a, b) => b.id - a.id)[0];
    const mask = newest("plan_brain_mask"), surf = newest("plan_brain_surface");
    if (!mask) { checkText.textContent = "No plan yet: Start planning makes the brain mask and surface."; return; }
    if (mask.id === shownMask) return;
    shownMask = mask.id;
    const vol = parseNifti(await gunzipIfNeeded(await (await apiBlob(`/api/cases/${caseId}/results/${mask.id}`)).arrayBuffer()), mask.name);
    const q = maskQuickCheck(vol);
    if (!deps.alive()) return;
    if (!q) { checkText.textContent = "The plan's brain mask is empty: check the T1."; return; }
    canvas.width = q.width;
    canvas.height = q.height;
    const ctx = canvas.getContext("2d");
    if (ctx) {
      const img = ctx.createImageData(q.width, q.height);
      for (let i = 0; i < q.grey.length; i++) { img.data[4 * i] = q.grey[i] ? 255 : 20; img.data[4 * i + 1] = q.grey[i] ? 190 : 24; img.data[4 * i + 2] = q.grey[i] ? 150 : 30; img.data[4 * i + 3] = 255; }
      ctx.putImageData(img, 0, 0);
    }
    canvas.hidden = false;
    canvas.dataset.voxels = String(q.voxels);
    const ml = (q.voxels * vol.spacing[0] * vol.spacing[1] * vol.spacing[2]) / 1000;
    const maskLine = `Brain mask ${vol.dims.join("x")} voxels, ${ml.toFixed(0)} ml; slices through its centroid (voxel ${q.centroid.join(", ")}).`;
    checkText.textContent = maskLine + (surf ? " Loading the brain surface…" : " No brain surface in this plan.");
    if (!surf || !ctx) return;
    // The surface (src/surface_outline.ts): cut by the same three slices, drawn over the mask.
    try {
      const mesh = parsePly(await (await apiBlob(`/api/cases/${caseId}/results/${surf.id}`)).arrayBuffer(), surf.name);
      if (!deps.alive()) return;
      const o = surfaceOutline(mesh, vol, q.centroid);
      const n = q.height;
      ctx.strokeStyle = "#39c6ff";
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      o.panels.forEach((segs, p) => { for (const [u1, v1, u2, v2] of segs) { ctx.moveTo(p * n + u1 * n, v1 * n); ctx.lineTo(p * n + u2 * n, v2 * n); } });
      ctx.stroke();
      const segments = o.panels.reduce((t, x) => t + x.length, 0);
      canvas.dataset.surfaceSegments = String(segments);
      canvas.dataset.surfaceInMask = o.inMask.toFixed(3);
      checkText.textContent = `${maskLine} Brain surface ${surf.name} (${(mesh.faces.length / 3).toLocaleString("en")} triangles) cut by the same slices, in blue: ` +
        `${(100 * o.inMask).toFixed(0)} % of its outline inside the mask (within 2 voxels)${o.inMask < 0.9 ? " — the surface leaves the brain mask: check the plan" : ""}.`;
    } catch (e) {
      checkText.textContent = `${maskLine} The brain surface ${surf.name} could not be drawn: ${e instanceof Error ? e.message : String(e)}`;
    }
  };
  const track = (j: PlanJob) => {
    if (j.kind !== "plan" || Number(j.params?.case_id) !== caseId || (job && j.id < job.id)) return;
    const was = job?.state;
    job = j;
    showJob();
    if (j.state === "succeeded" && was !== "succeeded") loadCase().catch(deps.showError);
  };
  deps.onLeave(deps.onJob(track));
  // Fallback: push messages can be dropped under load (docs/api/push.md).
  const timer = setInterval(() => {
    if (job && (job.state === "queued" || job.state === "running"))
      apiJson<PlanJob>("GET", `/api/jobs/${job.id}`).then((j) => { if (deps.alive()) track(j); }, () => undefined);
  }, 2000);
  deps.onLeave(() => clearInterval(timer));
  start.addEventListener("click", async () => {
    start.disabled = true;
    try { track(await apiJson<PlanJob>("POST", "/api/jobs", { kind: "plan", params: { case_id: caseId } })); } catch (e) { deps.showError(e); start.disabled = false; }
  });
  cancel.addEventListener("click", async () => {
    if (!job) return;
    try { await apiJson("POST", `/api/jobs/${job.id}/cancel`); } catch (e) { deps.showError(e); }
  });
  apiJson<{ jobs: PlanJob[] }>("GET", "/api/jobs").then((r) => { job = planJobOf(r.jobs, caseId); showJob(); }, deps.showError);
  loadCase().catch(deps.showError);
}
