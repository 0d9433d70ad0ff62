import { describe, expect, it } from "vitest";
import { auditDetails, auditRows, fmtBytes, holdings, patientLine, registrationRows, type CaseRecord } from "../src/case_detail";

const base: CaseRecord = { id: 1, uid: "u", title: "t", state: "new", patient_id: null, created_utc: "2026-11-22T10:00:00.123Z", updated_utc: "2026-11-22T10:00:00Z" };

describe("case contents", () => {
  it("says what an empty case lacks", () => {
    expect(holdings({ ...base, volumes: [], photos: [], registrations: [], results: [] }))
      .toEqual(["No volume yet", "No photo yet", "No landmarks yet", "No ROI yet", "Not registered yet"]);
  });

  it("counts what a full case holds, with the best NMI of the succeeded runs", () => {
    const c: CaseRecord = {
      ...base,
      volumes: [{ id: 1, modality: "T1", original_name: "t1.nii.gz", sha256: "ab", size_bytes: 5, created_utc: "" },
                { id: 2, modality: "T1", original_name: "mask", sha256: "cd", size_bytes: 5, created_utc: "" }],
      photos: [{ id: 1, original_name: "p.png", sha256: "ef", intrinsics: { width: 640, height: 480 }, created_utc: "" }],
      landmarks: { id: 1, revision: 2, points: [{ name: "L1", world_mm: [1, 2, 3], pixel: [4, 5] }] },
      roi: { id: 1, revision: 1, roi: { type: "closed-cardinal-spline", points: [[1, 2], [3, 4], [5, 6]] } },
      registrations: [{ id: 1, status: "succeeded", created_utc: "", nmi: 1.2 }, { id: 2, status: "cancelled", created_utc: "", nmi: 1.9 },
                      { id: 3, status: "succeeded", created_utc: "", nmi: 1.25 }],
      results: [{ id: 1, kind: "result", name: "r.json", media_type: "application/json", registration_id: 1 }],
    };
    expect(holdings(c)).toEqual(["2 volumes (T1)", "1 photo", "1 landmark pair (revision 2)", "ROI with 3 control points (revision 1)",
                                 "3 registrations, 2 succeeded, best NMI 1.2500", "1 result file"]);
  });

  it("lists registrations newest first with dashes for missing figures", () => {
    const rows = registrationRows([{ id: 1, status: "succeeded", created_utc: "2026-11-22T10:00:00Z", nmi: 1.23456, seconds: 12.34, evaluations: 800 },
                                   { id: 2, status: "failed", created_utc: "2026-11-22T11:00:00Z", error: "photo: unreadable" }]);
    expect(rows[0]).toEqual(["#2", "failed", "–", "–", "–", "2026-11-22 11:00:00 UTC", "photo: unreadable"]);
    expect(rows[1]).toEqual(["#1", "succeeded", "1.2346", "12.3 s", "800", "2026-11-22 10:00:00 UTC", ""]);
  });

  it("writes the patient, sizes and audit details in plain words", () => {
    expect(patientLine(undefined)).toBe("No patient recorded");
    expect(patientLine({ id: 1, mrn: "M1", family_name: "Doe", given_name: "Jo", birth_date: "1970-01-02" })).toBe("Doe, Jo · MRN M1 · born 1970-01-02");
    expect(fmtBytes(512)).toBe("512 B");
    expect(fmtBytes(1536)).toBe("1.5 KiB");
    expect(fmtBytes(3 * 1024 * 1024)).toBe("3.0 MiB");
    expect(fmtBytes(-1)).toBe("?");
    expect(auditDetails({ from: "new", to: "planned", n: 3 })).toBe("from: new, to: planned, n: 3");
    expect(auditDetails(null)).toBe("");
    expect(auditDetails({ x: "y".repeat(300) }, 20)).toHaveLength(20);
    const rows = auditRows([{ id: 1, at_utc: "2026-11-22T10:00:00Z", actor: "kiosk", action: "case.create" },
                            { id: 2, at_utc: "2026-11-22T10:01:00Z", actor: "rita", action: "case.view", details: { via: "http" } }]);
    expect(rows.map((r) => r[2])).toEqual(["case.view", "case.create"]);
    expect(rows[0]).toEqual(["2026-11-22 10:01:00 UTC", "rita", "case.view", "via: http"]);
  });
});
