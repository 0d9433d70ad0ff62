// The status bar's pill words (issue 7, 7.30): short enough that all six pills are whole at
// 1280x800 (the e2e checks scrollWidth <= clientWidth), with the rate and the renderer's state
// kept; no tooltip carries anything the pill does not say.

/** Tracker: the rate when streaming, else its state. */
export function trackerPill(state: string | undefined, hz: number | undefined): string {
  if (state === "streaming") return typeof hz === "number" ? `Tracker ${hz.toFixed(0)} Hz` : "Tracker streaming";
  return `Tracker ${state ?? "unknown"}`;
}

/** Tools: the missing ones by name (what the technician must act on), else how many are seen. */
export function toolsPill(seen: string[], missing: string[]): string {
  if (missing.length) return `Missing: ${missing.join(", ")}`;
  if (!seen.length) return "No tools seen";
  return seen.length <= 2 ? `Tools: ${seen.join(", ")}` : `Tools: ${seen.length} seen`;
}

/** Renderer: its backend and state; "failed" names the reason in the banner, not here. */
export function rendererPill(state: string | undefined, backend: string | undefined): string {
  if (state === "failed") return "Render failed";
  // Before the renderer names its backend (the MRI still loading) the pill said "Render ? ready".
  return `Render ${backend ? `${backend} ` : ""}${state ?? "unknown"}`;
}

/** Jobs: "idle" or the counts. */
export function jobsPill(running: number, queued: number): string {
  if (running === 0 && queued === 0) return "Jobs idle";
  return `Jobs ${running} run, ${queued} queued`;
}
