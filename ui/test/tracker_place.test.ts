import { describe, expect, it } from "vitest";
import { newFiducialLabel, placeFiducial, sliceTapToImageMm, type Vec3 } from "../src/tracker_model";

describe("image fiducials by touch on the tri-planar slices", () => {
  const c: Vec3 = [10, -20, 30];
  const size = 240, fov = 220, px = fov / size;
  it("maps a tap on each panel to the point that panel shows (the daemon's tri_planar axes)", () => {
    // The centre of each panel is the slices' point.
    for (const panel of [0, 1, 2]) expect(sliceTapToImageMm(c, panel * size + size / 2, size / 2, size, fov)).toEqual(c);
    // Axial: right on the screen = +x (patient left), down = +y (posterior).
    const a = sliceTapToImageMm(c, size / 2 + 24, size / 2 + 12, size, fov)!;
    expect(a[0]).toBeCloseTo(c[0] + 24 * px, 9); expect(a[1]).toBeCloseTo(c[1] + 12 * px, 9); expect(a[2]).toBeCloseTo(c[2], 9);
    // Coronal: right = +x, up = +z (superior).
    const k = sliceTapToImageMm(c, size + size / 2 - 6, size / 2 - 30, size, fov)!;
    expect(k[0]).toBeCloseTo(c[0] - 6 * px, 9); expect(k[1]).toBeCloseTo(c[1], 9); expect(k[2]).toBeCloseTo(c[2] + 30 * px, 9);
    // Sagittal: right = +y (posterior), down = -z.
    const s = sliceTapToImageMm(c, 2 * size + size / 2 + 50, size / 2 + 5, size, fov)!;
    expect(s[0]).toBeCloseTo(c[0], 9); expect(s[1]).toBeCloseTo(c[1] + 50 * px, 9); expect(s[2]).toBeCloseTo(c[2] - 5 * px, 9);
    expect(sliceTapToImageMm(c, -1, 10, size, fov)).toBeNull();
    expect(sliceTapToImageMm(c, 3 * size, 10, size, fov)).toBeNull();
  });
  it("moves a fiducial that exists, adds a new one otherwise", () => {
    const fids = [{ label: "F1", p_image_mm: [0, 0, 0] as Vec3 }, { label: "nasion", p_image_mm: [1, 2, 3] as Vec3 }];
    expect(placeFiducial(fids, "nasion", [4, 5, 6])).toEqual([{ label: "F1", p_image_mm: [0, 0, 0] }, { label: "nasion", p_image_mm: [4, 5, 6] }]);
    expect(placeFiducial(fids, "F2", [7, 8, 9]).map((f) => f.label)).toEqual(["F1", "nasion", "F2"]);
    expect(newFiducialLabel(fids)).toBe("F2");
    expect(fids[1].p_image_mm).toEqual([1, 2, 3]); // the input is not changed
  });
});
