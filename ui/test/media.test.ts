import { describe, expect, it } from "vitest";
import { mediaChoices, mediaImport, mediaLine, type MediaAnswer } from "../src/media";

describe("USB stick volumes", () => {
  it("words what the stick holds, or why nothing", () => {
    const a: MediaAnswer = { root: "/media", present: true, truncated: false, volumes: [
      { path: "patient/MR_T1", kind: "dicom", files: 6, size_bytes: 3 * 1024 * 1024 },
      { path: "t1.nii.gz", kind: "nifti", size_bytes: 2048 },
    ] };
    const c = mediaChoices(a);
    expect(c.map((x) => x.value)).toEqual(["patient/MR_T1", "t1.nii.gz"]);
    expect(c[0].label).toMatch(/^patient\/MR_T1 — DICOM series, 6 files, 3(\.0)? MiB$/);
    expect(c[1].label).toMatch(/^t1\.nii\.gz — NIfTI, 2(\.0)? KiB$/);
    expect(mediaLine(a)).toBe("2 volumes on the stick under /media. Choose one and its modality, then Import.");
    expect(mediaLine({ ...a, truncated: true })).toContain("cut off");
    expect(mediaLine({ root: "/media", present: false, truncated: false, volumes: [] })).toBe("No USB stick found (/media is empty or missing). Plug the stick in and look again.");
    expect(mediaLine({ root: "/media", present: true, truncated: false, volumes: [] })).toContain("Nothing to import");
    expect(mediaImport(4, "patient/MR_T1", "T1")).toEqual({ path: "/api/cases/4/volumes/import-media", body: { path: "patient/MR_T1", modality: "T1" } });
  });
});
