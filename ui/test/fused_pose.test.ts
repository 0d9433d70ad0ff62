import { describe, expect, it } from "vitest";
import { depthOf, orbitCamera, pinchPan, translateCamera } from "../src/fused_pose";

const T = [[1, 0, 0, 5], [0, 0, -1, 20], [0, 1, 0, 300], [0, 0, 0, 1]];
const apply = (M: number[][], p: number[]) => [0, 1, 2].map((i) => M[i][0] * p[0] + M[i][1] * p[1] + M[i][2] * p[2] + M[i][3]);

describe("orbitCamera", () => {
  it("is the same camera without a turn", () => {
    const M = orbitCamera(T, 0, 0, 300);
    for (let i = 0; i < 4; ++i) for (let j = 0; j < 4; ++j) expect(M[i][j]).toBeCloseTo(T[i][j], 12);
  });
  it("keeps the pivot's picture point and its distance, and stays rigid", () => {
    // The world point the camera sees at the pivot (camera (0, 0, 300)).
    const pw = [-5, 0, 20]; // T * pw = (0, 0, 300): on the optical axis
    const pc = apply(T, pw);
    const M = orbitCamera(T, 25, -10, pc[2]);
    const q = apply(M, pw);
    expect(pc).toEqual([0, 0, 300]);
    expect(q[0]).toBeCloseTo(pc[0], 9);
    expect(q[1]).toBeCloseTo(pc[1], 9);
    expect(q[2]).toBeCloseTo(pc[2], 9);
    const R = M.slice(0, 3).map((r) => r.slice(0, 3));
    for (let i = 0; i < 3; ++i)
      for (let j = 0; j < 3; ++j) expect(R[i].reduce((s, x, k) => s + x * R[j][k], 0)).toBeCloseTo(i === j ? 1 : 0, 9);
  });
  it("turns other points: a 90 degree yaw moves a point off the axis", () => {
    const M = orbitCamera(T, 90, 0, 300);
    const off = apply(T, [50, 0, -20]); // 50 mm right of the pivot's world point... in the camera: x + 50
    const moved = apply(M, [50, 0, -20]);
    expect(Math.abs(moved[0] - off[0])).toBeGreaterThan(40);
    expect(depthOf(M, [50, 0, -20])).toBeCloseTo(moved[2], 9);
  });
});


describe("pinch and two-finger pan", () => {
  const T = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 400], [0, 0, 0, 1]]; // the origin 400 mm ahead
  const proj = (M: number[][], p: number[], f: number) => {
    const c = [0, 1, 2].map((i) => M[i][0] * p[0] + M[i][1] * p[1] + M[i][2] * p[2] + M[i][3]);
    return [(f * c[0]) / c[2], (f * c[1]) / c[2], c[2]];
  };
  it("a pinch to twice the distance doubles the picture about the pivot", () => {
    const r = pinchPan(T, 2, 0, 0, 400, 1000);
    expect(r.pivotDepthMm).toBeCloseTo(200, 9);
    const a = proj(T, [10, 5, 0], 1000), b = proj(r.T, [10, 5, 0], 1000);
    expect(b[0]).toBeCloseTo(2 * a[0], 9);
    expect(b[1]).toBeCloseTo(2 * a[1], 9);
  });
  it("a pan moves the pivot's plane with the fingers, pixel for pixel", () => {
    const r = pinchPan(T, 1, 30, -12, 400, 1000);
    const a = proj(T, [0, 0, 0], 1000), b = proj(r.T, [0, 0, 0], 1000);
    expect(b[0] - a[0]).toBeCloseTo(30, 9);
    expect(b[1] - a[1]).toBeCloseTo(-12, 9);
    expect(r.pivotDepthMm).toBeCloseTo(400, 9);
  });
  it("clamps the zoom and never goes through the pivot", () => {
    expect(pinchPan(T, 100, 0, 0, 400, 1000).pivotDepthMm).toBeCloseTo(100, 9);
    expect(pinchPan(T, 4, 0, 0, 60, 1000).pivotDepthMm).toBeCloseTo(30, 9);
    expect(translateCamera(T, 1, 2, 3)[2][3]).toBeCloseTo(397, 9);
  });
});
