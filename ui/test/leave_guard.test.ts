import { describe, expect, it } from "vitest";
import { LeaveGuard, unsavedMarksText } from "../src/leave_guard";

describe("LeaveGuard (7.47: unsaved marks are not dropped without a word)", () => {
  it("goes when nothing is unsaved", () => {
    const g = new LeaveGuard();
    g.arrived("#/case/1/photo");
    expect(g.decide("#/case/1/contents")).toEqual({ kind: "go" });
    g.set(() => null);
    expect(g.decide("#/case/1/contents")).toEqual({ kind: "go" });
  });
  it("asks, with the screen's words, and puts the hash back", () => {
    const g = new LeaveGuard();
    g.arrived("#/case/1/photo");
    let dirty = true;
    g.set(() => unsavedMarksText(false, dirty));
    const d = g.decide("#/case/1/contents");
    expect(d.kind).toBe("ask");
    if (d.kind !== "ask") return;
    expect(d.back).toBe("#/case/1/photo");
    expect(d.to).toBe("#/case/1/contents");
    expect(d.reason).toBe("Unsaved ROI on Photo & marks: stay and tap Save, or leave without saving (the changes are dropped).");
    expect(g.decide("#/case/1/photo")).toEqual({ kind: "go" }); // the hash put back: no question
    dirty = false; // saved
    expect(g.decide("#/case/1/contents")).toEqual({ kind: "go" });
  });
  it("leave without saving: that one change goes; the next screen starts without the check", () => {
    const g = new LeaveGuard();
    g.arrived("#/case/1/photo");
    g.set(() => unsavedMarksText(true, true));
    expect(g.decide("#/jobs").kind).toBe("ask");
    g.allowOnce("#/jobs");
    expect(g.decide("#/cases").kind).toBe("ask"); // only the chosen destination
    expect(g.decide("#/jobs")).toEqual({ kind: "go" });
    g.arrived("#/jobs");
    expect(g.decide("#/cases")).toEqual({ kind: "go" });
  });
  it("names what is unsaved", () => {
    expect(unsavedMarksText(false, false)).toBeNull();
    expect(unsavedMarksText(true, false)).toContain("Unsaved landmarks on");
    expect(unsavedMarksText(true, true)).toContain("landmarks and ROI");
  });
});
