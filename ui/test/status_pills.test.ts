import { describe, expect, it } from "vitest";
import { jobsPill, rendererPill, toolsPill, trackerPill } from "../src/status_pills";

describe("status pills (7.30: whole at 1280x800)", () => {
  it("keeps the tracker's rate and state", () => {
    expect(trackerPill("streaming", 59.7)).toBe("Tracker 60 Hz");
    expect(trackerPill("stopped", 60)).toBe("Tracker stopped");
    expect(trackerPill(undefined, undefined)).toBe("Tracker unknown");
  });
  it("names missing tools first", () => {
    expect(toolsPill(["reference"], ["pointer"])).toBe("Missing: pointer");
    expect(toolsPill(["reference", "pointer"], [])).toBe("Tools: reference, pointer");
    expect(toolsPill(["a", "b", "c"], [])).toBe("Tools: 3 seen");
    expect(toolsPill([], [])).toBe("No tools seen");
  });
  it("keeps the renderer's backend and state, and the jobs' counts", () => {
    expect(rendererPill("ready", "gl")).toBe("Render gl ready");
    expect(rendererPill("failed", "gl")).toBe("Render failed");
    expect(rendererPill("ready", undefined)).toBe("Render ready");
    expect(rendererPill(undefined, undefined)).toBe("Render unknown");
    expect(jobsPill(0, 0)).toBe("Jobs idle");
    expect(jobsPill(1, 2)).toBe("Jobs 1 run, 2 queued");
  });
  it("all six pills together stay short (<= 110 characters at the longest usual state)", () => {
    const all = [trackerPill("streaming", 250), toolsPill(["reference", "pointer"], []), rendererPill("rendering", "gl"),
      jobsPill(2, 12), "Live", "Kiosk (full access)"].join("");
    expect(all.length).toBeLessThanOrEqual(110);
  });
});
