import { describe, expect, it } from "vitest";
import { dragOrbit, lookAt, namedViewOf, NAMED_VIEWS, orbitEye, orbitPose, zoomOrbit, type Vec3 } from "../src/orbit";

const apply = (T: number[][], p: Vec3) => [0, 1, 2].map((r) => T[r][0] * p[0] + T[r][1] * p[1] + T[r][2] * p[2] + T[r][3]);
const target: Vec3 = [-0.27, 10.93, 8.25];

describe("orbit", () => {
  it("the left view is core's standard left view (image right = posterior, image up = superior)", () => {
    const T = orbitPose({ azimuthDeg: 0, elevationDeg: 0, distanceMm: 450 }, target);
    const core = lookAt([target[0] + 450, target[1], target[2]], target, [0, 0, 1]);
    for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) expect(T[r][c]).toBeCloseTo(core[r][c], 9);
    expect(T[0].slice(0, 3)).toEqual([0, 1, 0].map((v) => expect.closeTo(v, 9)));
    expect(T[1].slice(0, 3)).toEqual([0, 0, -1].map((v) => expect.closeTo(v, 9)));
  });

  it("any orbit is a rigid pose that sees the target straight ahead at the distance", () => {
    for (const [az, el, d] of [[0, 0, 450], [-90, 30, 300], [137, -60, 800], [-179, 89, 200]]) {
      const T = orbitPose({ azimuthDeg: az, elevationDeg: el, distanceMm: d }, target);
      const R = T.slice(0, 3).map((r) => r.slice(0, 3));
      for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++)
        expect(R[i][0] * R[j][0] + R[i][1] * R[j][1] + R[i][2] * R[j][2]).toBeCloseTo(i === j ? 1 : 0, 9);
      const det = R[0][0] * (R[1][1] * R[2][2] - R[1][2] * R[2][1]) - R[0][1] * (R[1][0] * R[2][2] - R[1][2] * R[2][0]) + R[0][2] * (R[1][0] * R[2][1] - R[1][1] * R[2][0]);
      expect(det).toBeCloseTo(1, 9);
      const p = apply(T, target);
      expect(p[0]).toBeCloseTo(0, 6); expect(p[1]).toBeCloseTo(0, 6); expect(p[2]).toBeCloseTo(d, 6);
      expect(apply(T, orbitEye({ azimuthDeg: az, elevationDeg: el, distanceMm: d }, target)).map((v) => Math.abs(v))).toEqual([0, 0, 0].map(() => expect.closeTo(0, 6)));
    }
  });

  it("the anterior view looks from the front (-y in LPS) with the patient's left on the image right", () => {
    const v = NAMED_VIEWS.anterior;
    const eye = orbitEye({ ...v, distanceMm: 450 }, [0, 0, 0]);
    expect(eye[1]).toBeCloseTo(-450, 6);
    const T = orbitPose({ ...v, distanceMm: 450 }, [0, 0, 0]);
    expect(apply(T, [10, 0, 0])[0]).toBeGreaterThan(0); // +x (left) to the image right
    expect(apply(T, [0, 0, 10])[1]).toBeLessThan(0); // superior up
  });

  it("drags turn and tilt (clamped), pinches zoom (clamped), named views are recognised", () => {
    const o = { azimuthDeg: 0, elevationDeg: 0, distanceMm: 450 };
    expect(dragOrbit(o, 225, 0).azimuthDeg).toBeCloseTo(-90, 9); // right drag: towards the front
    expect(namedViewOf({ ...dragOrbit(o, 225, 0) })).toBe("anterior");
    expect(dragOrbit(o, -500, 0).azimuthDeg).toBeCloseTo(-160, 9); // 200 deg wraps to -160
    expect(dragOrbit(o, 0, 1000).elevationDeg).toBe(89);
    expect(dragOrbit(o, 0, -1000).elevationDeg).toBe(-89);
    expect(namedViewOf(o)).toBe("left");
    expect(namedViewOf(dragOrbit(o, 10, 0))).toBeNull();
    expect(zoomOrbit(o, 2).distanceMm).toBe(225);
    expect(zoomOrbit(o, 100).distanceMm).toBe(150);
    expect(zoomOrbit(o, 0.01).distanceMm).toBe(1500);
    expect(zoomOrbit(o, NaN).distanceMm).toBe(450);
  });
});
