import { describe, expect, it, vi } from "vitest";
import { DaemonDraftSync, DraftError, draftRequester, fromDaemon, loadDaemonDraft, MarksDrafts, pickDraft, restoredText, saveFailedText, toDaemonBody,
  withoutSavedParts, type DaemonDraftBody, type DraftLandmark, type DraftRequest, type MarksDraft, type Px } from "../src/marks_draft";
import { ApiError, auth, plainMessage } from "../src/api";
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

describe("the daemon's copy of unsaved marks (7.47: a restart of chromium itself)", () => {
  const body = (u: number): DaemonDraftBody => ({ photo_id: 3, saved_utc: `2026-11-27T15:42:1${u % 10}.000Z`,
    landmarks: { from_revision: 2, points: [{ label: "L1", world_mm: [1, 2, 3], pixel: [u, 40] }] } });

  it("keeps the time of the last change: the same content again keeps it", () => {
    let t = 0;
    const d = new MarksDrafts(new MemStore(), () => `2026-11-27T15:00:0${t++}.000Z`);
    expect(d.keep(7, 3, "", null, { points: roi, fromRevision: 1 })?.savedUtc).toBe("2026-11-27T15:00:00.000Z");
    expect(d.keep(7, 3, "", null, { points: roi, fromRevision: 1 })?.savedUtc).toBe("2026-11-27T15:00:00.000Z"); // a redraw
    expect(d.keep(7, 3, "", null, { points: roi.slice(1), fromRevision: 1 })?.savedUtc).toBe("2026-11-27T15:00:01.000Z");
    expect(d.keep(7, 3, "", null, null)).toBeNull();
  });

  it("goes to the daemon and back as the same draft; another photo or a damaged one is not taken", () => {
    const k = new MarksDrafts(new MemStore(), () => "2026-11-23T12:34:56.789Z");
    const d = k.keep(7, 3, "tina", { points: lms, fromRevision: null }, { points: roi, fromRevision: 4 })!;
    const b = toDaemonBody(d);
    expect(b).toEqual({ photo_id: 3, saved_utc: "2026-11-23T12:34:56.789Z",
      landmarks: { from_revision: null, points: lms.map((l) => ({ label: l.name, world_mm: l.world_mm, pixel: l.pixel })) },
      roi: { from_revision: 4, points: roi } });
    const back = JSON.parse(JSON.stringify({ ...b, owner: "user:3", updated_utc: "2026-11-23T12:34:57.000Z" }));
    expect(fromDaemon(back, 7, 3, "tina")).toEqual(d);
    expect(fromDaemon(back, 7, 4, "tina")).toBeNull(); // a newer photo since: its pixels are not on it
    expect(fromDaemon(null, 7, 3, "")).toBeNull();
    expect(fromDaemon({ ...back, roi: { points: [[1, "x"]] } }, 7, 3, "")).toBeNull();
    expect(fromDaemon({ photo_id: 3, saved_utc: "2026-11-23T12:34:56.789Z" }, 7, 3, "")).toBeNull(); // nothing in it
  });

  it("restores the newer of the tab's and the daemon's, says where it came from, and skips parts already saved", () => {
    const at = (t: string): MarksDraft => ({ caseId: 7, photoId: 3, user: "", savedUtc: t, roi: roi });
    const tab = at("2026-11-27T15:00:00.000Z"), daemon = at("2026-11-27T15:00:01.000Z");
    expect(pickDraft(tab, daemon)).toEqual({ draft: daemon, source: "daemon" });
    expect(pickDraft(daemon, tab)?.source).toBe("tab");
    expect(pickDraft(tab, at(tab.savedUtc))?.source).toBe("tab"); // a tie: this tab's
    expect(pickDraft(null, daemon)?.source).toBe("daemon");
    expect(pickDraft(null, null)).toBeNull();
    expect(restoredText({ ...daemon, roi: roi.slice(0, 1) }, { landmarks: null, roi: null }, "daemon")).toBe(
      "Restored your unsaved ROI (1 point) from 2026-11-27 15:00:01 UTC, kept by the cart's daemon: they are not saved yet. Tap Save ROI to store them.");
    expect(restoredText(tab, { landmarks: null, roi: null })).not.toContain("daemon");
    // A Save that went through before the browser died: that part is what is stored, not restored.
    const both: MarksDraft = { ...daemon, landmarks: lms, landmarksRevision: 1 };
    expect(withoutSavedParts(both, { landmarks: lms.map((l) => ({ ...l })), roi: null })).toEqual({ ...daemon });
    expect(withoutSavedParts(both, { landmarks: null, roi: [...roi] })).toEqual({ ...daemon, landmarks: lms, landmarksRevision: 1, roi: undefined, roiRevision: undefined });
    expect(withoutSavedParts(daemon, { landmarks: null, roi: roi.map((p) => [p[0], p[1]] as Px) })).toBeNull();
    expect(withoutSavedParts(daemon, { landmarks: null, roi: roi.slice(1) })).toEqual(daemon);
  });

  it("writes the daemon's copy 500 ms after the last change, one at a time, and drops it once saved", async () => {
    vi.useFakeTimers();
    try {
      const calls: string[] = [];
      const req: DraftRequest = async (method, path, b) => {
        calls.push(`${method} ${path}${b ? ` u=${(b as DaemonDraftBody).landmarks?.points[0].pixel[0]}` : ""}`);
        return { kept: true };
      };
      const s = new DaemonDraftSync(7, req);
      s.assume(null); // the daemon has none
      s.schedule(null); // nothing unsaved: nothing to send
      s.schedule(body(1)); s.schedule(body(2));
      await vi.advanceTimersByTimeAsync(400);
      s.schedule(body(3)); // a drag: only its end goes
      await vi.advanceTimersByTimeAsync(499);
      expect(calls).toEqual([]);
      await vi.advanceTimersByTimeAsync(1);
      expect(calls).toEqual(["PUT /api/cases/7/drafts/marks u=3"]);
      s.schedule({ ...body(3), saved_utc: "2026-11-27T16:00:00.000Z" }); // a redraw, same content
      await vi.advanceTimersByTimeAsync(1000);
      expect(calls.length).toBe(1);
      // Saved: the draft goes at once.
      s.schedule(null);
      await s.flush();
      expect(calls).toEqual(["PUT /api/cases/7/drafts/marks u=3", "DELETE /api/cases/7/drafts/marks?reason=saved"]);
      // The daemon unreachable: tried again every 5 s until it answers, then no more.
      let tries = 0;
      const unreachable = new DaemonDraftSync(7, async () => { if (++tries < 3) throw new DraftError(0, "down"); return {}; });
      unreachable.assume(null);
      unreachable.schedule(body(5));
      await vi.advanceTimersByTimeAsync(500);
      expect(tries).toBe(1);
      expect(unreachable.lastError).toContain("down");
      await vi.advanceTimersByTimeAsync(4999);
      expect(tries).toBe(1);
      await vi.advanceTimersByTimeAsync(1);
      expect(tries).toBe(2);
      await vi.advanceTimersByTimeAsync(5000);
      expect(tries).toBe(3);
      expect(unreachable.lastError).toBe("");
      await vi.advanceTimersByTimeAsync(20000);
      expect(tries).toBe(3);
      // A refusal (400, 403, 404, 413) would be refused again: not repeated.
      const refused = new DaemonDraftSync(7, async () => { calls.push("refused"); throw new DraftError(400, "bad"); });
      refused.assume(null);
      refused.schedule(body(6));
      await vi.advanceTimersByTimeAsync(30000);
      expect(calls.filter((c) => c === "refused").length).toBe(1);
    } finally { vi.useRealTimers(); }
  });

  it("drops nothing it could not read, flushes when the screen is left, and Leave without saving drops after a keep under way", async () => {
    vi.useFakeTimers();
    try {
      const calls: string[] = [];
      let hold: (() => void) | null = null;
      const req: DraftRequest = async (method, path) => {
        calls.push(`${method} ${path}`);
        if (method === "PUT" && hold === null) await new Promise<void>((r) => { hold = r; });
        return {};
      };
      const unknown = new DaemonDraftSync(7, req);
      unknown.assume(undefined); // the GET failed: its draft is not known
      unknown.schedule(null);
      await vi.advanceTimersByTimeAsync(1000);
      expect(calls).toEqual([]);
      const s = new DaemonDraftSync(8, req);
      s.assume(null);
      s.schedule(body(1));
      s.dispose(); // left at once: sent without waiting for the 500 ms
      await vi.advanceTimersByTimeAsync(0);
      expect(calls).toEqual(["PUT /api/cases/8/drafts/marks"]);
      const d = s.discard(); // Leave without saving while that PUT is under way
      await vi.advanceTimersByTimeAsync(10);
      expect(calls.length).toBe(1); // the drop waits for it
      hold!();
      await d;
      expect(calls).toEqual(["PUT /api/cases/8/drafts/marks", "DELETE /api/cases/8/drafts/marks?reason=discarded"]);
      s.schedule(body(2)); // nothing after leaving
      await vi.advanceTimersByTimeAsync(1000);
      expect(calls.length).toBe(2);
    } finally { vi.useRealTimers(); }
  });

  it("asks with the session's token and never brings up the login screen by itself", async () => {
    const seen: { path: string; init?: RequestInit }[] = [];
    let status = 200;
    const fetchLike = async (path: string, init?: RequestInit) => {
      seen.push({ path, init });
      return new Response(status === 200 ? JSON.stringify({ draft: null }) : JSON.stringify({ error: { message: "x" } }), { status });
    };
    let loginShown = 0;
    auth.onUnauthorized = () => { loginShown++; };
    try {
      const request = draftRequester(() => "tok123", fetchLike);
      expect(await loadDaemonDraft(request, 7, 3, "")).toEqual({ draft: null, body: null });
      expect((seen[0].init?.headers as Record<string, string>).Authorization).toBe("Bearer tok123");
      status = 401;
      await expect(request("PUT", "/api/cases/7/drafts/marks", body(1))).rejects.toMatchObject({ status: 401 });
      await expect(loadDaemonDraft(request, 7, 3, "")).resolves.toBeUndefined();
      expect(loginShown).toBe(0);
      const down = draftRequester(() => null, async () => { throw new TypeError("Failed to fetch"); });
      await expect(down("GET", "/api/cases/7/drafts/marks")).rejects.toMatchObject({ status: 0 });
    } finally { auth.onUnauthorized = null; }
  });
});
