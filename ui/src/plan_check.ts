// The Preoperative quick check's arithmetic, without the DOM (issue 7, 7.6a/b, 7.34): the plan's
// brain mask (NIfTI, 256^3 for the bundled MRI) read, three slices through its centroid, and the
// plan's surface (PLY) cut by the same slices. Run in a Web Worker by plan_screen.ts
// (off_thread.ts): on the page's main thread the parse and the loops were one task of ~340 ms
// (ui_e2e_resilience), long enough to freeze the screen.
import { gunzipIfNeeded, parseNifti, type Volume } from "./nifti";
import { parsePly, surfaceOutline, type Seg } from "./surface_outline";

export interface MaskCheck { width: number; height: number; grey: Uint8ClampedArray; centroid: [number, number, number]; voxels: number }

/** Three orthogonal slices (axial, coronal, sagittal in voxel index order) through the mask's
 *  centroid, side by side, as 8-bit grey (255 inside). `n`: each slice's side in the output
 *  (nearest neighbour). Null for an empty mask. */
export function maskQuickCheck(vol: Volume, n = 160): MaskCheck | null {
  const [X, Y, Z] = vol.dims;
  let sx = 0, sy = 0, sz = 0, cnt = 0;
  for (let k = 0; k < Z; k++) for (let j = 0; j < Y; j++) for (let i = 0; i < X; i++)
    if (vol.data[i + X * (j + Y * k)] > 0) { sx += i; sy += j; sz += k; cnt++; }
  if (!cnt) return null;
  const c: [number, number, number] = [Math.round(sx / cnt), Math.round(sy / cnt), Math.round(sz / cnt)];
  const grey = new Uint8ClampedArray(3 * n * n);
  const at = (i: number, j: number, k: number) => (vol.data[i + X * (j + Y * k)] > 0 ? 255 : 0);
  // Panel p: (u, v) over the two axes other than its normal; v flipped so superior/anterior is up.
  const panels: ((u: number, v: number) => number)[] = [
    (u, v) => at(Math.floor(u * X), Math.floor((1 - v) * Y), c[2]) , // axial: i across, j up
    (u, v) => at(Math.floor(u * X), c[1], Math.floor((1 - v) * Z)), // coronal: i across, k up
    (u, v) => at(c[0], Math.floor(u * Y), Math.floor((1 - v) * Z)), // sagittal: j across, k up
  ];
  for (let p = 0; p < 3; p++)
    for (let r = 0; r < n; r++)
      for (let q = 0; q < n; q++) grey[r * 3 * n + p * n + q] = panels[p]((q + 0.5) / n, (r + 0.5) / n);
  return { width: 3 * n, height: n, grey, centroid: c, voxels: cnt };
}

export interface PlanCheck {
  dims: [number, number, number];
  spacing: [number, number, number];
  mask: MaskCheck | null;
  /** The surface's cut (when a PLY was given and the mask is not empty). */
  surface?: { triangles: number; panels: Seg[][]; inMask: number };
  /** Why the surface could not be drawn (the mask picture is still good). */
  surfaceError?: string;
}

/** The whole check from the stored files' bytes (the mask gzipped or not). Throws naming the
 *  mask when it cannot be read; a bad surface is reported in `surfaceError`. */
export async function planCheck(maskBytes: ArrayBuffer, maskName: string, plyBytes: ArrayBuffer | null, plyName: string): Promise<PlanCheck> {
  const vol = parseNifti(await gunzipIfNeeded(maskBytes), maskName);
  const mask = maskQuickCheck(vol);
  const out: PlanCheck = { dims: vol.dims, spacing: vol.spacing, mask };
  if (mask && plyBytes) {
    try {
      const mesh = parsePly(plyBytes, plyName);
      const o = surfaceOutline(mesh, vol, mask.centroid);
      out.surface = { triangles: mesh.faces.length / 3, panels: o.panels, inMask: o.inMask };
    } catch (e) {
      out.surfaceError = e instanceof Error ? e.message : String(e);
    }
  }
  return out;
}
