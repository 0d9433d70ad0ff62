import { describe, expect, it } from "vitest";
import { fusedLayers, fusedModalityFields, fusedRequest, layersNeedGl } from "../src/fused_modalities";
import type { CaseRecord } from "../src/case_detail";

const rec = (over: Partial<CaseRecord>): CaseRecord =>
  ({ id: 4, uid: "u", title: "t", state: "new", patient_id: null, created_utc: "", updated_utc: "", ...over });
const res = (id: number, kind: string) => ({ id, kind, name: kind, media_type: "", registration_id: null });
const T = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 300], [0, 0, 0, 1]];
const view = { width: 640, height: 480, preset: "cortex_t1", camera: { fx: 800 }, T_camera_from_world: T, surfaceOpacity: 0.5 };

describe("fused view modalities", () => {
  it("offers only the modalities the case's plan has", () => {
    expect(fusedLayers(rec({ results: [res(1, "plan_brain_surface"), res(2, "plan_brain_mask")] }))).toBeNull();
    expect(fusedLayers(rec({}))).toBeNull();
    expect(fusedLayers(rec({ results: [res(1, "plan_fmri_on_t1")] }))!.map((l) => l.name)).toEqual(["t1", "fmri"]);
    const all = fusedLayers(rec({ results: [res(1, "plan_ct_on_t1"), res(2, "plan_fmri_on_t1")] }))!;
    expect(all.map((l) => l.name)).toEqual(["t1", "ct", "fmri"]);
    expect(all.every((l) => l.visible)).toBe(true);
  });

  it("sends no modalities without layers: the plain fused view (any renderer)", () => {
    expect(fusedModalityFields(null, "cortex_t1")).toEqual({});
    const body = fusedRequest(view, null);
    expect(body).toEqual({ width: 640, height: 480, preset: "cortex_t1", camera: { fx: 800 }, T_camera_from_world: T, surface_opacity: 0.5 });
    expect("case_id" in body).toBe(false);
  });

  it("sends every layer, hidden ones and weights too, the T1 with the view's preset, and no case_id", () => {
    const layers = fusedLayers(rec({ results: [res(1, "plan_ct_on_t1"), res(2, "plan_fmri_on_t1")] }))!;
    layers[1].visible = false;          // CT off
    layers[2].weight = 0.25;            // fMRI lighter
    layers[0].weight = 7;               // clamped
    const body = fusedRequest({ ...view, preset: "surface_white", surfaceOpacity: 1.5 }, layers);
    expect(body.surface_opacity).toBe(1);
    expect("case_id" in body).toBe(false);
    expect(body.modalities).toEqual([
      { name: "t1", transfer_function: "surface_white", weight: 1, visible: true },
      { name: "ct", transfer_function: "ct_bone", weight: 0.7, visible: false },
      { name: "fmri", transfer_function: "fmri_hot", weight: 0.25, visible: true },
    ]);
    // Turning a layer back on changes only its entry.
    layers[1].visible = true;
    const again = fusedRequest({ ...view, preset: "surface_white" }, layers).modalities as { visible: boolean }[];
    expect(again.map((m) => m.visible)).toEqual([true, true, true]);
  });

  it("knows the CPU renderer's refusal (the view then shows the T1 alone)", () => {
    expect(layersNeedGl("fused modalities: multimodal views need the GL renderer (renderer.kind is cpu)")).toBe(true);
    expect(layersNeedGl("fused modalities[1].name: case 4 has no plan with a CT (upload one and run a plan job first)")).toBe(false);
  });
});
