import { describe, expect, it } from "vitest";
import { caseRenderFields, defaultLayers, histogramBars, histogramPath, newestT1, planModalities, type VolumeHistogram } from "../src/case_render";
import type { CaseRecord } from "../src/case_detail";

const rec = (over: Partial<CaseRecord>): CaseRecord =>
  ({ id: 4, uid: "u", title: "t", state: "new", patient_id: null, created_utc: "", updated_utc: "", ...over });
const vol = (id: number, modality: string) => ({ id, modality, original_name: "v.nii.gz", sha256: "", size_bytes: 1, created_utc: "" });
const res = (id: number, kind: string) => ({ id, kind, name: kind, media_type: "", registration_id: null });

describe("case renders", () => {
  it("renders the case's newest T1", () => {
    expect(newestT1(rec({ volumes: [vol(3, "T1"), vol(9, "mask"), vol(7, "T1"), vol(8, "CT")] }))).toBe(7);
    expect(newestT1(rec({ volumes: [vol(2, "CT")] }))).toBeNull();
    expect(newestT1(rec({}))).toBeNull();
  });

  it("offers the modalities the case's plan stored", () => {
    expect(planModalities(rec({ results: [res(1, "plan_brain_mask"), res(2, "plan_json")] }))).toEqual(["t1"]);
    expect(planModalities(rec({ results: [res(1, "plan_ct_on_t1"), res(2, "plan_fmri_on_t1")] }))).toEqual(["t1", "ct", "fmri"]);
    expect(planModalities(rec({ results: [res(5, "plan_fmri_on_t1")] }))).toEqual(["t1", "fmri"]);
  });

  it("sends case_id always, and every layer (hidden ones too) when there is more than the T1", () => {
    expect(caseRenderFields(4, defaultLayers(["t1"]))).toEqual({ case_id: 4 });
    const layers = defaultLayers(["t1", "ct"]);
    layers[1].visible = false;
    layers[1].weight = 1.4;
    const tf = { colour: [[0, 1, 0, 0], [1, 1, 0, 0]], opacity: [[0, 0], [1, 1]] };
    const f = caseRenderFields(4, layers, { preset: "skin", tf });
    expect(f).toEqual({ case_id: 4, modalities: [
      { name: "t1", transfer_function: tf, weight: 1, visible: true },
      { name: "ct", transfer_function: "ct_bone", weight: 1, visible: false },
    ] });
    expect((caseRenderFields(4, layers, { preset: "skin", tf: null }).modalities as { transfer_function: unknown }[])[0].transfer_function).toBe("skin");
  });

  it("draws the histogram in the units of the view's transfer function", () => {
    const hg: VolumeHistogram = { case_id: 4, volume_id: 7, bins: 4, normalizations: {
      whole: { range: [0, 100], outside: [0, 10, 0, 0], inside: [0, 0, Math.E - 1, 0] },
      brain_only: { range: [20, 80], outside: [5, 0, 0, 0], inside: [0, Math.E ** 2 - 1, 0, 0] },
    } };
    // brain only: inside the mask over the brain's range, log scale, tallest 1
    const b = histogramBars(hg, true);
    expect(b[1]).toBeCloseTo(1);
    expect(b[0]).toBe(0);
    // whole: inside + outside over the whole range
    const w = histogramBars(hg, false);
    expect(w[1]).toBeCloseTo(1);
    expect(w[2]).toBeCloseTo(1 / Math.log1p(10));
    // no mask: brain only falls back to the whole volume
    const nomask: VolumeHistogram = { ...hg, normalizations: { whole: { range: [0, 1], outside: [0, 0, 0, 0] }, brain_only: null } };
    expect(histogramBars(nomask, true)).toEqual([0, 0, 0, 0]);
    expect(histogramPath(4, 7, 64)).toBe("/api/cases/4/volumes/7/histogram?bins=64");
  });
});

describe("layer histograms", () => {
  it("asks the stored T1's histogram or the plan's CT / fMRI one", async () => {
    const { layerHistogramPath } = await import("../src/case_render");
    expect(layerHistogramPath(4, "t1", 7, 64)).toBe("/api/cases/4/volumes/7/histogram?bins=64");
    expect(layerHistogramPath(4, "t1", null)).toBeNull();
    expect(layerHistogramPath(4, "ct", null, 32)).toBe("/api/cases/4/plan/ct/histogram?bins=32");
    expect(layerHistogramPath(4, "fmri", 7)).toBe("/api/cases/4/plan/fmri/histogram?bins=128");
  });
});
