// The small live plot of NMI against evaluations (registration jobs), drawn on a canvas.

export interface NmiPoint {
  evaluation: number;
  nmi: number;
}

export interface PlotScale {
  xMin: number;
  xMax: number;
  yMin: number;
  yMax: number;
  toX: (evaluation: number) => number;
  toY: (nmi: number) => number;
}

/** Maps evaluations to [pad, width-pad] and NMI to [height-pad, pad] (higher NMI is up).
 *  The NMI axis spans the data with 10 % margin, at least 0.01 wide, clamped to [1, 2]
 *  (NMI's range); the evaluation axis starts at 0 and spans at least 10. */
export function scalePlot(points: readonly NmiPoint[], width: number, height: number, pad = 8): PlotScale {
  const finite = points.filter((p) => Number.isFinite(p.evaluation) && Number.isFinite(p.nmi));
  let lo = Infinity, hi = -Infinity, xMax = 10;
  for (const p of finite) {
    lo = Math.min(lo, p.nmi);
    hi = Math.max(hi, p.nmi);
    xMax = Math.max(xMax, p.evaluation);
  }
  if (!finite.length) { lo = 1; hi = 1.1; }
  let span = hi - lo;
  const minSpan = 0.01;
  if (span < minSpan) {
    const mid = (hi + lo) / 2;
    lo = mid - minSpan / 2;
    hi = mid + minSpan / 2;
    span = minSpan;
  }
  let yMin = Math.max(1, lo - span * 0.1);
  let yMax = Math.min(2, hi + span * 0.1);
  if (yMax - yMin < minSpan) {
    if (yMin <= 1) yMax = yMin + minSpan; else yMin = yMax - minSpan;
  }
  const w = Math.max(1, width - 2 * pad), h = Math.max(1, height - 2 * pad);
  return {
    xMin: 0, xMax, yMin, yMax,
    toX: (e) => pad + (Math.min(Math.max(e, 0), xMax) / xMax) * w,
    toY: (n) => pad + (1 - (Math.min(Math.max(n, yMin), yMax) - yMin) / (yMax - yMin)) * h,
  };
}

/** Draws the points (line) and the best so far (second line) on a 2D context. */
export function drawNmiPlot(ctx: CanvasRenderingContext2D, points: readonly NmiPoint[], width: number, height: number): void {
  ctx.clearRect(0, 0, width, height);
  ctx.fillStyle = "#10161d";
  ctx.fillRect(0, 0, width, height);
  const s = scalePlot(points, width, height, 10);
  ctx.strokeStyle = "#2a3542";
  ctx.lineWidth = 1;
  ctx.strokeRect(10, 10, width - 20, height - 20);
  ctx.fillStyle = "#8fa3b8";
  ctx.font = "18px sans-serif";
  ctx.fillText(s.yMax.toFixed(3), 16, 32);
  ctx.fillText(s.yMin.toFixed(3), 16, height - 18);
  ctx.textAlign = "right";
  ctx.fillText(`${s.xMax} evaluations`, width - 16, height - 18);
  ctx.textAlign = "left";
  if (!points.length) return;
  const line = (ys: number[], colour: string, lw: number) => {
    ctx.strokeStyle = colour;
    ctx.lineWidth = lw;
    ctx.beginPath();
    points.forEach((p, i) => {
      const x = s.toX(p.evaluation), y = s.toY(ys[i]);
      if (i === 0) ctx.moveTo(x, y); else ctx.lineTo(x, y);
    });
    ctx.stroke();
  };
  line(points.map((p) => p.nmi), "#4fa3ff", 1.5);
  let best = -Infinity;
  line(points.map((p) => (best = Math.max(best, p.nmi))), "#ffcf4a", 2.5);
}
