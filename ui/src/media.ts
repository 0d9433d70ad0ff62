// Preoperative data from a USB stick (issue 7, 7.4): what GET /api/media/volumes lists (volume
// files and DICOM folders under the daemon's media.removable_root) as choices in words, and the
// import request (POST /api/cases/{id}/volumes/import-media). No DOM here: unit-tested.
import { fmtBytes } from "./case_detail";

export interface MediaVolume { path: string; kind: "nifti" | "nrrd" | "metaimage" | "dicom"; size_bytes: number; files?: number }
export interface MediaAnswer { root: string; present: boolean; note?: string; truncated: boolean; volumes: MediaVolume[] }

const KIND_WORDS: Record<string, string> = { nifti: "NIfTI", nrrd: "NRRD", metaimage: "MetaImage", dicom: "DICOM series" };

/** One choice per volume: the path on the stick, its kind and size. */
export function mediaChoices(a: MediaAnswer): { value: string; label: string }[] {
  return a.volumes.map((v) => ({
    value: v.path,
    label: `${v.path === "." ? "(the stick itself)" : v.path} — ${KIND_WORDS[v.kind] ?? v.kind}${v.kind === "dicom" ? `, ${v.files} files` : ""}, ${fmtBytes(v.size_bytes)}`,
  }));
}

/** The line beside the choices: what was found, or why nothing (no stick, nothing on it). */
export function mediaLine(a: MediaAnswer): string {
  if (!a.present) return `No USB stick found (${a.root} is empty or missing). Plug the stick in and look again.`;
  if (!a.volumes.length) return `Nothing to import on the stick under ${a.root}: no .nii, .nii.gz, .nrrd, .mha file or DICOM folder.`;
  const n = a.volumes.length;
  return `${n} volume${n > 1 ? "s" : ""} on the stick under ${a.root}${a.truncated ? " (the listing was cut off: too many files)" : ""}. Choose one and its modality, then Import.`;
}

/** The import request's path and body. */
export function mediaImport(caseId: number, path: string, modality: string): { path: string; body: { path: string; modality: string } } {
  return { path: `/api/cases/${caseId}/volumes/import-media`, body: { path, modality } };
}
