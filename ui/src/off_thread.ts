// Heavy reading of volumes and meshes in a Web Worker (volume_worker.ts), so that the page keeps
// answering touches while it runs (issue 7, 7.34). Vite bundles the worker as its own file next
// to the page's (served by the daemon like the rest: offline). Without Worker (vitest's node)
// the task runs here.
import type { Volume } from "./nifti";
import type { PlanCheck } from "./plan_check";
import { runVolumeTask, type VolumeTask } from "./volume_tasks";

function run<T>(task: VolumeTask, transfer: Transferable[]): Promise<T> {
  if (typeof Worker === "undefined") return runVolumeTask(task) as Promise<T>;
  return new Promise<T>((resolve, reject) => {
    const w = new Worker(new URL("./volume_worker.ts", import.meta.url), { type: "module" });
    w.onmessage = (e: MessageEvent<{ ok?: T; error?: string }>) => {
      w.terminate();
      if (e.data.error !== undefined) reject(new Error(e.data.error)); else resolve(e.data.ok as T);
    };
    w.onerror = (e) => { w.terminate(); reject(new Error(`the page's volume reader (a Web Worker) failed: ${e.message || "it did not load"}`)); };
    w.postMessage(task, transfer);
  });
}

/** A NIfTI file's bytes (gzipped or not) read into a volume, off the main thread. */
export function parseNiftiOffThread(bytes: ArrayBuffer, name: string): Promise<Volume> {
  return run<Volume>({ kind: "nifti", bytes, name }, [bytes]);
}

/** The Preoperative quick check (plan_check.ts) off the main thread. */
export function planCheckOffThread(mask: ArrayBuffer, maskName: string, ply: ArrayBuffer | null, plyName: string): Promise<PlanCheck> {
  return run<PlanCheck>({ kind: "plan-check", mask, maskName, ply, plyName }, ply ? [mask, ply] : [mask]);
}
