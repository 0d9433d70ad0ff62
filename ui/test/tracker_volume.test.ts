import { describe, expect, it } from "vitest";
import { caseSliceVolume, slicesPath, suggestedFiducialsPath } from "../src/tracker_model";

describe("the Tracker screen's slices come from the open case's volume", () => {
  it("uses the case's newest T1, else the bundled MRI", () => {
    expect(caseSliceVolume({ id: 7, volumes: [{ id: 3, modality: "T1" }, { id: 9, modality: "mask" }, { id: 5, modality: "T1" }, { id: 11, modality: "CT" }] }))
      .toEqual({ caseId: 7, volumeId: 5 });
    expect(caseSliceVolume({ id: 7, volumes: [{ id: 2, modality: "CT" }, { id: 4, modality: "mask" }] })).toBeNull();
    expect(caseSliceVolume({ id: 7 })).toBeNull();
    expect(caseSliceVolume(null)).toBeNull();
  });

  it("asks for the case's slices with case_id and volume_id, the bundled ones without", () => {
    const vol = caseSliceVolume({ id: 12, volumes: [{ id: 40, modality: "T1" }] });
    expect(slicesPath([1.234, -5, 60.05], 240, 220, vol))
      .toBe("/api/navigation/slices?x=1.23&y=-5.00&z=60.05&size=240&fov_mm=220&format=jpeg&case_id=12&volume_id=40");
    expect(slicesPath([0, 0, 0], 240, undefined, null)).toBe("/api/navigation/slices?x=0.00&y=0.00&z=0.00&size=240&fov_mm=220&format=jpeg");
    expect(slicesPath([0, 0, 0], 240)).not.toContain("case_id");
  });

  it("suggests skin fiducials on the same volume", () => {
    expect(suggestedFiducialsPath({ caseId: 12, volumeId: 40 })).toBe("/api/navigation/suggested-fiducials?case_id=12&volume_id=40");
    expect(suggestedFiducialsPath(null)).toBe("/api/navigation/suggested-fiducials");
  });
});
