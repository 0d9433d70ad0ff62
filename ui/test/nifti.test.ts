import { describe, expect, it } from "vitest";
import { apply4, centreLps, gunzipIfNeeded, invert4, parseNifti, pickSurface, pixelRay, sampleAt } from "../src/nifti";
import { orbitPose } from "../src/orbit";
import { ballNifti } from "./volume_fixtures";

describe("surface pick on a NIfTI mask", () => {
  it("reads the grid, maps voxels to LPS (RAS flipped) by the qform or the sform", () => {
    for (const q of [true, false]) {
      const vol = parseNifti(ballNifti(21, 6, 2, [-20, -30, 10], q));
      expect(vol.dims).toEqual([21, 21, 21]);
      expect(vol.spacing).toEqual([2, 2, 2]);
      // voxel (0,0,0) is RAS (-20, -30, 10) -> LPS (20, 30, 10); the centre voxel (10,10,10) RAS (0,-10,30)
      expect(apply4(vol.ijkToLps, [0, 0, 0])).toEqual([20, 30, 10]);
      expect(centreLps(vol)).toEqual([-0, 10, 30].map((x) => expect.closeTo(x, 9)));
      expect(sampleAt(vol, centreLps(vol))).toBe(1);
      expect(sampleAt(vol, [500, 0, 0])).toBe(0);
      const back = apply4(vol.lpsToIjk, apply4(vol.ijkToLps, [3, 4, 5]));
      back.forEach((x, i) => expect(x).toBeCloseTo([3, 4, 5][i], 9));
    }
    expect(() => parseNifti(new ArrayBuffer(10), "m.nii")).toThrow(/m.nii: too short/);
    expect(() => parseNifti(new ArrayBuffer(400), "m.nii")).toThrow(/not a NIfTI-1 file/);
    expect(invert4([[2, 0, 0, 1], [0, 2, 0, 0], [0, 0, 2, 0], [0, 0, 0, 1]])[0]).toEqual([0.5, 0, 0, -0.5]);
  });

  it("gunzips a .nii.gz and passes plain bytes through", async () => {
    const raw = ballNifti(9, 3, 1, [0, 0, 0]);
    const gz = await new Response(new Blob([raw]).stream().pipeThrough(new CompressionStream("gzip"))).arrayBuffer();
    expect(new Uint8Array(gz)[0]).toBe(0x1f);
    expect(new Uint8Array(await gunzipIfNeeded(gz))).toEqual(new Uint8Array(raw));
    expect(await gunzipIfNeeded(raw)).toBe(raw);
  });

  it("a ray from an orbit camera through the image centre lands on the ball's surface", () => {
    const vol = parseNifti(ballNifti(41, 15, 1, [-20, -20, -20])); // ball radius 15 mm round LPS (0,0,0)
    const c = centreLps(vol);
    for (const [az, el] of [[0, 0], [-90, 0], [45, 30], [180, -60]]) {
      const T = orbitPose({ azimuthDeg: az, elevationDeg: el, distanceMm: 300 }, c);
      const { origin, dir } = pixelRay(T, { fx: 1000, fy: 1000, cx: 319.5, cy: 239.5 }, 319.5, 239.5);
      const p = pickSurface(vol, origin, dir, 600)!;
      expect(p).not.toBeNull();
      expect(Math.hypot(p[0] - c[0], p[1] - c[1], p[2] - c[2])).toBeGreaterThan(14);
      expect(Math.hypot(p[0] - c[0], p[1] - c[1], p[2] - c[2])).toBeLessThan(16.5);
      expect(Math.hypot(p[0] - origin[0], p[1] - origin[1], p[2] - origin[2])).toBeCloseTo(285, -1);
    }
    // A pixel off to the side misses it.
    const T = orbitPose({ azimuthDeg: 0, elevationDeg: 0, distanceMm: 300 }, c);
    const off = pixelRay(T, { fx: 1000, fy: 1000, cx: 319.5, cy: 239.5 }, 319.5 + 200, 239.5);
    expect(pickSurface(vol, off.origin, off.dir, 600)).toBeNull();
  });
});
