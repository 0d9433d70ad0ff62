import { describe, expect, it } from "vitest";
import { addPoint, deletePoint, hitPoint, interp, MIN_GAP, movePoint, pointsFromTf, setColour, tfFromPoints, type TfJson } from "../src/tf_model";

const preset: TfJson = {
  name: "cortex_t1", units: "normalized",
  colour: [[0, 0.3, 0.1, 0.1], [0.55, 0.95, 0.75, 0.7], [1, 1, 0.95, 0.9]],
  opacity: [[0, 0], [0.22, 0], [0.35, 0.6], [1, 1]],
  gradient_opacity: [[0, 0.2], [0.05, 1]],
};

describe("transfer function model", () => {
  it("interpolates piecewise linearly, constant beyond the ends", () => {
    expect(interp([[0, 0], [1, 1]], 0.25)).toEqual([0.25]);
    expect(interp([[0.2, 1], [0.4, 3]], 0)).toEqual([1]);
    expect(interp([[0.2, 1], [0.4, 3]], 0.9)).toEqual([3]);
    expect(interp([], 0.5)).toEqual([]);
  });

  it("merges a preset's colour and opacity lists into one point list describing the same function", () => {
    const pts = pointsFromTf(preset);
    expect(pts.map((p) => p.x)).toEqual([0, 0.22, 0.35, 0.55, 1]);
    const tf = tfFromPoints(pts, preset);
    for (const x of [0, 0.1, 0.22, 0.3, 0.35, 0.5, 0.55, 0.8, 1]) {
      expect(interp(tf.opacity, x)[0]).toBeCloseTo(interp(preset.opacity, x)[0], 3);
      interp(tf.colour, x).forEach((v, k) => expect(v).toBeCloseTo(interp(preset.colour, x)[k], 3));
    }
    expect(tf.gradient_opacity).toEqual(preset.gradient_opacity);
    expect(tf.units).toBe("normalized");
    expect(tf.name).toBe("custom");
    // sorted by x, as the daemon requires
    expect(tf.opacity.map((p) => p[0])).toEqual([...tf.opacity.map((p) => p[0])].sort((a, b) => a - b));
  });

  it("keeps a dragged point between its neighbours and inside [0, 1]", () => {
    const pts = pointsFromTf(preset);
    const moved = movePoint(pts, 2, 0.9, 1.7);
    expect(moved[2].x).toBeCloseTo(0.55 - MIN_GAP, 9);
    expect(moved[2].opacity).toBe(1);
    expect(movePoint(pts, 2, 0.0, -1)[2]).toMatchObject({ x: 0.22 + MIN_GAP, opacity: 0 });
    expect(movePoint(pts, 0, -5, 0.5)[0].x).toBe(0);
    expect(movePoint(pts, 4, 5, 0.5)[4].x).toBe(1);
    expect(pts[2].x).toBe(0.35); // the input is not changed
  });

  it("adds a point with the colour there, refuses one on top of another, keeps at least two", () => {
    const pts = pointsFromTf(preset);
    const r = addPoint(pts, 0.45, 0.3)!;
    expect(r.index).toBe(3);
    expect(r.points).toHaveLength(6);
    expect(r.points[3].colour[0]).toBeCloseTo(interp(preset.colour, 0.45)[0], 6);
    expect(addPoint(pts, 0.351, 0.5)).toBeNull();
    let few = deletePoint(pts, 1);
    expect(few).toHaveLength(4);
    few = deletePoint(deletePoint(deletePoint(few, 0), 0), 0);
    expect(few).toHaveLength(2);
    expect(deletePoint(pts, 9)).toBe(pts);
    expect(setColour(pts, 0, [2, -1, 0.5])[0].colour).toEqual([1, 0, 0.5]);
  });

  it("finds the point under a finger within its radius", () => {
    const pts = pointsFromTf(preset);
    // point 2 (x 0.35, opacity 0.6) in a 300 x 150 plot is at (105, 60)
    expect(hitPoint(pts, 110, 70, 300, 150)).toBe(2);
    expect(hitPoint(pts, 200, 10, 300, 150)).toBe(-1);
  });
});
