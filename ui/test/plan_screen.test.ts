import { describe, expect, it } from "vitest";
import { maskQuickCheck, planJobOf, type PlanJob } from "../src/plan_screen";
import type { Volume } from "../src/nifti";

const I4 = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];

describe("Preoperative step", () => {
  it("finds the case's newest plan job", () => {
    const jobs: PlanJob[] = [
      { id: 3, kind: "plan", state: "succeeded", stage: "", fraction: 1, params: { case_id: 2 } },
      { id: 5, kind: "register", state: "running", stage: "", fraction: 0.2, params: { case_id: 2 } },
      { id: 7, kind: "plan", state: "running", stage: "surface", fraction: 0.6, params: { case_id: 2 } },
      { id: 9, kind: "plan", state: "queued", stage: "", fraction: 0, params: { case_id: 4 } },
    ];
    expect(planJobOf(jobs, 2)?.id).toBe(7);
    expect(planJobOf(jobs, 4)?.id).toBe(9);
    expect(planJobOf(jobs, 1)).toBeNull();
  });

  it("draws three slices through the mask's centroid", () => {
    // A 20x10x8 grid with a box mask i 4..11, j 2..5, k 1..4 (centroid 7.5, 3.5, 2.5).
    const X = 20, Y = 10, Z = 8;
    const data = new Uint8Array(X * Y * Z);
    for (let k = 1; k <= 4; k++) for (let j = 2; j <= 5; j++) for (let i = 4; i <= 11; i++) data[i + X * (j + Y * k)] = 1;
    const vol: Volume = { dims: [X, Y, Z], spacing: [1, 1, 1], data, ijkToLps: I4, lpsToIjk: I4 };
    const q = maskQuickCheck(vol, 40)!;
    expect(q.voxels).toBe(8 * 4 * 4);
    expect(q.centroid).toEqual([8, 4, 3]); // rounded
    expect(q.width).toBe(120);
    expect(q.height).toBe(40);
    // Axial panel: inside at i = 8 (u = 0.425), j = 4 (v: 1 - 4.5/10 = 0.55); outside at the corner.
    const px = (p: number, u: number, v: number) => q.grey[Math.floor(v * 40) * 120 + p * 40 + Math.floor(u * 40)];
    expect(px(0, 0.425, 0.55)).toBe(255);
    expect(px(0, 0.02, 0.02)).toBe(0);
    // Coronal (i across, k up): k = 3 is v = 1 - 3.5/8; sagittal (j across, k up).
    expect(px(1, 0.425, 1 - 3.5 / 8)).toBe(255);
    expect(px(2, 0.45, 1 - 3.5 / 8)).toBe(255);
    expect(px(2, 0.95, 1 - 3.5 / 8)).toBe(0);
    expect(maskQuickCheck({ ...vol, data: new Uint8Array(X * Y * Z) })).toBeNull();
  });
});
