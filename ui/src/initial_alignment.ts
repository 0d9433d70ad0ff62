// The landmarks' initial alignment on Photo & marks (issue 7, 7.19): the pose the register job
// starts from, computed by the daemon from the pairs as they are on the screen (saved or not:
// POST /api/cases/{id}/landmarks/initial-pose, docs/api/case-data.md "Initial alignment"),
// each pair's reprojection error in px and the RMS. No DOM here: unit-tested.
import { apiJson, plainMessage, type FetchLike } from "./api";

export type Px = [number, number];
export interface PairIn { name: string; world_mm: number[]; pixel: Px }
export interface AlignedPair { label: string; world_mm: number[]; pixel: Px; projected_pixel: Px | null; error_px: number | null }
/** The daemon's answer. */
export interface Alignment {
  case_id: number;
  photo_id: number;
  method: string;
  T_camera_from_world: number[][];
  rms_px: number;
  max_error_px: number;
  /** The pairs' spread (0 on a line, 1 a round cloud) and, when they lie nearly on a line, why
   *  that matters in words (core's landmark_spread_warning; "" when well spread). */
  spread?: { world: number; pixel: number };
  warning?: string;
  inliers: number[];
  pairs: AlignedPair[];
}

/** The fewest pairs a pose can be fitted from (core's fit_pose_pnp and validate_landmarks). */
export const MIN_PAIRS = 4;

/** An error is "high" (drawn in the warning colour) above this many px: a mislabelled or
 *  misplaced twin, not picking noise (core's RANSAC threshold is 1.5 % of the width, >= 4 px). */
export function highErrorPx(photoWidthPx: number): number {
  return Math.max(4, 0.015 * photoWidthPx);
}

/** The request body for the pairs on the screen. */
export function alignmentBody(pairs: PairIn[], photoId: number): { landmarks: { label: string; world_mm: number[]; pixel: Px }[]; photo_id: number } {
  return { landmarks: pairs.map((p) => ({ label: p.name, world_mm: p.world_mm, pixel: p.pixel })), photo_id: photoId };
}

/** The line under the pairs: the RMS and the worst pair, or why there is no alignment yet. */
export function alignmentHeadline(a: Alignment | null, pairCount: number, error: string): string {
  if (pairCount < MIN_PAIRS) return `Initial alignment: needs at least ${MIN_PAIRS} pairs (${pairCount} now).`;
  if (error) return `Initial alignment: not possible with these pairs: ${error}`;
  if (!a) return "Initial alignment: computing…";
  let worst = -1;
  a.pairs.forEach((p, i) => { if (p.error_px !== null && (worst < 0 || p.error_px > (a.pairs[worst].error_px ?? 0))) worst = i; });
  const w = worst >= 0 ? `, worst ${a.pairs[worst].label} ${a.pairs[worst].error_px!.toFixed(1)} px` : "";
  const line = `Initial alignment from ${a.pairs.length} pairs: reprojection RMS ${a.rms_px.toFixed(2)} px${w} (${a.method}).`;
  return a.warning ? `${line} Warning: ${a.warning}.` : line;
}

/** One pair's error in words for its row ("2.3 px", "—" while none). */
export function pairErrorText(a: Alignment | null, index: number): string {
  const e = a?.pairs[index]?.error_px;
  return e === null || e === undefined ? "— px" : `${e.toFixed(1)} px`;
}

/**
 * Asks the daemon for the alignment of the pairs as they are now, after each change. Only the
 * answer to the newest request is taken (an older one that arrives late is dropped), so a quick
 * series of edits never shows the alignment of pairs that are no longer on the screen.
 */
export class AlignmentFetcher {
  private seq = 0;
  alignment: Alignment | null = null;
  error = "";
  pairCount = 0;
  constructor(
    private readonly caseId: number,
    private readonly onChange: () => void,
    private readonly fetchImpl: FetchLike = fetch,
  ) {}

  /** Requests the alignment of `pairs` (fewer than MIN_PAIRS: none, no request). Resolves when
   *  this request's answer (or refusal) was taken or dropped as stale. */
  async update(pairs: PairIn[], photoId: number): Promise<void> {
    const my = ++this.seq;
    this.pairCount = pairs.length;
    this.alignment = null;
    this.error = "";
    this.onChange();
    if (pairs.length < MIN_PAIRS) return;
    try {
      const a = await apiJson<Alignment>("POST", `/api/cases/${this.caseId}/landmarks/initial-pose`, alignmentBody(pairs, photoId), this.fetchImpl);
      if (my !== this.seq) return;
      this.alignment = a;
    } catch (e) {
      if (my !== this.seq) return;
      this.error = plainMessage(e);
    }
    this.onChange();
  }
}
