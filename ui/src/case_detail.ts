// What a case of the store holds (GET /api/cases/{id}) and its audit trail (/audit), turned
// into the words and table rows the case's Contents screen shows. Pure functions: unit-tested.

export interface Patient { id: number; mrn: string; family_name: string; given_name?: string; birth_date?: string | null }
export interface VolumeEntry { id: number; modality: string; original_name: string; sha256: string; size_bytes: number; created_utc: string }
export interface PhotoEntry { id: number; original_name: string; sha256: string; intrinsics?: { width?: number; height?: number } | null; created_utc: string }
export interface LandmarkPoint { name: string; world_mm: number[]; pixel: number[] }
export interface Registration { id: number; status: string; created_utc: string; nmi?: number; seconds?: number; evaluations?: number; final_pose?: unknown; error?: string }
export interface ResultEntry { id: number; kind: string; name: string; media_type: string; registration_id: number | null }
export interface CaseRecord {
  id: number; uid: string; title: string; state: string; patient_id: number | null; created_utc: string; updated_utc: string;
  patient?: Patient;
  volumes?: VolumeEntry[]; photos?: PhotoEntry[];
  landmarks?: { id: number; revision: number; points: LandmarkPoint[] };
  roi?: { id: number; revision: number; roi: { type?: string; tension?: number; points?: number[][] } };
  registrations?: Registration[]; results?: ResultEntry[];
}
export interface AuditEntry { id: number; at_utc: string; actor: string; action: string; details?: unknown }

export function fmtTime(utc: string | undefined | null): string {
  return utc ? utc.replace("T", " ").replace(/\.\d+Z$|Z$/, "") + " UTC" : "";
}

export function fmtBytes(n: number): string {
  if (!Number.isFinite(n) || n < 0) return "?";
  if (n < 1024) return `${n} B`;
  const units = ["KiB", "MiB", "GiB"];
  let v = n / 1024, i = 0;
  while (v >= 1024 && i < units.length - 1) { v /= 1024; i++; }
  return `${v >= 100 ? v.toFixed(0) : v.toFixed(1)} ${units[i]}`;
}

const plural = (n: number, one: string, many = `${one}s`) => `${n} ${n === 1 ? one : many}`;

/** One line per kind of thing the case holds, in workflow order ("nothing yet" lines included,
 *  so the reader sees what is missing). */
export function holdings(c: CaseRecord): string[] {
  const vols = c.volumes ?? [], photos = c.photos ?? [], regs = c.registrations ?? [];
  const mods = [...new Set(vols.map((v) => v.modality))];
  const out = [
    vols.length ? `${plural(vols.length, "volume")} (${mods.join(", ")})` : "No volume yet",
    photos.length ? plural(photos.length, "photo") : "No photo yet",
    c.landmarks ? `${plural(c.landmarks.points.length, "landmark pair")} (revision ${c.landmarks.revision})` : "No landmarks yet",
    c.roi ? `ROI with ${plural(c.roi.roi.points?.length ?? 0, "control point")} (revision ${c.roi.revision})` : "No ROI yet",
  ];
  if (!regs.length) out.push("Not registered yet");
  else {
    const ok = regs.filter((r) => r.status === "succeeded");
    const best = ok.reduce<number | null>((b, r) => (typeof r.nmi === "number" && (b === null || r.nmi > b) ? r.nmi : b), null);
    out.push(`${plural(regs.length, "registration")}, ${ok.length} succeeded${best !== null ? `, best NMI ${best.toFixed(4)}` : ""}`);
  }
  if (c.results?.length) out.push(plural(c.results.length, "result file"));
  return out;
}

export function patientLine(p: Patient | undefined): string {
  if (!p) return "No patient recorded";
  const name = [p.family_name, p.given_name].filter(Boolean).join(", ");
  return `${name || "(no name)"} · MRN ${p.mrn}${p.birth_date ? ` · born ${p.birth_date}` : ""}`;
}

/** The registrations table: newest first. */
export function registrationRows(regs: Registration[] | undefined): string[][] {
  return [...(regs ?? [])].sort((a, b) => b.id - a.id).map((r) => [
    `#${r.id}`, r.status,
    typeof r.nmi === "number" ? r.nmi.toFixed(4) : "–",
    typeof r.seconds === "number" ? `${r.seconds.toFixed(1)} s` : "–",
    typeof r.evaluations === "number" ? String(r.evaluations) : "–",
    fmtTime(r.created_utc),
    r.error ?? "",
  ]);
}

/** An audit entry's details in one short line: `key: value` pairs, nested values as JSON. */
export function auditDetails(d: unknown, maxLen = 160): string {
  if (d === null || d === undefined) return "";
  let s: string;
  if (typeof d === "object" && !Array.isArray(d))
    s = Object.entries(d as Record<string, unknown>).map(([k, v]) => `${k}: ${typeof v === "string" ? v : JSON.stringify(v)}`).join(", ");
  else s = typeof d === "string" ? d : JSON.stringify(d);
  return s.length > maxLen ? `${s.slice(0, maxLen - 1)}…` : s;
}

/** The audit table, newest first (the daemon answers oldest first). */
export function auditRows(entries: AuditEntry[]): string[][] {
  return [...entries].reverse().map((e) => [fmtTime(e.at_utc), e.actor, e.action, auditDetails(e.details)]);
}
