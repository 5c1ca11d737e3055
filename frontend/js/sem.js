// The SEM panel: the image on a canvas, zoom and pan, an ROI drawn with the mouse, the
// planned grid drawn over it (snake order and overlaps), coordinates in the stage frame.

export class SemView {
  /**
   * @param {HTMLCanvasElement} canvas
   * @param {HTMLElement} coords where the stage coordinates under the mouse are written
   * @param {(roi: object|null) => void} onRoi called with {col,row,width,height} in pixels
   */
  constructor(canvas, coords, onRoi) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.coords = coords;
    this.onRoi = onRoi;
    this.image = null; // {bitmap, meta}
    this.scale = 1;
    this.offset = { x: 0, y: 0 }; // canvas position of image pixel (0, 0)
    this.roi = null;
    this.drag = null;
    this.plan = null;
    this.loads = 0; // images asked for so far: only the newest one is shown
    canvas.addEventListener("mousedown", (e) => this.down(e));
    canvas.addEventListener("mousemove", (e) => this.move(e));
    window.addEventListener("mouseup", (e) => this.up(e));
    canvas.addEventListener("wheel", (e) => this.wheel(e), { passive: false });
    canvas.addEventListener("keydown", (e) => this.key(e));
  }

  /** A place in line for an image about to be asked for: an image claimed later wins. */
  claim() {
    return ++this.loads;
  }

  async load(meta, ticket = this.claim()) {
    const response = await fetch(`/api/sem/${meta.id}/image.png`);
    const blob = await response.blob();
    const bitmap = await createImageBitmap(blob);
    // an image asked for later (the operator acquired one while this one loaded) wins, and
    // keeps the ROI drawn on it
    if (ticket !== this.loads) return;
    this.image = { bitmap, meta };
    this.canvas.dataset.semId = meta.id;
    this.roi = null;
    this.plan = null;
    this.fit();
    this.onRoi(null);
  }

  fit() {
    if (!this.image) return;
    const { width, height } = this.image.meta;
    this.scale = Math.min(this.canvas.width / width, this.canvas.height / height);
    this.offset = {
      x: (this.canvas.width - width * this.scale) / 2,
      y: (this.canvas.height - height * this.scale) / 2,
    };
    this.draw();
  }

  // image pixel <-> canvas <-> stage
  toPixel(e) {
    const r = this.canvas.getBoundingClientRect();
    const cx = ((e.clientX - r.left) * this.canvas.width) / r.width;
    const cy = ((e.clientY - r.top) * this.canvas.height) / r.height;
    return { col: (cx - this.offset.x) / this.scale, row: (cy - this.offset.y) / this.scale };
  }

  // through the image's affine map: stage = origin + matrix @ (col, row)
  toStage(col, row) {
    const { origin, matrix: [[a, b], [c, d]] } = this.image.meta;
    return { x: origin[0] + a * col + b * row, y: origin[1] + c * col + d * row };
  }

  fromStage(x, y) {
    const { origin, matrix: [[a, b], [c, d]] } = this.image.meta;
    const u = x - origin[0];
    const v = y - origin[1];
    const det = a * d - b * c;
    return { col: (d * u - b * v) / det, row: (a * v - c * u) / det };
  }

  clamp(p) {
    const { width, height } = this.image.meta;
    return { col: Math.min(Math.max(p.col, 0), width), row: Math.min(Math.max(p.row, 0), height) };
  }

  down(e) {
    if (!this.image) return;
    this.canvas.focus();
    if (e.shiftKey || e.button === 1) {
      this.drag = { pan: true, x: e.clientX, y: e.clientY, offset: { ...this.offset } };
    } else if (e.button === 0) {
      this.drag = { pan: false, start: this.clamp(this.toPixel(e)) };
    }
    e.preventDefault();
  }

  move(e) {
    if (!this.image) return;
    const p = this.toPixel(e);
    const s = this.toStage(p.col, p.row);
    this.coords.textContent = `x ${(s.x * 1e6).toFixed(3)} µm, y ${(s.y * 1e6).toFixed(3)} µm`;
    if (!this.drag) return;
    if (this.drag.pan) {
      const r = this.canvas.getBoundingClientRect();
      const k = this.canvas.width / r.width;
      this.offset = {
        x: this.drag.offset.x + (e.clientX - this.drag.x) * k,
        y: this.drag.offset.y + (e.clientY - this.drag.y) * k,
      };
    } else {
      const q = this.clamp(p);
      const a = this.drag.start;
      this.drag.rect = {
        col: Math.min(a.col, q.col),
        row: Math.min(a.row, q.row),
        width: Math.abs(q.col - a.col),
        height: Math.abs(q.row - a.row),
      };
    }
    this.draw();
  }

  up() {
    if (!this.drag) return;
    const rect = this.drag.rect;
    const drew = !this.drag.pan;
    this.drag = null;
    if (drew && rect && rect.width >= 2 && rect.height >= 2) {
      this.roi = rect;
      this.plan = null;
      this.onRoi(rect);
    }
    this.draw();
  }

  key(e) {
    if (!this.image) return;
    const step = 40;
    const moves = { ArrowLeft: [step, 0], ArrowRight: [-step, 0], ArrowUp: [0, step], ArrowDown: [0, -step] };
    if (e.key === "Escape") {
      this.drag = null;
      this.roi = null;
      this.plan = null;
      this.onRoi(null);
    } else if (e.key === "+" || e.key === "=") {
      this.zoomAt(this.canvas.width / 2, this.canvas.height / 2, 1.25);
    } else if (e.key === "-") {
      this.zoomAt(this.canvas.width / 2, this.canvas.height / 2, 0.8);
    } else if (e.key === "0") {
      this.fit();
    } else if (moves[e.key]) {
      this.offset.x += moves[e.key][0];
      this.offset.y += moves[e.key][1];
    } else {
      return;
    }
    e.preventDefault();
    this.draw();
  }

  wheel(e) {
    if (!this.image) return;
    e.preventDefault();
    const r = this.canvas.getBoundingClientRect();
    const cx = ((e.clientX - r.left) * this.canvas.width) / r.width;
    const cy = ((e.clientY - r.top) * this.canvas.height) / r.height;
    this.zoomAt(cx, cy, e.deltaY < 0 ? 1.2 : 1 / 1.2);
  }

  zoomAt(cx, cy, factor) {
    const scale = Math.min(Math.max(this.scale * factor, 0.05), 64);
    const f = scale / this.scale;
    this.offset = { x: cx - (cx - this.offset.x) * f, y: cy - (cy - this.offset.y) * f };
    this.scale = scale;
    this.draw();
  }

  setPlan(plan) {
    this.plan = plan;
    this.draw();
  }

  pointToCanvas(col, row) {
    return [this.offset.x + col * this.scale, this.offset.y + row * this.scale];
  }

  rectToCanvas(col, row, width, height) {
    return [this.offset.x + col * this.scale, this.offset.y + row * this.scale, width * this.scale, height * this.scale];
  }

  draw() {
    const { ctx, canvas } = this;
    ctx.fillStyle = "#111";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    if (!this.image) {
      ctx.fillStyle = "#aaa";
      ctx.font = "16px system-ui";
      ctx.fillText("Acquire or upload an SEM image", 20, 30);
      return;
    }
    const { bitmap, meta } = this.image;
    ctx.imageSmoothingEnabled = this.scale < 2;
    ctx.drawImage(bitmap, this.offset.x, this.offset.y, meta.width * this.scale, meta.height * this.scale);
    if (this.plan) this.drawPlan();
    const rect = (this.drag && this.drag.rect) || this.roi;
    if (rect) {
      ctx.strokeStyle = "#ffd000";
      ctx.lineWidth = 2;
      ctx.setLineDash([6, 4]);
      ctx.strokeRect(...this.rectToCanvas(rect.col, rect.row, rect.width, rect.height));
      ctx.setLineDash([]);
    }
  }

  drawPlan() {
    const { ctx } = this;
    const plan = this.plan;
    const centres = [];
    ctx.lineWidth = 1;
    for (const p of plan.patches) {
      // a patch is a stage-aligned rectangle: on a rotated image, a turned one
      const [x0, y0] = p.origin;
      const corners = [
        [x0, y0],
        [x0 + plan.patchWidth, y0],
        [x0 + plan.patchWidth, y0 + plan.patchHeight],
        [x0, y0 + plan.patchHeight],
      ].map(([x, y]) => {
        const q = this.fromStage(x, y);
        return this.pointToCanvas(q.col, q.row);
      });
      ctx.beginPath();
      corners.forEach(([cx, cy], i) => (i ? ctx.lineTo(cx, cy) : ctx.moveTo(cx, cy)));
      ctx.closePath();
      ctx.fillStyle = "rgba(60, 170, 255, 0.12)"; // overlaps add up to darker blue
      ctx.fill();
      ctx.strokeStyle = "rgba(60, 170, 255, 0.9)";
      ctx.stroke();
      const cx = corners.reduce((t, [x]) => t + x, 0) / 4;
      const cy = corners.reduce((t, [, y]) => t + y, 0) / 4;
      centres.push([cx, cy, p.index]);
    }
    ctx.strokeStyle = "#ff5a36"; // the snake: acquisition order
    ctx.beginPath();
    centres.forEach(([x, y], i) => (i ? ctx.lineTo(x, y) : ctx.moveTo(x, y)));
    ctx.stroke();
    ctx.fillStyle = "#fff";
    ctx.font = "11px system-ui";
    for (const [x, y, i] of centres) ctx.fillText(String(i), x - 4, y + 4);
  }
}
