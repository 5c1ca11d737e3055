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

/** Heights (metres; nm on the left axis) and the SEM signal (its own units, right axis)
 * along a profile, `null` where either does not reach. */
export function plotProfile(canvas, cut) {
  const ctx = canvas.getContext("2d");
  const { width, height } = canvas;
  ctx.clearRect(0, 0, width, height);
  ctx.font = "11px system-ui";
  const span = cut.distance[cut.distance.length - 1] || 1;
  const x = (d) => 36 + ((width - 72) * d) / span;
  const trace = (values, colour, side) => {
    const seen = values.filter((v) => v !== null);
    if (!seen.length) return;
    const lo = Math.min(...seen);
    const hi = Math.max(...seen);
    const y = (v) => height - 14 - ((height - 30) * (v - lo)) / Math.max(hi - lo, 1e-30);
    ctx.strokeStyle = colour;
    ctx.fillStyle = colour;
    ctx.beginPath();
    let pen = false;
    values.forEach((v, k) => {
      if (v === null) return void (pen = false);
      pen ? ctx.lineTo(x(cut.distance[k]), y(v)) : ctx.moveTo(x(cut.distance[k]), y(v));
      pen = true;
    });
    ctx.stroke();
    const label = (v) => (side === "left" ? (v * 1e9).toFixed(1) : v.toPrecision(3));
    const at = side === "left" ? 2 : width - 34;
    ctx.fillText(label(hi), at, 24);
    ctx.fillText(label(lo), at, height - 16);
  };
  trace(cut.height, "#c45500", "left");
  trace(cut.sem, "#3a6ea5", "right");
  ctx.fillStyle = "#666";
  ctx.fillText("height (nm)", 36, 12);
  ctx.fillText("SEM signal", width - 100, 12);
  ctx.fillText(`${(span * 1e9).toFixed(0)} nm along the line`, width / 2 - 50, height - 2);
}
