// Unsaved landmark and ROI edits of Photo & marks (issue 7, 7.47 "nothing entered is lost"),
// kept in two places:
// - per case in the tab's sessionStorage (MarksDrafts): written on every edit, read back when the
//   screen is drawn again after a reload of the page or after the login screen replaced it (an
//   expired or revoked session, then logging in again);
// - by the daemon, per case and per owner (the kiosk, or the logged-in user), through
//   GET/PUT/DELETE /api/cases/N/drafts/marks (DaemonDraftSync, 500 ms after the last edit): the
//   tab's storage dies with chromium (the kiosk unit starts it with a fresh profile), the
//   daemon's copy does not.
// On open the newer of the two is restored (pickDraft), with a line saying so; both are dropped
// part by part once saved, and all at once on "Leave without saving" (docs/ui.md).
import type { FetchLike } from "./api";
import type { KeyValueStore } from "./session";

export type Px = [number, number];
export interface DraftLandmark { name: string; world_mm: number[]; pixel: Px }

export interface MarksDraft {
  caseId: number;
  photoId: number;        // the photo the pixels are on
  user: string;           // who edited ("" for the kiosk): another user is not given them
  savedUtc: string;       // when the last edit was kept
  landmarks?: DraftLandmark[];
  landmarksRevision?: number | null; // the stored revision the edit started from (null: none)
  roi?: Px[];
  roiRevision?: number | null;
}

const PREFIX = "cortexfuse.marks.";
const isPx = (p: unknown): p is Px => Array.isArray(p) && p.length === 2 && p.every((v) => typeof v === "number" && Number.isFinite(v));

/** The draft read back as stored, or null when it is missing or not one (a damaged entry is
 *  removed: it could not be restored anyway). */
function parse(raw: string | null, caseId: number): MarksDraft | null {
  if (raw === null) return null;
  try {
    const d = JSON.parse(raw) as MarksDraft;
    if (valid(d, caseId)) return d;
  } catch { /* not JSON */ }
  return null;
}

/** Whether `d` is a whole draft of case `caseId` (its parts the right shapes, at least one). */
function valid(d: MarksDraft, caseId: number): boolean {
  if (!d || typeof d !== "object") return false;
  const lmOk = d.landmarks === undefined || (Array.isArray(d.landmarks) && d.landmarks.every((l) =>
    l && typeof l.name === "string" && Array.isArray(l.world_mm) && l.world_mm.length === 3 && l.world_mm.every(Number.isFinite) && isPx(l.pixel)));
  const roiOk = d.roi === undefined || (Array.isArray(d.roi) && d.roi.every(isPx));
  return d.caseId === caseId && Number.isInteger(d.photoId) && typeof d.user === "string" && typeof d.savedUtc === "string" &&
    lmOk && roiOk && !!(d.landmarks || d.roi);
}

/** The parts of a draft without its time: two drafts with the same content compare equal. */
const content = (d: MarksDraft | null): string =>
  d ? JSON.stringify([d.photoId, d.user, d.landmarks ?? null, d.landmarksRevision ?? null, d.roi ?? null, d.roiRevision ?? null]) : "";

export class MarksDrafts {
  constructor(private readonly store: KeyValueStore, private readonly nowUtc: () => string = () => new Date().toISOString()) {}

  private key(caseId: number): string { return `${PREFIX}${caseId}`; }

  /** The case's unsaved edits for this photo and user, or null. */
  load(caseId: number, photoId: number, user: string): MarksDraft | null {
    const raw = this.store.getItem(this.key(caseId));
    const d = parse(raw, caseId);
    if (!d && raw !== null) this.store.removeItem(this.key(caseId));
    return d && d.photoId === photoId && d.user === user ? d : null;
  }

  /** Keeps the parts that are unsaved (null: that part is saved); nothing unsaved removes the entry.
   *  The time is that of the last change: the same content again keeps the time it had. Returns
   *  the draft as kept (null: nothing unsaved), also when the storage refused it. */
  keep(caseId: number, photoId: number, user: string,
       landmarks: { points: DraftLandmark[]; fromRevision: number | null } | null,
       roi: { points: Px[]; fromRevision: number | null } | null): MarksDraft | null {
    if (!landmarks && !roi) { this.store.removeItem(this.key(caseId)); return null; }
    const d: MarksDraft = { caseId, photoId, user, savedUtc: "" };
    if (landmarks) {
      d.landmarks = landmarks.points.map((l) => ({ name: l.name, world_mm: [...l.world_mm], pixel: [l.pixel[0], l.pixel[1]] }));
      d.landmarksRevision = landmarks.fromRevision;
    }
    if (roi) { d.roi = roi.points.map((p) => [p[0], p[1]] as Px); d.roiRevision = roi.fromRevision; }
    let before: MarksDraft | null = null;
    try { before = parse(this.store.getItem(this.key(caseId)), caseId); } catch { /* storage off */ }
    d.savedUtc = before && content(before) === content(d) ? before.savedUtc : this.nowUtc();
    try {
      this.store.setItem(this.key(caseId), JSON.stringify(d));
    } catch { /* storage full or off: the on-screen edits stay; the leave guard still asks */ }
    return d;
  }

  /** Everything of the case dropped (Leave without saving). */
  drop(caseId: number): void { this.store.removeItem(this.key(caseId)); }
}

/** The line shown when edits were restored: what, since when, that they are not saved, and what
 *  changed in the store meanwhile. `stored`: the case's revisions now (null: none stored). */
export function restoredText(d: MarksDraft, stored: { landmarks: number | null; roi: number | null }, source: DraftSource = "tab"): string {
  const parts: string[] = [];
  if (d.landmarks) parts.push(`landmarks (${d.landmarks.length} pair${d.landmarks.length === 1 ? "" : "s"})`);
  if (d.roi) parts.push(`ROI (${d.roi.length} point${d.roi.length === 1 ? "" : "s"})`);
  const at = d.savedUtc.replace("T", " ").replace(/\.\d+Z$|Z$/, "");
  const saves = [d.landmarks ? "Save landmarks" : "", d.roi ? "Save ROI" : ""].filter(Boolean).join(" and ");
  const where = source === "daemon" ? ", kept by the cart's daemon" : "";
  let text = `Restored your unsaved ${parts.join(" and ")} from ${at} UTC${where}: they are not saved yet. Tap ${saves} to store them.`;
  const newer: string[] = [];
  if (d.landmarks && (d.landmarksRevision ?? null) !== stored.landmarks) newer.push(`landmarks (now revision ${stored.landmarks ?? "none"})`);
  if (d.roi && (d.roiRevision ?? null) !== stored.roi) newer.push(`ROI (now revision ${stored.roi ?? "none"})`);
  if (newer.length) text += ` Meanwhile someone saved the ${newer.join(" and ")}: saving replaces that.`;
  return text;
}

/** The words for a Save of marks that failed. An unreachable daemon gets its own line: the edits
 *  stay (on the screen and kept for the tab) and the next step is to tap Save again once the
 *  link is back; any other refusal is the daemon's own words. */
export function saveFailedText(what: "landmarks" | "ROI", e: unknown, plain: (e: unknown) => string): string {
  const status = (e as { status?: unknown } | null)?.status;
  if (status === 0)
    return `The ${what} were not saved: the daemon cannot be reached. Your changes stay on this screen and in this browser tab; ` +
      `tap Save ${what === "ROI" ? "ROI" : "landmarks"} again when the status bar says Live.`;
  return plain(e);
}

// ---- the daemon's copy (GET/PUT/DELETE /api/cases/N/drafts/marks, docs/api/case-data.md) ------

/** Where a restored draft came from: this tab's storage or the daemon. */
export type DraftSource = "tab" | "daemon";

/** A draft as the daemon keeps it (PUT body; GET answers it with owner and updated_utc too). */
export interface DaemonDraftBody {
  photo_id: number;
  saved_utc: string;
  landmarks?: { from_revision: number | null; points: { label: string; world_mm: number[]; pixel: Px }[] };
  roi?: { from_revision: number | null; points: Px[] };
}

export function toDaemonBody(d: MarksDraft): DaemonDraftBody {
  const b: DaemonDraftBody = { photo_id: d.photoId, saved_utc: d.savedUtc };
  if (d.landmarks) b.landmarks = { from_revision: d.landmarksRevision ?? null, points: d.landmarks.map((l) => ({ label: l.name, world_mm: [...l.world_mm], pixel: [l.pixel[0], l.pixel[1]] })) };
  if (d.roi) b.roi = { from_revision: d.roiRevision ?? null, points: d.roi.map((p) => [p[0], p[1]] as Px) };
  return b;
}

/** The daemon's draft as one of the tab's, or null when there is none, it is not whole, or its
 *  pixels are on another photo than `photoId` (a newer photo was taken since). */
export function fromDaemon(j: unknown, caseId: number, photoId: number, user: string): MarksDraft | null {
  const b = j as DaemonDraftBody | null;
  if (!b || typeof b !== "object" || b.photo_id !== photoId) return null;
  const d: MarksDraft = { caseId, photoId, user, savedUtc: b.saved_utc };
  try {
    if (b.landmarks) {
      d.landmarks = b.landmarks.points.map((l) => ({ name: l.label, world_mm: [...l.world_mm], pixel: [l.pixel[0], l.pixel[1]] as Px }));
      d.landmarksRevision = b.landmarks.from_revision ?? null;
    }
    if (b.roi) { d.roi = b.roi.points.map((p) => [p[0], p[1]] as Px); d.roiRevision = b.roi.from_revision ?? null; }
  } catch { return null; }
  return valid(d, caseId) ? d : null;
}

/** The draft to restore: the newer of the tab's and the daemon's (by the time of the last edit;
 *  the tab's on a tie), or null when neither. */
export function pickDraft(tab: MarksDraft | null, daemon: MarksDraft | null): { draft: MarksDraft; source: DraftSource } | null {
  if (tab && daemon) return Date.parse(daemon.savedUtc) > Date.parse(tab.savedUtc) ? { draft: daemon, source: "daemon" } : { draft: tab, source: "tab" };
  if (tab) return { draft: tab, source: "tab" };
  if (daemon) return { draft: daemon, source: "daemon" };
  return null;
}

/** `d` without the parts that equal what is stored now (a Save went through but dropping the
 *  draft did not: nothing to restore there); null when nothing is left. */
export function withoutSavedParts(d: MarksDraft, stored: { landmarks: DraftLandmark[] | null; roi: Px[] | null }): MarksDraft | null {
  const same = (a: unknown, b: unknown) => JSON.stringify(a) === JSON.stringify(b);
  const out: MarksDraft = { ...d };
  if (d.landmarks && stored.landmarks && same(d.landmarks.map((l) => [l.name, l.world_mm, l.pixel]), stored.landmarks.map((l) => [l.name, l.world_mm, l.pixel]))) {
    delete out.landmarks; delete out.landmarksRevision;
  }
  if (d.roi && stored.roi && same(d.roi, stored.roi)) { delete out.roi; delete out.roiRevision; }
  return out.landmarks || out.roi ? out : null;
}

/** A refusal or failure of a draft request: `status` 0 when the daemon was not reached. */
export class DraftError extends Error {
  constructor(readonly status: number, message: string) { super(message); this.name = "DraftError"; }
}

/** The daemon's draft requests with the session's token. Not through api.ts's apiJson: a draft
 *  written in the background must not bring up the login screen by itself (the person's next
 *  Save does, with its own words). */
export function draftRequester(tokenOf: () => string | null, fetchImpl: FetchLike = (i, o) => fetch(i, o)) {
  return async (method: "GET" | "PUT" | "DELETE", path: string, body?: unknown): Promise<unknown> => {
    const headers: Record<string, string> = {};
    const token = tokenOf();
    if (token) headers.Authorization = `Bearer ${token}`;
    if (body !== undefined) headers["Content-Type"] = "application/json";
    let res: Response;
    try {
      res = await fetchImpl(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
    } catch {
      throw new DraftError(0, `${method} ${path}: the daemon cannot be reached`);
    }
    const text = await res.text().catch(() => "");
    if (!res.ok) throw new DraftError(res.status, `${method} ${path}: HTTP ${res.status} ${text.slice(0, 200)}`);
    try { return JSON.parse(text); } catch { return null; }
  };
}
export type DraftRequest = ReturnType<typeof draftRequester>;

const draftPath = (caseId: number) => `/api/cases/${caseId}/drafts/marks`;

/** The daemon's draft of this case for this photo and user, `null` when it has none, or
 *  `undefined` when it could not be asked (then nothing may be dropped there on its behalf). */
export async function loadDaemonDraft(request: DraftRequest, caseId: number, photoId: number, user: string):
    Promise<{ draft: MarksDraft | null; body: DaemonDraftBody | null } | undefined> {
  try {
    const j = (await request("GET", draftPath(caseId))) as { draft?: DaemonDraftBody | null } | null;
    const body = j?.draft ?? null;
    return { draft: fromDaemon(body, caseId, photoId, user), body };
  } catch { return undefined; }
}

const bodyKey = (b: DaemonDraftBody | null): string => {
  if (!b) return "none";
  const { saved_utc: _t, ...rest } = b;
  void _t;
  return JSON.stringify(rest);
};

/** Keeps the daemon's copy of the screen's draft in step with the screen: `schedule` the draft
 *  after each change (null: nothing unsaved any more, i.e. saved), sent `delayMs` after the last
 *  one, one request at a time, the same content not sent twice; a failure that may pass (the
 *  daemon unreachable, a session to renew, 5xx) is tried again every `retryMs`. */
export class DaemonDraftSync {
  private pending: { body: DaemonDraftBody | null } | null = null;
  private sentKey: string | undefined;   // what the daemon holds as far as we know (undefined: unknown)
  private timer: ReturnType<typeof setTimeout> | null = null;
  private busy = false;
  private inflight: Promise<void> | null = null;
  private disposed = false;
  private retriesLeft = Infinity;
  /** The last failure, "" after a success (for tests and the console). */
  lastError = "";
  sent = 0;

  constructor(private readonly caseId: number, private readonly request: DraftRequest,
              private readonly delayMs = 500, private readonly retryMs = 5000) {}

  /** What the daemon holds now (from loadDaemonDraft): the same content is then not sent again.
   *  Without it (the GET failed) nothing is dropped there until a draft has been sent. */
  assume(body: DaemonDraftBody | null | undefined): void { this.sentKey = body === undefined ? undefined : bodyKey(body); }

  schedule(body: DaemonDraftBody | null): void {
    if (this.disposed) return;
    const key = bodyKey(body);
    if (!this.pending && !this.busy && (key === this.sentKey || (body === null && this.sentKey === undefined))) return;
    this.pending = { body };
    this.arm(this.delayMs);
  }

  /** Sends what is pending now (after a Save: the draft goes at once). */
  flush(): Promise<void> { this.clear(); return this.pump(); }

  /** Leave without saving: the daemon's draft dropped now, anything pending forgotten. */
  async discard(): Promise<void> {
    this.clear();
    this.pending = null;
    this.disposed = true;
    await this.inflight; // a keep still under way must not land after the drop
    try {
      await this.request("DELETE", `${draftPath(this.caseId)}?reason=discarded`);
      this.sentKey = "none";
    } catch (e) { this.lastError = String((e as Error)?.message ?? e); }
  }

  /** The screen is left: what is pending goes now, with a few more tries if it fails. */
  dispose(): void {
    if (this.disposed) return;
    this.disposed = true;
    this.retriesLeft = 6;
    this.clear();
    void this.pump();
  }

  private clear(): void { if (this.timer !== null) { clearTimeout(this.timer); this.timer = null; } }
  private arm(ms: number): void { this.clear(); this.timer = setTimeout(() => { this.timer = null; void this.pump(); }, ms); }

  private pump(): Promise<void> {
    if (this.busy || !this.pending) return this.inflight ?? Promise.resolve();
    const p: Promise<void> = this.send().finally(() => { if (this.inflight === p) this.inflight = null; });
    this.inflight = p;
    return p;
  }

  private async send(): Promise<void> {
    if (!this.pending) return;
    const { body } = this.pending;
    const key = bodyKey(body);
    if (key === this.sentKey || (body === null && this.sentKey === undefined)) { this.pending = null; return; }
    this.busy = true;
    this.pending = null;
    try {
      if (body) await this.request("PUT", draftPath(this.caseId), body);
      else await this.request("DELETE", `${draftPath(this.caseId)}?reason=saved`);
      this.sentKey = key;
      this.sent++;
      this.lastError = "";
    } catch (e) {
      const status = (e as DraftError).status ?? 0;
      this.lastError = String((e as Error)?.message ?? e);
      // Worth another try later (unless something newer came meanwhile): unreachable, a session
      // to renew, the daemon failing; a refusal (400, 403, 404, 413) would be refused again.
      if (!this.pending && (status === 0 || status === 401 || status >= 500) && this.retriesLeft-- > 0) {
        this.pending = { body };
        this.busy = false;
        this.arm(this.retryMs);
        return;
      }
    }
    this.busy = false;
    if (this.pending) { if (this.disposed) queueMicrotask(() => void this.pump()); else this.arm(this.delayMs); }
  }
}
