import { describe, expect, it } from "vitest";
import { parsePly, surfaceOutline, type Mesh } from "../src/surface_outline";
import type { Volume } from "../src/nifti";
import { binaryPly, sphere } from "./volume_fixtures";

const I4 = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];
function ballMask(c: number[], r: number, n = 40): Volume {
  const data = new Uint8Array(n * n * n);
  for (let k = 0; k < n; k++) for (let j = 0; j < n; j++) for (let i = 0; i < n; i++)
    data[i + n * (j + n * k)] = Math.hypot(i - c[0], j - c[1], k - c[2]) <= r ? 1 : 0;
  return { dims: [n, n, n], spacing: [1, 1, 1], data, ijkToLps: I4, lpsToIjk: I4 };
}

describe("surface outline on the mask check", () => {
  const s = sphere([20, 20, 20], 10);
  it("reads the binary and the ASCII PLY alike, and refuses a cut one", () => {
    const m = parsePly(binaryPly(s), "brain_surface.ply");
    expect(m.vertices.length).toBe(3 * s.v.length);
    expect(m.faces.length).toBe(3 * 2 * s.f.length);
    expect(m.vertices[3 * 5 + 2]).toBeCloseTo(s.v[5][2], 4);
    const ascii = `ply\nformat ascii 1.0\nelement vertex ${s.v.length}\nproperty float x\nproperty float y\nproperty float z\nelement face ${s.f.length}\nproperty list uchar int vertex_indices\nend_header\n` +
      s.v.map((p) => p.join(" ")).join("\n") + "\n" + s.f.map((f) => `${f.length} ${f.join(" ")}`).join("\n") + "\n";
    const a = parsePly(new TextEncoder().encode(ascii).buffer as ArrayBuffer);
    expect(Array.from(a.faces)).toEqual(Array.from(m.faces));
    expect(() => parsePly(binaryPly(s, 7), "brain_surface.ply")).toThrow(/brain_surface.ply: PLY cut short/);
    expect(() => parsePly(new TextEncoder().encode("solid stl\n").buffer as ArrayBuffer, "x.stl")).toThrow(/x.stl: not a PLY file/);
  });

  it("cuts the surface by the three slices and tells a surface inside its mask from one beside it", () => {
    const mesh: Mesh = parsePly(binaryPly(s));
    const mask = ballMask([20, 20, 20], 10);
    const o = surfaceOutline(mesh, mask, [20, 20, 20]);
    for (const panel of o.panels) {
      expect(panel.length).toBeGreaterThan(40);
      // Every endpoint on the circle of radius 10 about the centre (panel units back to voxels).
      for (const [u1, v1] of panel) expect(Math.hypot(u1 * 40 - 0.5 - 20, (1 - v1) * 40 - 0.5 - 20)).toBeGreaterThan(9.7);
      for (const [u1, v1] of panel) expect(Math.hypot(u1 * 40 - 0.5 - 20, (1 - v1) * 40 - 0.5 - 20)).toBeLessThan(10.01);
    }
    expect(o.inMask).toBeGreaterThan(0.99);
    expect(o.lengthVox).toBeGreaterThan(3 * 2 * Math.PI * 10 * 0.95);
    // A surface 6 voxels beside its mask: about half of its outline out of the mask (by the
    // geometry of two circles of radius 10, 6 apart, with 2 voxels of slack: 52 %).
    const shifted = parsePly(binaryPly(sphere([26, 20, 20], 10)));
    expect(surfaceOutline(shifted, mask, [20, 20, 20]).inMask).toBeLessThan(0.75);
  });
});
