// The Tracker screen's "Cortical landmarks" panel, its logic (no DOM): what the daemon's landmark
// and brain-shift endpoints answer (docs/api/navigation.md "Cortical landmarks"), the label to
// suggest next, which landmark is in which set, and the brain-shift table (the seed's Table 3.3)
// as cells.

import type { Vec3 } from "./tracker_model";

export interface Landmark {
  label: string;
  set: string;
  p_reference_mm: Vec3;
  p_image_mm: Vec3;
  spread_mm: number;
  frames: number;
  registration_revision: number;
  recorded_utc?: string;
}
/** GET /api/cases/{id}/navigation/landmarks */
export interface LandmarksAnswer {
  case_id: number;
  revision: number;
  registration_revision: number; // the accepted registration now; 0: none
  sets: { set: string; count: number }[];
  landmarks: Landmark[];
}
export interface ShiftRow { label: string; earlier_image_mm: Vec3; later_image_mm: Vec3; d_mm: Vec3; magnitude_mm: number }
/** POST /api/cases/{id}/navigation/brain-shift */
export interface BrainShift {
  earlier: string;
  later: string;
  n: number;
  rows: ShiftRow[];
  mean_d_mm: Vec3;
  sd_d_mm: Vec3;
  mean_abs_d_mm: Vec3;
  mean_magnitude_mm: number;
  sd_magnitude_mm: number;
  max_magnitude_mm: number;
  missing_later: string[];
  missing_earlier: string[];
  same_registration: boolean;
  table: string;
}

export const EARLIER = "initial";
export const LATER = "later";

/** A label the daemon accepts: 1..64 characters, no '/' or control characters. "" when fine,
 *  else why not. */
export function labelProblem(label: string): string {
  if (!label.trim()) return "Type a label for the landmark.";
  if (label.length > 64) return "A label has at most 64 characters.";
  // eslint-disable-next-line no-control-regex
  if (/[\u0000-\u001f/]/.test(label)) return "A label must not hold '/' or control characters.";
  return "";
}

export function labelsOf(lms: Landmark[], set: string): string[] {
  return lms.filter((l) => l.set === set).map((l) => l.label);
}

/** The label to suggest for the next recording in `set`: in the later set, the first landmark of
 *  the earlier set not yet re-digitised (the same label pairs them); otherwise L1, L2, ... not
 *  yet used in any set. */
export function suggestLabel(lms: Landmark[], set: string, earlier = EARLIER): string {
  const inSet = new Set(labelsOf(lms, set));
  if (set !== earlier) {
    const todo = labelsOf(lms, earlier).find((l) => !inSet.has(l));
    if (todo) return todo;
  }
  const used = new Set(lms.map((l) => l.label));
  for (let i = 1; ; i++) if (!used.has(`L${i}`)) return `L${i}`;
}

export interface LandmarkLine { label: string; earlier: Landmark | null; later: Landmark | null }
/** One line per label, in the order first recorded: where it is in each of the two sets. */
export function landmarkLines(lms: Landmark[], earlier = EARLIER, later = LATER): LandmarkLine[] {
  const order: string[] = [];
  for (const l of lms) if ((l.set === earlier || l.set === later) && !order.includes(l.label)) order.push(l.label);
  return order.map((label) => ({
    label,
    earlier: lms.find((l) => l.set === earlier && l.label === label) ?? null,
    later: lms.find((l) => l.set === later && l.label === label) ?? null,
  }));
}

/** The report can be asked for: both sets hold a landmark of the same label. */
export function canReport(lms: Landmark[], earlier = EARLIER, later = LATER): boolean {
  const e = new Set(labelsOf(lms, earlier));
  return labelsOf(lms, later).some((l) => e.has(l));
}

/** Signed to 0.01 mm with a true minus; a value that rounds to 0 is "+0.00" (never "−0.00"). */
const signed = (v: number) => {
  const r = Math.round(v * 100) / 100;
  return `${r >= 0 ? "+" : "−"}${Math.abs(r).toFixed(2)}`;
};

/** The brain-shift table as cells: a header, one row per landmark (dx, dy, dz signed, |d|, mm),
 *  then mean ± sd per axis and of |d|. */
export function shiftTable(r: BrainShift): { head: string[]; rows: string[][]; summary: string[] } {
  const head = ["Landmark", "dx (L) mm", "dy (P) mm", "dz (S) mm", "|d| mm"];
  const rows = r.rows.map((x) => [x.label, signed(x.d_mm[0]), signed(x.d_mm[1]), signed(x.d_mm[2]), x.magnitude_mm.toFixed(2)]);
  const ms = (m: number, s: number) => `${signed(m)} ± ${s.toFixed(2)}`;
  const summary = [`mean ± sd (n = ${r.n})`, ms(r.mean_d_mm[0], r.sd_d_mm[0]), ms(r.mean_d_mm[1], r.sd_d_mm[1]), ms(r.mean_d_mm[2], r.sd_d_mm[2]),
    `${r.mean_magnitude_mm.toFixed(2)} ± ${r.sd_magnitude_mm.toFixed(2)}`];
  return { head, rows, summary };
}

/** What the report leaves out or should be read with care, in words ("" when nothing). */
export function shiftNotes(r: BrainShift): string {
  const notes: string[] = [];
  if (r.missing_later.length) notes.push(`not re-digitised in “${r.later}”: ${r.missing_later.join(", ")}`);
  if (r.missing_earlier.length) notes.push(`only in “${r.later}”: ${r.missing_earlier.join(", ")}`);
  if (!r.same_registration) notes.push("the two sets went through different patient registrations: the shift includes their difference");
  return notes.join("; ");
}

/** The largest shift in words, for the line above the table. */
export function shiftHeadline(r: BrainShift): string {
  return `Brain shift “${r.earlier}” → “${r.later}” over ${r.n} landmark${r.n === 1 ? "" : "s"}: mean |d| ${r.mean_magnitude_mm.toFixed(2)} mm, largest ${r.max_magnitude_mm.toFixed(2)} mm`;
}
