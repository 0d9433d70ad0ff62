// The fused view's free viewpoint: the registered camera turned about a pivot in front of it
// (as core's orbit_pose does: the scene rotated about the pivot in the camera frame, yaw about
// the camera's vertical axis, then pitch about its horizontal axis), and back ("Camera view").
export type Mat4 = number[][];

function mul(a: number[][], b: number[][]): number[][] {
  return a.map((row) => b[0].map((_, j) => row.reduce((s, x, k) => s + x * b[k][j], 0)));
}

/** `T` (T_camera_from_world, 4x4 rows) orbited by yaw/pitch degrees about the camera-frame point
 * (0, 0, pivotDepthMm): the pivot stays where it is in the picture's centre. */
export function orbitCamera(T: Mat4, yawDeg: number, pitchDeg: number, pivotDepthMm: number): Mat4 {
  const a = (yawDeg * Math.PI) / 180, b = (pitchDeg * Math.PI) / 180;
  const Ry = [[Math.cos(a), 0, Math.sin(a)], [0, 1, 0], [-Math.sin(a), 0, Math.cos(a)]];
  const Rx = [[1, 0, 0], [0, Math.cos(b), -Math.sin(b)], [0, Math.sin(b), Math.cos(b)]];
  const R = mul(Rx, Ry);
  const p = [0, 0, pivotDepthMm];
  const t = [0, 1, 2].map((i) => p[i] - (R[i][0] * p[0] + R[i][1] * p[1] + R[i][2] * p[2]));
  const M = [[...R[0], t[0]], [...R[1], t[1]], [...R[2], t[2]], [0, 0, 0, 1]];
  return mul(M, T);
}

/** Depth of the world point `p` (LPS mm) in the camera of `T`. */
export function depthOf(T: Mat4, p: number[]): number {
  return T[2][0] * p[0] + T[2][1] * p[1] + T[2][2] * p[2] + T[2][3];
}

/** `T` with the camera moved along its own axes: the scene shifted by (dxMm, dyMm) in the
 *  camera's x/y (right, down) and the camera dzMm closer along its view axis. */
export function translateCamera(T: Mat4, dxMm: number, dyMm: number, dzMm: number): Mat4 {
  return mul([[1, 0, 0, dxMm], [0, 1, 0, dyMm], [0, 0, 1, -dzMm], [0, 0, 0, 1]], T);
}

/** Pinch and two-finger pan: the fingers' distance grew by `scale` (clamped 0.25..4) and their
 *  midpoint moved (duPx, dvPx) view pixels. The point at `pivotDepthMm` in front of the camera
 *  looks `scale` times bigger (the camera comes to pivotDepthMm / scale from it) and follows the
 *  fingers (a pixel is depth / focalPx mm there). Returns the pose and the pivot's new depth. */
export function pinchPan(T: Mat4, scale: number, duPx: number, dvPx: number, pivotDepthMm: number, focalPx: number): { T: Mat4; pivotDepthMm: number } {
  const s = Math.min(4, Math.max(0.25, scale));
  const depth = Math.max(30, pivotDepthMm / s);
  const dz = pivotDepthMm - depth;
  return { T: translateCamera(T, (duPx * depth) / focalPx, (dvPx * depth) / focalPx, dz), pivotDepthMm: depth };
}
