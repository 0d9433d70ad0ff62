// The Web Worker that reads volumes and meshes off the page's main thread (issue 7, 7.34: the
// UI never freezes): one task per worker, started by off_thread.ts. No DOM here.
import { runVolumeTask, transferablesOf, type VolumeTask } from "./volume_tasks";

self.onmessage = async (e: MessageEvent<VolumeTask>) => {
  try {
    const result = await runVolumeTask(e.data);
    (self as unknown as Worker).postMessage({ ok: result }, transferablesOf(result));
  } catch (err) {
    (self as unknown as Worker).postMessage({ error: err instanceof Error ? err.message : String(err) });
  }
};
