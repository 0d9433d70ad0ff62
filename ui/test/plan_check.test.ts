import { describe, expect, it } from "vitest";
import { parseNiftiOffThread, planCheckOffThread } from "../src/off_thread";
import { ballNifti, binaryPly, sphere } from "./volume_fixtures";

// The quick check as the Preoperative screen asks for it (off_thread.ts: in a Web Worker in the
// browser, here in the thread: vitest's node has no Worker).
describe("the Preoperative quick check off the main thread (7.34)", () => {
  // A 41^3 ball mask of radius 10 voxels, 1 mm, voxel (i, j, k) at RAS (i, j, k) = LPS (-i, -j, k);
  // the plan's surface a sphere of radius 9.5 mm about the same centre, in LPS.
  const mask = () => ballNifti(41, 10, 1, [0, 0, 0]);
  const surf = sphere([-20, -20, 20], 9.5);

  it("draws the mask's three slices and cuts the surface by them", async () => {
    const chk = await planCheckOffThread(mask(), "plan1_brain_mask.nii", binaryPly(surf), "plan1_brain_surface.ply");
    expect(chk.dims).toEqual([41, 41, 41]);
    expect(chk.mask?.centroid).toEqual([20, 20, 20]);
    expect(chk.mask!.voxels).toBeGreaterThan(4000); // 4/3 pi 10^3 = 4189
    expect(chk.mask!.voxels).toBeLessThan(4400);
    expect(chk.surface?.triangles).toBe(2 * surf.f.length);
    expect(chk.surface!.panels.every((p) => p.length > 20)).toBe(true);
    expect(chk.surface!.inMask).toBeGreaterThan(0.99);
    expect(chk.surfaceError).toBeUndefined();
  });

  it("a cut surface file is named and the mask picture stays; a bad mask is refused naming it", async () => {
    const chk = await planCheckOffThread(mask(), "m.nii", binaryPly(surf, 100), "plan1_brain_surface.ply");
    expect(chk.mask?.voxels).toBeGreaterThan(4000);
    expect(chk.surface).toBeUndefined();
    expect(chk.surfaceError).toMatch(/plan1_brain_surface\.ply/);
    await expect(planCheckOffThread(new TextEncoder().encode("not a volume").buffer as ArrayBuffer, "plan1_brain_mask.nii.gz", null, ""))
      .rejects.toThrow(/plan1_brain_mask\.nii\.gz: too short/);
  });

  it("reads a mask for picking the same way", async () => {
    const v = await parseNiftiOffThread(mask(), "mask.nii");
    expect(v.dims).toEqual([41, 41, 41]);
    expect(v.data[20 + 41 * (20 + 41 * 20)]).toBe(1);
  });
});
