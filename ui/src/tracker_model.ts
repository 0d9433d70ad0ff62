// The Tracker screen's logic (no DOM): what the daemon's navigation endpoints answer
// (docs/api/navigation.md), how each tool is shown, which fiducial comes next, the pointer mapped
// into the image, and when the slices need a new picture.

export type Vec3 = [number, number, number];
export type Mat4 = number[][]; // 4x4 rows, last row 0 0 0 1

export interface ToolJson {
  name: string;
  status: string; // "ok", "missing", "disabled", "unoccupied"
  stale?: boolean;
  out_of_volume?: boolean;
  partially_out_of_volume?: boolean;
  rms_mm?: number;
}
/** GET /api/navigation/pointer */
export interface PointerAnswer {
  enabled: boolean;
  state: string; // the tracker session's state ("streaming", ...)
  frame_rate_hz: number;
  frame: { seq: number; frame: number; tools?: ToolJson[] } | null;
  age_ms?: number;
  p_reference_mm: Vec3 | null;
  p_tracker_mm: Vec3 | null;
  tip_pointer_mm: Vec3;
  tip_source?: string; // "default (the pointer tool's origin)" or "pivot calibration: rms ..."
}
export interface ImageFiducial { label: string; p_image_mm: Vec3 }
export interface PatientFiducial { label: string; p_reference_mm: Vec3; spread_mm: number; frames: number; recorded_utc?: string }
export interface FiducialRow { label: string; p_image_mm: Vec3; p_reference_mm: Vec3; residual_mm: number; used: boolean }
/** POST /api/cases/{id}/navigation/register (and the accepted one, with revision and accepted_utc) */
export interface Registration {
  T_image_from_reference: Mat4;
  fre_mm: number;
  fle_mm: number;
  n_used: number;
  fiducials: FiducialRow[];
  excluded: string[];
  missing: string[];
  predicted_tre_mm: number;
  target: string;
  image_fiducials_revision: number;
  patient_fiducials_revision: number;
  params: { outlier_mm: number; fle_mm: number };
  revision?: number;
  accepted_utc?: string;
}
/** GET /api/cases/{id}/navigation */
export interface NavState {
  case_id: number;
  state: string;
  image_fiducials: { revision: number; fiducials: ImageFiducial[] };
  patient_fiducials: { revision: number; fiducials: PatientFiducial[] };
  accepted: Registration | null;
  accepted_count: number;
}

export type Level = "ok" | "warn" | "bad";
export interface ToolView { name: string; text: string; level: Level; rms: string }

/** How one tool is shown: seen (green), partly out of volume (amber), missing / stale / out of
 *  volume (red), with the words saying which. A frame older than 0.5 s makes every tool stale. */
export function toolView(t: ToolJson, frameAgeMs = 0): ToolView {
  const rms = typeof t.rms_mm === "number" ? `${t.rms_mm.toFixed(2)} mm` : "—";
  if (frameAgeMs > 500) return { name: t.name, text: `stale (no frame for ${(frameAgeMs / 1000).toFixed(1)} s)`, level: "bad", rms: "—" };
  if (t.stale) return { name: t.name, text: "stale (not seen for 0.5 s)", level: "bad", rms: "—" };
  if (t.status !== "ok") return { name: t.name, text: t.out_of_volume ? "out of the tracking volume" : t.status === "missing" ? "missing (not seen)" : t.status, level: "bad", rms: "—" };
  if (t.out_of_volume) return { name: t.name, text: "seen, out of the tracking volume", level: "bad", rms };
  if (t.partially_out_of_volume) return { name: t.name, text: "seen, partly out of volume", level: "warn", rms };
  return { name: t.name, text: "seen", level: "ok", rms };
}

/** Every tool of the newest frame; one line when there is none. */
export function toolViews(a: PointerAnswer | null): ToolView[] {
  if (!a || !a.enabled) return [{ name: "tracker", text: "disabled", level: "bad", rms: "—" }];
  if (!a.frame) return [{ name: "tracker", text: `no frame yet (${a.state})`, level: "bad", rms: "—" }];
  return (a.frame.tools ?? []).map((t) => toolView(t, a.age_ms ?? 0));
}

/** The rate line: the measured rate, amber below 20 Hz, red at 0. */
export function rateView(a: PointerAnswer | null): { text: string; level: Level } {
  const hz = a?.frame_rate_hz ?? 0;
  return { text: `${hz.toFixed(0)} Hz (${a?.state ?? "unknown"})`, level: hz <= 0 ? "bad" : hz < 20 ? "warn" : "ok" };
}

/** T · p for a rigid 4x4. */
export function applyT(T: Mat4, p: Vec3): Vec3 {
  return [0, 1, 2].map((r) => T[r][0] * p[0] + T[r][1] * p[1] + T[r][2] * p[2] + T[r][3]) as Vec3;
}

/** The pointer tip in the image (LPS mm) through a registration, or null. */
export function pointerInImage(a: PointerAnswer | null, reg: Registration | null): Vec3 | null {
  if (!a?.p_reference_mm || !reg) return null;
  return applyT(reg.T_image_from_reference, a.p_reference_mm);
}

export interface FiducialLine { label: string; recorded: boolean; residual: string; note: string; level: Level | "none" }
/** The list of fiducials to touch, in the image list's order, with what the registration says
 *  about each (residual, excluded). */
export function fiducialLines(nav: NavState, reg: Registration | null): FiducialLine[] {
  const recorded = new Set(nav.patient_fiducials.fiducials.map((f) => f.label));
  return nav.image_fiducials.fiducials.map((f) => {
    const row = reg?.fiducials.find((r) => r.label === f.label);
    if (!recorded.has(f.label)) return { label: f.label, recorded: false, residual: "", note: "to touch", level: "none" };
    if (!row) return { label: f.label, recorded: true, residual: "", note: "recorded", level: "ok" };
    const res = `${row.residual_mm.toFixed(2)} mm`;
    if (!row.used) return { label: f.label, recorded: true, residual: res, note: "excluded (outlier): touch it again", level: "bad" };
    return { label: f.label, recorded: true, residual: res, note: "used", level: row.residual_mm > 2 ? "warn" : "ok" };
  });
}

/** The fiducial to touch next: the selected one when given, else the first not yet recorded. */
export function nextFiducial(nav: NavState, selected: string | null): string | null {
  const labels = nav.image_fiducials.fiducials.map((f) => f.label);
  if (selected && labels.includes(selected)) return selected;
  const recorded = new Set(nav.patient_fiducials.fiducials.map((f) => f.label));
  return labels.find((l) => !recorded.has(l)) ?? null;
}

/** Enough fiducials recorded (paired with the image's) to register: 3. */
export function canRegister(nav: NavState): boolean {
  const labels = new Set(nav.image_fiducials.fiducials.map((f) => f.label));
  return nav.patient_fiducials.fiducials.filter((f) => labels.has(f.label)).length >= 3;
}

/** FRE in words: below 1.5 mm good, below 3 mm acceptable with care, above: redo. */
export function freVerdict(fre: number): { text: string; level: Level } {
  if (fre < 1.5) return { text: `FRE ${fre.toFixed(2)} mm: good`, level: "ok" };
  if (fre < 3) return { text: `FRE ${fre.toFixed(2)} mm: acceptable, check the excluded and large residuals`, level: "warn" };
  return { text: `FRE ${fre.toFixed(2)} mm: too large, redo the fiducials`, level: "bad" };
}

/** The slices need a new picture when the point moved more than `minMoveMm` (0.5 mm by default). */
export function needsNewSlices(prev: Vec3 | null, p: Vec3 | null, minMoveMm = 0.5): boolean {
  if (!p) return false;
  if (!prev) return true;
  return Math.hypot(p[0] - prev[0], p[1] - prev[1], p[2] - prev[2]) > minMoveMm;
}

/** The caption under the slices, with the last failed slice request said (issue 7: a failed
 *  fetch is not swallowed: the picture would stay old or empty without a word). */
export function sliceCaptionText(caption: string, sliceError: string): string {
  if (!sliceError) return caption;
  return `${caption ? `${caption} ` : ""}The MRI slices could not be loaded (${sliceError.replace(/\.$/, "")}); trying again every second.`;
}

/** The volume the Tracker screen's slices are cut from: the open case's own T1 (its newest, the
 *  volume its image fiducials are placed on), or null for the daemon's bundled MRI (data.t1). */
export interface SliceVolume { caseId: number; volumeId: number }

/** The slice volume of a case record (GET /api/cases/{id}): its newest T1, else null (a case
 *  without a T1 of its own shows the bundled MRI). */
export function caseSliceVolume(c: { id: number; volumes?: { id: number; modality: string }[] } | null): SliceVolume | null {
  if (!c) return null;
  let best: number | null = null;
  for (const v of c.volumes ?? []) if (v.modality === "T1" && (best === null || v.id > best)) best = v.id;
  return best === null ? null : { caseId: c.id, volumeId: best };
}

const volumeQuery = (vol: SliceVolume | null) => (vol ? `case_id=${vol.caseId}&volume_id=${vol.volumeId}` : "");

/** GET /api/navigation/slices for a point: of the case's volume (`vol`), else of data.t1. */
export function slicesPath(p: Vec3, size: number, fovMm = 220, vol: SliceVolume | null = null): string {
  const q = volumeQuery(vol);
  return `/api/navigation/slices?x=${p[0].toFixed(2)}&y=${p[1].toFixed(2)}&z=${p[2].toFixed(2)}&size=${Math.round(size)}&fov_mm=${fovMm}&format=jpeg${q ? `&${q}` : ""}`;
}

/** GET /api/navigation/suggested-fiducials on the same volume as the slices. */
export function suggestedFiducialsPath(vol: SliceVolume | null): string {
  const q = volumeQuery(vol);
  return `/api/navigation/suggested-fiducials${q ? `?${q}` : ""}`;
}

/** The pointer tip in use, in words. */
export function tipLine(a: PointerAnswer | null): string {
  if (!a) return "Pointer tip: unknown (no answer from the daemon)";
  const t = a.tip_pointer_mm;
  return `Pointer tip (${t.map((v) => v.toFixed(2)).join(", ")}) mm in the pointer's frame: ${a.tip_source ?? "default"}`;
}

/** A pivot calibration's answer in words (POST /api/navigation/pivot). */
export interface PivotAnswer { tip_pointer_mm: Vec3; rms_mm: number; rotation_spread_deg: number; poses: number; warning: string; applied: boolean }
export function pivotLine(p: PivotAnswer): string {
  const tip = p.tip_pointer_mm.map((v) => v.toFixed(2)).join(", ");
  return `${p.applied ? "Tip calibrated" : "Tip measured (not applied)"}: (${tip}) mm, rms ${p.rms_mm.toFixed(2)} mm over ${p.poses} poses, swivelled ${p.rotation_spread_deg.toFixed(1)}°${p.warning ? `; ${p.warning}` : ""}`;
}

export function fmtPoint(p: Vec3 | null): string {
  return p ? `(${p.map((v) => v.toFixed(1)).join(", ")}) mm` : "—";
}

/** The LPS mm point under a tap on the tri-planar image of GET /api/navigation/slices centred at
 *  `centre` (x, y: continuous pixel coordinates of the whole image, 0..3*size by 0..size, as the
 *  daemon samples them: panel u/v axes axial (+x, +y), coronal (+x, -z), sagittal (+y, -z), fovMm
 *  across each panel). Null outside the image. */
export function sliceTapToImageMm(centre: Vec3, x: number, y: number, size: number, fovMm = 220): Vec3 | null {
  if (!(x >= 0 && x < 3 * size && y >= 0 && y <= size)) return null;
  const panel = Math.min(2, Math.floor(x / size));
  const px = fovMm / size;
  const du = (x - panel * size - size / 2) * px, dv = (y - size / 2) * px;
  const axes: [Vec3, Vec3][] = [[[1, 0, 0], [0, 1, 0]], [[1, 0, 0], [0, 0, -1]], [[0, 1, 0], [0, 0, -1]]];
  const [u, v] = axes[panel];
  return [0, 1, 2].map((i) => centre[i] + du * u[i] + dv * v[i]) as Vec3;
}

/** The image fiducials with `label` placed at `p` (moved when it exists, else added). */
export function placeFiducial(fids: { label: string; p_image_mm: Vec3 }[], label: string, p: Vec3): { label: string; p_image_mm: Vec3 }[] {
  const out = fids.map((f) => (f.label === label ? { label, p_image_mm: p } : { label: f.label, p_image_mm: f.p_image_mm }));
  if (!fids.some((f) => f.label === label)) out.push({ label, p_image_mm: p });
  return out;
}

/** A new fiducial's label: F1, F2, ... not yet used. */
export function newFiducialLabel(fids: { label: string }[]): string {
  const used = new Set(fids.map((f) => f.label));
  for (let i = 1; ; i++) if (!used.has(`F${i}`)) return `F${i}`;
}
