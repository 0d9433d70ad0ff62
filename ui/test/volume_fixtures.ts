// Synthetic files the UI reads (a NIfTI mask, a PLY surface), shared by the unit tests.

/** A NIfTI-1 file: n^3 uint8 voxels, 1 = inside a ball of radius r voxels round the centre;
 *  qform: identity rotation, offset (ox, oy, oz) RAS, spacing s mm. */
export function ballNifti(n: number, r: number, s: number, o: [number, number, number], qform = true): ArrayBuffer {
  const buf = new ArrayBuffer(352 + n * n * n);
  const v = new DataView(buf);
  v.setInt32(0, 348, true);
  [3, n, n, n, 1, 1, 1, 1].forEach((d, i) => v.setInt16(40 + 2 * i, d, true));
  v.setInt16(70, 2, true); v.setInt16(72, 8, true);
  [1, s, s, s].forEach((p, i) => v.setFloat32(76 + 4 * i, p, true));
  v.setFloat32(108, 352, true);
  if (qform) {
    v.setInt16(252, 1, true);
    o.forEach((x, i) => v.setFloat32(268 + 4 * i, x, true));
  } else {
    v.setInt16(254, 1, true);
    [[s, 0, 0, o[0]], [0, s, 0, o[1]], [0, 0, s, o[2]]].forEach((row, r) => row.forEach((x, k) => v.setFloat32(280 + 16 * r + 4 * k, x, true)));
  }
  const c = (n - 1) / 2;
  const d = new Uint8Array(buf, 352);
  for (let k = 0; k < n; k++) for (let j = 0; j < n; j++) for (let i = 0; i < n; i++)
    d[i + n * (j + n * k)] = Math.hypot(i - c, j - c, k - c) <= r ? 1 : 0;
  return buf;
}

/** A UV sphere of radius r about c (world = voxel indices here). */
export function sphere(c: number[], r: number, nu = 48, nv = 24): { v: number[][]; f: number[][] } {
  const v: number[][] = [], f: number[][] = [];
  for (let a = 0; a <= nv; a++) for (let b = 0; b < nu; b++) {
    const th = (Math.PI * a) / nv, ph = (2 * Math.PI * b) / nu;
    v.push([c[0] + r * Math.sin(th) * Math.cos(ph), c[1] + r * Math.sin(th) * Math.sin(ph), c[2] + r * Math.cos(th)]);
  }
  for (let a = 0; a < nv; a++) for (let b = 0; b < nu; b++) {
    const i = a * nu + b, j = a * nu + (b + 1) % nu;
    f.push([i, j, j + nu, i + nu]); // quads: the reader fans them into triangles
  }
  return { v, f };
}

/** Binary little-endian PLY as VTK writes it (float xyz, float normals, uchar/int lists). */
export function binaryPly(s: { v: number[][]; f: number[][] }, cut = 0): ArrayBuffer {
  const head = `ply\nformat binary_little_endian 1.0\ncomment SPACE=LPS\nelement vertex ${s.v.length}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face ${s.f.length}\nproperty list uchar int vertex_indices\nend_header\n`;
  const hb = new TextEncoder().encode(head);
  const size = hb.length + s.v.length * 24 + s.f.reduce((t, f) => t + 1 + 4 * f.length, 0);
  const buf = new ArrayBuffer(size), dv = new DataView(buf);
  new Uint8Array(buf).set(hb);
  let o = hb.length;
  for (const p of s.v) { for (const x of [...p, 0, 0, 1]) { dv.setFloat32(o, x, true); o += 4; } }
  for (const f of s.f) { dv.setUint8(o++, f.length); for (const i of f) { dv.setInt32(o, i, true); o += 4; } }
  return cut ? buf.slice(0, size - cut) : buf;
}
