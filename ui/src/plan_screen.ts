// The Preoperative step of a case (issue 7): the case's volumes, `Start planning` (the plan
// job: brain mask, surface, CT/fMRI on the T1) with its progress bar from the push channel's
// notify_job (and a 2 s poll in case one is dropped), Cancel, and when the plan is there a quick
// check picture of its brain mask: three orthogonal slices through the mask's centroid, drawn
// here from the stored plan_brain_mask (NIfTI), with the plan's surface cut by the same slices;
// read and computed in a Web Worker (plan_check.ts, off_thread.ts) so the screen never freezes.
import { apiBlob, apiJson, plainMessage } from "./api";
import { h } from "./dom";
import { planCheckOffThread } from "./off_thread";
import "./plan_screen.css";

export interface PlanJob { id: number; kind: string; state: string; stage: string; fraction: number; error?: string; params?: Record<string, unknown> }
interface CaseLite { volumes?: { id: number; modality: string; original_name: string }[]; results?: { id: number; kind: string; name: string }[] }

/** The newest plan job of the case (any state), or null. */
export function planJobOf(jobs: PlanJob[], caseId: number): PlanJob | null {
  let best: PlanJob | null = null;
  for (const j of jobs) if (j.kind === "plan" && Number(j.params?.case_id) === caseId && (!best || j.id > best.id)) best = j;
  return best;
}

// The mask picture's arithmetic lives in plan_check.ts (run in a Web Worker, off_thread.ts).
export { maskQuickCheck } from "./plan_check";

export interface PlanDeps {
  alive: () => boolean;
  writable: boolean;
  showError: (e: unknown) => void;
  onLeave: (f: () => void) => void;
  /** Hear every notify_job; returns the unsubscribe. */
  onJob: (f: (j: PlanJob) => void) => () => void;
}

export function planScreen(caseId: number, body: HTMLElement, deps: PlanDeps): void {
  const vols = h("p", { class: "muted plan-volumes", "data-testid": "plan-volumes" }, "Loading…");
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
    // Both files fetched here (async), read and cut in the worker: no long task on this page.
    const maskBytes = await (await apiBlob(`/api/cases/${caseId}/results/${mask.id}`)).arrayBuffer();
    let plyBytes: ArrayBuffer | null = null, plyFetchError = "";
    if (surf) {
      checkText.textContent = "Reading the brain mask and surface…";
      try { plyBytes = await (await apiBlob(`/api/cases/${caseId}/results/${surf.id}`)).arrayBuffer(); } catch (e) { plyFetchError = plainMessage(e); }
    }
    const chk = await planCheckOffThread(maskBytes, mask.name, plyBytes, surf?.name ?? "");
    const q = chk.mask;
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
    const ml = (q.voxels * chk.spacing[0] * chk.spacing[1] * chk.spacing[2]) / 1000;
    const maskLine = `Brain mask ${chk.dims.join("x")} voxels, ${ml.toFixed(0)} ml; slices through its centroid (voxel ${q.centroid.join(", ")}).`;
    if (!surf) { checkText.textContent = `${maskLine} No brain surface in this plan.`; return; }
    const why = plyFetchError || chk.surfaceError;
    if (!chk.surface || !ctx) { checkText.textContent = `${maskLine} The brain surface ${surf.name} could not be drawn: ${why ?? "no picture to draw on"}`; return; }
    // The surface (src/surface_outline.ts): cut by the same three slices, drawn over the mask.
    const o = chk.surface;
    const n = q.height;
    ctx.strokeStyle = "#39c6ff";
    ctx.lineWidth = 1.5;
    ctx.beginPath();
    o.panels.forEach((segs, p) => { for (const [u1, v1, u2, v2] of segs) { ctx.moveTo(p * n + u1 * n, v1 * n); ctx.lineTo(p * n + u2 * n, v2 * n); } });
    ctx.stroke();
    const segments = o.panels.reduce((t, x) => t + x.length, 0);
    canvas.dataset.surfaceSegments = String(segments);
    canvas.dataset.surfaceInMask = o.inMask.toFixed(3);
    checkText.textContent = `${maskLine} Brain surface ${surf.name} (${o.triangles.toLocaleString("en")} triangles) cut by the same slices, in blue: ` +
      `${(100 * o.inMask).toFixed(0)} % of its outline inside the mask (within 2 voxels)${o.inMask < 0.9 ? " — the surface leaves the brain mask: check the plan" : ""}.`;
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
