// What volume_worker.ts does for the page (and what off_thread.ts does itself where there is no
// Worker, as under vitest): read a NIfTI volume, or the Preoperative quick check.
import { gunzipIfNeeded, parseNifti, type Volume } from "./nifti";
import { planCheck, type PlanCheck } from "./plan_check";

export type VolumeTask =
  | { kind: "nifti"; bytes: ArrayBuffer; name: string }
  | { kind: "plan-check"; mask: ArrayBuffer; maskName: string; ply: ArrayBuffer | null; plyName: string };

export async function runVolumeTask(t: VolumeTask): Promise<Volume | PlanCheck> {
  if (t.kind === "nifti") return parseNifti(await gunzipIfNeeded(t.bytes), t.name);
  return planCheck(t.mask, t.maskName, t.ply, t.plyName);
}

/** The large buffers of a result, handed over rather than copied. */
export function transferablesOf(r: Volume | PlanCheck): Transferable[] {
  if ("data" in r) return ArrayBuffer.isView(r.data) ? [r.data.buffer as ArrayBuffer] : [];
  return r.mask ? [r.mask.grey.buffer as ArrayBuffer] : [];
}
