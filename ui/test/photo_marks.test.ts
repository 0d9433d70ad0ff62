import { describe, expect, it } from "vitest";
import { cardinalPath, cardinalPoint, clampPx, defaultCamera, imageKind, insertRoiPoint, nearest, projectPoint, type Px } from "../src/photo_marks";

const square: Px[] = [[0, 0], [100, 0], [100, 100], [0, 100]];

describe("photo marks", () => {
  it("draws a closed spline through every control point", () => {
    const d = cardinalPath(square, 0);
    expect(d.startsWith("M0,0 C")).toBe(true);
    expect(d.endsWith(" Z")).toBe(true);
    expect(d.match(/C/g)).toHaveLength(4);
    for (let i = 0; i < 4; i++) {
      expect(cardinalPoint(square, i, 0)).toEqual(square[i]);
      const e = cardinalPoint(square, i, 1);
      expect(e[0]).toBeCloseTo(square[(i + 1) % 4][0], 9);
      expect(e[1]).toBeCloseTo(square[(i + 1) % 4][1], 9);
    }
    // Catmull-Rom bulges out of the square between corners; tension 1 is the straight polygon.
    expect(cardinalPoint(square, 0, 0.5, 0)[1]).toBeLessThan(0);
    expect(cardinalPoint(square, 0, 0.5, 1)).toEqual([50, 0]);
    expect(cardinalPath([[1, 2], [3, 4]])).toBe("M1,2 L3,4");
    expect(cardinalPath([])).toBe("");
  });

  it("inserts a tapped point into the nearest edge and appends the first three", () => {
    expect(insertRoiPoint([], [5, 5])).toEqual({ points: [[5, 5]], index: 0 });
    const r = insertRoiPoint(square, [50, -5]);
    expect(r.index).toBe(1);
    expect(r.points[1]).toEqual([50, -5]);
    const r2 = insertRoiPoint(square, [-5, 50]);
    expect(r2.index).toBe(4);
  });

  it("finds marks under a finger, keeps pixels in the photo, projects world points", () => {
    expect(nearest(square, [97, 4], 10)).toBe(1);
    expect(nearest(square, [50, 50], 10)).toBe(-1);
    expect(clampPx([-3, 900], 640, 480)).toEqual([-0.5, 479.5]);
    const T = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 500], [0, 0, 0, 1]];
    const K = { fx: 1000, fy: 1000, cx: 319.5, cy: 239.5 };
    expect(projectPoint(T, K, [0, 0, 0])).toEqual([319.5, 239.5]);
    expect(projectPoint(T, K, [50, -25, 0])).toEqual([419.5, 189.5]);
    expect(projectPoint(T, K, [0, 0, -600])).toBeNull();
    expect(defaultCamera(640, 480, 800)).toMatchObject({ width: 640, height: 480, fx: 800, fy: 800, cx: 319.5, cy: 239.5 });
  });

  it("tells PNG and JPEG by their signature, anything else not", () => {
    expect(imageKind(new Uint8Array([0x89, 0x50, 0x4e, 0x47, 0x0d, 0x0a, 0x1a, 0x0a, 0]))).toBe("png");
    expect(imageKind(new Uint8Array([0xff, 0xd8, 0xff, 0xe0]))).toBe("jpeg");
    expect(imageKind(new TextEncoder().encode("hello, not a photo"))).toBeNull();
    expect(imageKind(new Uint8Array([0x47, 0x49, 0x46, 0x38]))).toBeNull(); // GIF
  });
});
