import { describe, expect, it } from "vitest";
import {
  canReport, labelProblem, landmarkLines, shiftHeadline, shiftNotes, shiftTable, suggestLabel,
  type BrainShift, type Landmark,
} from "../src/landmarks_model";
import type { Vec3 } from "../src/tracker_model";

const lm = (label: string, set: string, p: Vec3 = [0, 0, 0]): Landmark => ({
  label, set, p_reference_mm: p, p_image_mm: p, spread_mm: 0.05, frames: 18, registration_revision: 7,
});

const report = (over: Partial<BrainShift> = {}): BrainShift => ({
  earlier: "initial", later: "later", n: 2,
  rows: [
    { label: "L1", earlier_image_mm: [0, 0, 0], later_image_mm: [0.5, 3, -0.25], d_mm: [0.5, 3, -0.25], magnitude_mm: Math.hypot(0.5, 3, -0.25) },
    { label: "L2", earlier_image_mm: [1, 1, 1], later_image_mm: [0.6, 3.5, 1], d_mm: [-0.4, 2.5, 0], magnitude_mm: Math.hypot(-0.4, 2.5) },
  ],
  mean_d_mm: [0.05, 2.75, -0.126], sd_d_mm: [0.636, 0.354, 0.177], mean_abs_d_mm: [0.45, 2.75, 0.125],
  mean_magnitude_mm: 2.81, sd_magnitude_mm: 0.37, max_magnitude_mm: 3.05,
  missing_later: [], missing_earlier: [], same_registration: true, table: "",
  ...over,
});

describe("landmark labels", () => {
  it("suggests L1, L2, ... in the first set, skipping labels used in any set", () => {
    expect(suggestLabel([], "initial")).toBe("L1");
    expect(suggestLabel([lm("L1", "initial"), lm("L2", "initial")], "initial")).toBe("L3");
    expect(suggestLabel([lm("L1", "initial"), lm("L3", "later")], "initial")).toBe("L2");
  });
  it("suggests in the later set the first earlier landmark not yet re-digitised, then new ones", () => {
    const ls = [lm("L1", "initial"), lm("L2", "initial"), lm("gyrus", "initial"), lm("L1", "later")];
    expect(suggestLabel(ls, "later")).toBe("L2");
    expect(suggestLabel([...ls, lm("L2", "later")], "later")).toBe("gyrus");
    expect(suggestLabel([...ls, lm("L2", "later"), lm("gyrus", "later")], "later")).toBe("L3");
  });
  it("refuses what the daemon refuses, in words", () => {
    expect(labelProblem("L1")).toBe("");
    expect(labelProblem("  ")).toMatch(/Type a label/);
    expect(labelProblem("a/b")).toMatch(/'\/'/);
    expect(labelProblem("x".repeat(65))).toMatch(/64/);
    expect(labelProblem("a\tb")).toMatch(/control/);
  });
});

describe("landmark lines and the report's availability", () => {
  it("lists each label once, in the order first recorded, with where it is", () => {
    const lines = landmarkLines([lm("L2", "initial"), lm("L1", "initial"), lm("L2", "later"), lm("X", "other"), lm("L3", "later")]);
    expect(lines.map((l) => l.label)).toEqual(["L2", "L1", "L3"]);
    expect(lines[0].earlier?.set).toBe("initial");
    expect(lines[0].later?.set).toBe("later");
    expect(lines[1].later).toBeNull();
    expect(lines[2].earlier).toBeNull();
  });
  it("offers the report only when both sets share a label", () => {
    expect(canReport([])).toBe(false);
    expect(canReport([lm("L1", "initial"), lm("L2", "later")])).toBe(false);
    expect(canReport([lm("L1", "initial"), lm("L2", "later"), lm("L1", "later")])).toBe(true);
  });
});

describe("the brain-shift table", () => {
  it("gives one row per landmark, signed per axis, and mean ± sd", () => {
    const t = shiftTable(report());
    expect(t.head).toEqual(["Landmark", "dx (L) mm", "dy (P) mm", "dz (S) mm", "|d| mm"]);
    expect(t.rows).toEqual([["L1", "+0.50", "+3.00", "−0.25", "3.05"], ["L2", "−0.40", "+2.50", "+0.00", "2.53"]]);
    expect(t.summary).toEqual(["mean ± sd (n = 2)", "+0.05 ± 0.64", "+2.75 ± 0.35", "−0.13 ± 0.18", "2.81 ± 0.37"]);
    const tiny = report({ rows: [{ label: "L1", earlier_image_mm: [0, 0, 0], later_image_mm: [0, 0, 0], d_mm: [-0.004, 0.004, -0.006], magnitude_mm: 0.008 }] });
    expect(shiftTable(tiny).rows[0].slice(1, 4)).toEqual(["+0.00", "+0.00", "−0.01"]);
  });
  it("says what is missing either way and when the registrations differ", () => {
    expect(shiftNotes(report())).toBe("");
    const n = shiftNotes(report({ missing_later: ["L3"], missing_earlier: ["L9"], same_registration: false }));
    expect(n).toContain("not re-digitised in “later”: L3");
    expect(n).toContain("only in “later”: L9");
    expect(n).toContain("different patient registrations");
    expect(shiftHeadline(report())).toBe("Brain shift “initial” → “later” over 2 landmarks: mean |d| 2.81 mm, largest 3.05 mm");
  });
});
