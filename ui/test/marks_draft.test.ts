import { describe, expect, it } from "vitest";
import { MarksDrafts, restoredText, saveFailedText, type DraftLandmark, type Px } from "../src/marks_draft";
import { ApiError, plainMessage } from "../src/api";
import { LeaveGuard, unsavedMarksText } from "../src/leave_guard";

class MemStore {
  m = new Map<string, string>();
  getItem(k: string) { return this.m.get(k) ?? null; }
  setItem(k: string, v: string) { this.m.set(k, v); }
  removeItem(k: string) { this.m.delete(k); }
}

const lms: DraftLandmark[] = [
  { name: "L1", world_mm: [10, -20, 30.5], pixel: [100.25, 200] },
  { name: "nasion", world_mm: [0, 80, 5], pixel: [320, 40.5] },
];
const roi: Px[] = [[10, 10], [200, 12], [190, 150]];

describe("MarksDrafts (7.47: unsaved marks survive a reload and a login screen)", () => {
  it("keeps the unsaved parts per case and gives them back for the same photo and user", () => {
    const s = new MemStore();
    const d = new MarksDrafts(s, () => "2026-11-23T12:34:56.789Z");
    d.keep(7, 3, "", { points: lms, fromRevision: 2 }, null);
    d.keep(8, 5, "", null, { points: roi, fromRevision: null });
    const a = d.load(7, 3, "");
    expect(a?.landmarks).toEqual(lms);
    expect(a?.roi).toBeUndefined();
    expect(a?.landmarksRevision).toBe(2);
    expect(d.load(8, 5, "")?.roi).toEqual(roi);
    // Edits after the keep do not reach the stored copy (it is a copy, not the live arrays).
    lms[0].pixel[0] = 999;
    expect(d.load(7, 3, "")?.landmarks?.[0].pixel[0]).toBe(100.25);
    lms[0].pixel[0] = 100.25;
    // Another photo (the pixels belong to the old one) or another user: not restored, still kept.
    expect(d.load(7, 4, "")).toBeNull();
    expect(d.load(7, 3, "sam")).toBeNull();
    expect(d.load(7, 3, "")).not.toBeNull();
  });

  it("drops a part once saved, the entry once nothing is unsaved, and all of it on Leave without saving", () => {
    const s = new MemStore();
    const d = new MarksDrafts(s);
    d.keep(7, 3, "", { points: lms, fromRevision: 1 }, { points: roi, fromRevision: 1 });
    d.keep(7, 3, "", null, { points: roi, fromRevision: 1 }); // landmarks saved
    expect(d.load(7, 3, "")?.landmarks).toBeUndefined();
    expect(d.load(7, 3, "")?.roi).toEqual(roi);
    d.keep(7, 3, "", null, null); // ROI saved too
    expect(s.m.size).toBe(0);
    // Leave without saving (the leave guard's discard) forgets the case's draft.
    d.keep(7, 3, "", null, { points: roi, fromRevision: 1 });
    const g = new LeaveGuard();
    g.arrived("#/case/7/photo");
    g.set(() => unsavedMarksText(false, true), () => d.drop(7));
    expect(g.decide("#/case/7/contents").kind).toBe("ask");
    expect(s.m.size).toBe(1); // asking drops nothing
    g.allowOnce("#/case/7/contents");
    expect(s.m.size).toBe(0);
  });

  it("ignores and removes a damaged entry; a full storage loses nothing on the screen", () => {
    const s = new MemStore();
    s.setItem("cortexfuse.marks.7", "{not json");
    const d = new MarksDrafts(s);
    expect(d.load(7, 3, "")).toBeNull();
    expect(s.m.size).toBe(0);
    s.setItem("cortexfuse.marks.7", JSON.stringify({ caseId: 7, photoId: 3, user: "", savedUtc: "x", roi: [[1, "a"]] }));
    expect(d.load(7, 3, "")).toBeNull();
    const full = { getItem: () => null, removeItem: () => {}, setItem: () => { throw new Error("QuotaExceededError"); } };
    expect(() => new MarksDrafts(full).keep(1, 1, "", null, { points: roi, fromRevision: null })).not.toThrow();
  });

  it("says what was restored, that it is not saved, and what was saved meanwhile", () => {
    const k = new MarksDrafts(new MemStore(), () => "2026-11-23T12:34:56.789Z");
    k.keep(7, 3, "", { points: lms, fromRevision: 2 }, { points: roi, fromRevision: 1 });
    const draft = k.load(7, 3, "")!;
    expect(restoredText(draft, { landmarks: 2, roi: 1 })).toBe(
      "Restored your unsaved landmarks (2 pairs) and ROI (3 points) from 2026-11-23 12:34:56 UTC: they are not saved yet. " +
      "Tap Save landmarks and Save ROI to store them.");
    expect(restoredText(draft, { landmarks: 3, roi: 1 })).toContain("Meanwhile someone saved the landmarks (now revision 3): saving replaces that.");
    k.keep(7, 3, "", null, { points: roi.slice(0, 1), fromRevision: null });
    expect(restoredText(k.load(7, 3, "")!, { landmarks: 2, roi: null })).toBe(
      "Restored your unsaved ROI (1 point) from 2026-11-23 12:34:56 UTC: they are not saved yet. Tap Save ROI to store them.");
  });

  it("a Save that cannot reach the daemon says the changes stay and to save again; a refusal is the daemon's words", () => {
    const down = new ApiError(0, "unreachable", "The daemon cannot be reached (POST /api/cases/7/landmarks). Check that cortexfused is running; the screen retries on its own.");
    expect(saveFailedText("landmarks", down, plainMessage)).toBe(
      "The landmarks were not saved: the daemon cannot be reached. Your changes stay on this screen and in this browser tab; " +
      "tap Save landmarks again when the status bar says Live.");
    expect(saveFailedText("ROI", down, plainMessage)).toContain("tap Save ROI again");
    const refused = new ApiError(400, "bad_request", "roi points: a closed spline needs at least 3 points");
    expect(saveFailedText("ROI", refused, plainMessage)).toBe("roi points: a closed spline needs at least 3 points");
  });
});
