// The fused view's modalities (issue 4/7, docs/ui.md "Fused view"): the photo on the brain
// surface over the multimodal volume rendering, with the T1 and the plan's CT / fMRI each on or
// off and weighted. The layer model is the transfer-function editor's (case_render.ts
// ModalityLayer, defaultLayers, planModalities); POST /api/cases/{id}/fused takes the same
// `modalities` list as POST /api/render (docs/api/render.md). Pure request building (unit-tested)
// plus one small DOM widget.
import { h } from "./dom";
import type { CaseRecord } from "./case_detail";
import { caseRenderFields, defaultLayers, MODALITY_LABEL, planModalities, type ModalityLayer } from "./case_render";

/** The layers the fused view offers: the T1 and the CT / fMRI the case's plan stored; null when
 *  the plan has only the T1 (then no toggles and no `modalities`: the plain fused view). */
export function fusedLayers(c: CaseRecord): ModalityLayer[] | null {
  const names = planModalities(c);
  return names.length > 1 ? defaultLayers(names) : null;
}

/** The `modalities` field of a fused request: every layer, hidden ones too (turning one off
 *  then uploads nothing again), the T1 with the view's preset; {} without layers. The fused
 *  endpoint takes the case from its path, so no case_id. */
export function fusedModalityFields(layers: ModalityLayer[] | null, t1Preset: string): { modalities?: unknown[] } {
  if (!layers) return {};
  const f = caseRenderFields(0, layers, { preset: t1Preset, tf: null });
  return f.modalities ? { modalities: f.modalities as unknown[] } : {};
}

/** The whole body of POST /api/cases/{id}/fused for a view. */
export function fusedRequest(view: { width: number; height: number; preset: string; camera: unknown; T_camera_from_world: number[][]; surfaceOpacity: number },
                             layers: ModalityLayer[] | null): Record<string, unknown> {
  return {
    width: view.width, height: view.height, preset: view.preset, camera: view.camera, T_camera_from_world: view.T_camera_from_world,
    surface_opacity: Math.min(1, Math.max(0, view.surfaceOpacity)), ...fusedModalityFields(layers, view.preset),
  };
}

/** A refusal that means "this daemon cannot draw the layers" (the CPU renderer): 409 naming the
 *  GL renderer. The view then shows the T1 alone and says why. */
export function layersNeedGl(message: string): boolean {
  return /need the GL renderer/.test(message);
}

/** One row per layer: a big on/off button and a weight slider (48 px touch targets, style.css
 *  .btn / .slider). `onChange(final)`: false while a slider moves, true when it is let go or a
 *  button is tapped (render then). */
export class FusedModalityPanel {
  readonly el: HTMLElement;
  constructor(readonly layers: ModalityLayer[], private readonly onChange: (final: boolean) => void) {
    this.el = h("div", { class: "fused-modalities", "data-testid": "fused-modalities" });
    this.draw();
  }
  private draw(): void {
    this.el.replaceChildren(...this.layers.map((l) => {
      const label = MODALITY_LABEL[l.name];
      const onOff = h("button", { class: `btn${l.visible ? " active" : ""}`, type: "button", "data-testid": `fused-modality-${l.name}`,
        "data-visible": String(l.visible), "aria-pressed": String(l.visible) }, l.visible ? `${label}: on` : `${label}: off`);
      onOff.addEventListener("click", () => { l.visible = !l.visible; this.draw(); this.onChange(true); });
      const out = h("span", { class: "value" }, `${Math.round(l.weight * 100)} %`);
      const weight = h("input", { type: "range", min: 0, max: 100, step: 5, value: Math.round(l.weight * 100), class: "slider",
        "data-testid": `fused-weight-${l.name}`, "aria-label": `${label} weight`, disabled: !l.visible }) as HTMLInputElement;
      weight.addEventListener("input", () => { l.weight = Number(weight.value) / 100; out.textContent = `${weight.value} %`; this.onChange(false); });
      weight.addEventListener("change", () => this.onChange(true));
      return h("div", { class: "fused-modality", "data-name": l.name }, h("div", { class: "choices" }, onOff, h("span", { class: "muted" }, "Weight ", out)), weight);
    }));
  }
}
