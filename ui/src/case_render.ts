// The case view's renders of the case's own volumes (docs/api/render.md): case_id on every
// render and pick request, the multimodal layers (the case's T1 with its plan's CT / fMRI, each
// with its own transfer function, weight and on/off) and the intensity histogram drawn under
// the transfer-function editor (GET /api/cases/{id}/volumes/{vid}/histogram, in the transfer
// functions' normalised units). Pure functions (unit-tested) plus one small DOM widget, the
// modality tabs.
import { h } from "./dom";
import type { CaseRecord } from "./case_detail";
import type { TfJson } from "./tf_model";

export type ModalityName = "t1" | "ct" | "fmri";

/** The daemon's histogram answer (the parts the UI uses). */
export interface NormalizedHistogram {
  range: [number, number];
  outside: number[]; inside?: number[];
}
export interface VolumeHistogram {
  case_id: number; volume_id: number; bins: number;
  normalizations: { whole: NormalizedHistogram; brain_only: NormalizedHistogram | null };
}

/** One layer's look: a preset name or an edited transfer function, its weight (0..1), on/off. */
export interface ModalityLayer { name: ModalityName; preset: string; tf: TfJson | null; weight: number; visible: boolean }

export const MODALITY_LABEL: Record<ModalityName, string> = { t1: "T1", ct: "CT", fmri: "fMRI" };
const DEFAULT_PRESET: Record<ModalityName, string> = { t1: "cortex_t1", ct: "ct_bone", fmri: "fmri_hot" };
const PLAN_KIND: Record<Exclude<ModalityName, "t1">, string> = { ct: "plan_ct_on_t1", fmri: "plan_fmri_on_t1" };

/** The case's newest T1 (the volume its views render), or null. */
export function newestT1(c: CaseRecord): number | null {
  let id: number | null = null;
  for (const v of c.volumes ?? []) if (v.modality === "T1" && (id === null || v.id > id)) id = v.id;
  return id;
}

/** The modalities a multimodal view of the case can show: t1, and ct / fmri when a plan stored
 *  them (the plan job's resampled volumes). Only t1: no multimodal view. */
export function planModalities(c: CaseRecord): ModalityName[] {
  const kinds = new Set((c.results ?? []).map((r) => r.kind));
  const out: ModalityName[] = ["t1"];
  for (const m of ["ct", "fmri"] as const) if (kinds.has(PLAN_KIND[m])) out.push(m);
  return out;
}

export function defaultLayers(names: ModalityName[]): ModalityLayer[] {
  return names.map((name) => ({ name, preset: DEFAULT_PRESET[name], tf: null, weight: name === "t1" ? 1 : 0.7, visible: true }));
}

/** The case fields of a render / pick request: case_id, and with more than the T1 the
 *  `modalities` list (every layer, hidden ones too: hiding one then uploads nothing again).
 *  The T1 layer takes the view's own look (`t1Look`: its preset or edited tf). */
export function caseRenderFields(caseId: number, layers: ModalityLayer[], t1Look?: { preset: string; tf: TfJson | null }): Record<string, unknown> {
  const out: Record<string, unknown> = { case_id: caseId };
  if (layers.length < 2) return out;
  out.modalities = layers.map((l) => {
    const look = l.name === "t1" && t1Look ? t1Look : l;
    return { name: l.name, transfer_function: look.tf ?? look.preset, weight: Math.min(1, Math.max(0, l.weight)), visible: l.visible };
  });
  return out;
}

export function histogramPath(caseId: number, volumeId: number, bins = 128): string {
  return `/api/cases/${caseId}/volumes/${volumeId}/histogram?bins=${bins}`;
}

/** The histogram of a layer: the stored T1's, or the plan's CT / fMRI on the T1 grid. */
export function layerHistogramPath(caseId: number, layer: ModalityName, t1VolumeId: number | null, bins = 128): string | null {
  if (layer === "t1") return t1VolumeId === null ? null : histogramPath(caseId, t1VolumeId, bins);
  return `/api/cases/${caseId}/plan/${layer}/histogram?bins=${bins}`;
}

/** Bar heights 0..1 (log scale: a few bright voxels stay visible beside the background) of the
 *  histogram in the units the rendered transfer function uses: over the brain's range and
 *  inside its mask when the view is brain only (and the volume has a mask), else every voxel
 *  over the whole volume's range. */
export function histogramBars(hg: VolumeHistogram, brainOnly: boolean): number[] {
  const n = brainOnly && hg.normalizations.brain_only ? hg.normalizations.brain_only : hg.normalizations.whole;
  const counts = brainOnly && n.inside ? n.inside : n.outside.map((c, i) => c + (n.inside?.[i] ?? 0));
  const logs = counts.map((c) => Math.log1p(Math.max(0, c)));
  const max = Math.max(0, ...logs);
  return max > 0 ? logs.map((v) => v / max) : logs.map(() => 0);
}

/** Tabs to choose which modality the transfer-function editor edits, each with on/off and a
 *  weight slider (large touch targets). `onChange(final)` after every change. */
export class ModalityTabs {
  readonly el: HTMLElement;
  private active: ModalityName = "t1";
  constructor(readonly layers: ModalityLayer[], private readonly onSelect: (l: ModalityLayer) => void,
              private readonly onChange: (final: boolean) => void) {
    this.el = h("div", { class: "modality-tabs", "data-testid": "modality-tabs" });
    this.draw();
  }
  get selected(): ModalityLayer { return this.layers.find((l) => l.name === this.active) ?? this.layers[0]; }
  private draw(): void {
    const tabs = h("div", { class: "choices" }, ...this.layers.map((l) => h("button", {
      class: `btn${l.name === this.active ? " active" : ""}`, "data-value": l.name, "data-testid": `modality-${l.name}`,
      onclick: () => { this.active = l.name; this.draw(); this.onSelect(l); },
    }, `${MODALITY_LABEL[l.name]}${l.visible ? "" : " (off)"}`)));
    const l = this.selected;
    const onOff = h("button", { class: `btn${l.visible ? " active" : ""}`, "data-testid": "modality-visible" }, l.visible ? `${MODALITY_LABEL[l.name]} shown` : `${MODALITY_LABEL[l.name]} hidden`);
    onOff.addEventListener("click", () => { l.visible = !l.visible; this.draw(); this.onChange(true); });
    const out = h("span", { class: "value" }, `${Math.round(l.weight * 100)} %`);
    const weight = h("input", { type: "range", min: 0, max: 100, step: 5, value: Math.round(l.weight * 100), class: "slider", "data-testid": "modality-weight" }) as HTMLInputElement;
    weight.addEventListener("input", () => { l.weight = Number(weight.value) / 100; out.textContent = `${weight.value} %`; this.onChange(false); });
    weight.addEventListener("change", () => this.onChange(true));
    this.el.replaceChildren(tabs, h("div", { class: "choices" }, onOff), h("div", { class: "muted" }, "Weight ", out), weight);
  }
}
