// Unsaved landmark and ROI edits of Photo & marks, kept per case in the tab's sessionStorage
// (issue 7, 7.47 "nothing entered is lost"): written on every edit, read back when the screen is
// drawn again after a reload of the page or after the login screen replaced it (an expired or
// revoked session, then logging in again), dropped part by part once saved, and all at once on
// "Leave without saving". sessionStorage lives as long as the tab: the kiosk unit starts chromium
// with a fresh profile, so a restart of chromium itself loses them (docs/ui.md).
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
    const lmOk = d.landmarks === undefined || (Array.isArray(d.landmarks) && d.landmarks.every((l) =>
      l && typeof l.name === "string" && Array.isArray(l.world_mm) && l.world_mm.length === 3 && l.world_mm.every(Number.isFinite) && isPx(l.pixel)));
    const roiOk = d.roi === undefined || (Array.isArray(d.roi) && d.roi.every(isPx));
    if (d.caseId === caseId && Number.isInteger(d.photoId) && typeof d.user === "string" && lmOk && roiOk && (d.landmarks || d.roi)) return d;
  } catch { /* not JSON */ }
  return null;
}

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

  /** Keeps the parts that are unsaved (null: that part is saved); nothing unsaved removes the entry. */
  keep(caseId: number, photoId: number, user: string,
       landmarks: { points: DraftLandmark[]; fromRevision: number | null } | null,
       roi: { points: Px[]; fromRevision: number | null } | null): void {
    if (!landmarks && !roi) { this.store.removeItem(this.key(caseId)); return; }
    const d: MarksDraft = { caseId, photoId, user, savedUtc: this.nowUtc() };
    if (landmarks) {
      d.landmarks = landmarks.points.map((l) => ({ name: l.name, world_mm: [...l.world_mm], pixel: [l.pixel[0], l.pixel[1]] }));
      d.landmarksRevision = landmarks.fromRevision;
    }
    if (roi) { d.roi = roi.points.map((p) => [p[0], p[1]] as Px); d.roiRevision = roi.fromRevision; }
    try {
      this.store.setItem(this.key(caseId), JSON.stringify(d));
    } catch { /* storage full or off: the on-screen edits stay; the leave guard still asks */ }
  }

  /** Everything of the case dropped (Leave without saving). */
  drop(caseId: number): void { this.store.removeItem(this.key(caseId)); }
}

/** The line shown when edits were restored: what, since when, that they are not saved, and what
 *  changed in the store meanwhile. `stored`: the case's revisions now (null: none stored). */
export function restoredText(d: MarksDraft, stored: { landmarks: number | null; roi: number | null }): string {
  const parts: string[] = [];
  if (d.landmarks) parts.push(`landmarks (${d.landmarks.length} pair${d.landmarks.length === 1 ? "" : "s"})`);
  if (d.roi) parts.push(`ROI (${d.roi.length} point${d.roi.length === 1 ? "" : "s"})`);
  const at = d.savedUtc.replace("T", " ").replace(/\.\d+Z$|Z$/, "");
  const saves = [d.landmarks ? "Save landmarks" : "", d.roi ? "Save ROI" : ""].filter(Boolean).join(" and ");
  let text = `Restored your unsaved ${parts.join(" and ")} from ${at} UTC: they are not saved yet. Tap ${saves} to store them.`;
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
