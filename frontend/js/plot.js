// The merge panel's small plot: the residual of every iteration.

/** Residual (metres) per iteration as a line, labelled in nm. */
export function plotResiduals(canvas, residuals) {
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.fillStyle = "#666";
  ctx.font = "11px system-ui";
  ctx.fillText("residual per iteration (nm)", 6, 12);
  const r = residuals;
  if (r.length < 1) return;
  const hi = Math.max(...r.map((p) => p[1]));
  const lo = Math.min(...r.map((p) => p[1]));
  const n = Math.max(...r.map((p) => p[0]));
  const x = (i) => 30 + ((canvas.width - 40) * i) / Math.max(n, 1);
  const y = (v) => canvas.height - 12 - ((canvas.height - 30) * (v - lo)) / Math.max(hi - lo, 1e-12);
  ctx.strokeStyle = "#c45500";
  ctx.beginPath();
  r.forEach(([i, v], k) => (k ? ctx.lineTo(x(i), y(v)) : ctx.moveTo(x(i), y(v))));
  ctx.stroke();
  ctx.fillText(`${(hi * 1e9).toFixed(2)}`, 2, 24);
  ctx.fillText(`${(lo * 1e9).toFixed(2)}`, 2, canvas.height - 4);
}
