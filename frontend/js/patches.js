// The patches panel: a thumbnail per stored patch, placed where it lies in the grid.

/** Empty cells for every patch, rows bottom to top as on the stage. */
export function buildPatchGrid(grid, run) {
  grid.replaceChildren();
  grid.style.gridTemplateColumns = `repeat(${run.cols}, 1fr)`;
  const cells = new Map();
  for (let r = run.rows - 1; r >= 0; r--) {
    for (let c = 0; c < run.cols; c++) {
      const cell = document.createElement("div");
      cell.className = "empty";
      grid.append(cell);
      cells.set(`${r},${c}`, cell);
    }
  }
  for (const p of run.patches) {
    const cell = cells.get(`${p.row},${p.col}`);
    if (cell) cell.dataset.index = p.index;
  }
}

/** The stored patch's thumbnail in its cell (again, with `fresh`: a re-scan); `act` reports a
 * failure on the page. */
export function showPatch(grid, runId, index, act, fresh = false) {
  const cell = grid.querySelector(`[data-index="${index}"]`);
  if (!cell || (cell.tagName === "IMG" && !fresh)) return;
  let img = cell;
  if (cell.tagName !== "IMG") {
    img = document.createElement("img");
    img.alt = `patch ${index}`;
    img.dataset.index = index;
    if (cell.dataset.quality) img.dataset.quality = cell.dataset.quality;
    cell.replaceWith(img);
  }
  act(async () => {
    const response = await fetch(`/api/runs/${runId}/patches/${index}/preview.png?size=96&bare=true`);
    if (!response.ok) throw new Error(`patch ${index}: preview not available (HTTP ${response.status})`);
    const [lo, hi] = (response.headers.get("X-Height-Range") || "0,0").split(",").map(Number);
    img.src = URL.createObjectURL(await response.blob());
    img.alt = `patch ${index}: ${lo.toFixed(0)} … ${hi.toFixed(0)} nm (dark … bright)`;
    img.title = img.dataset.reason ? `${img.alt}; ${img.dataset.reason}` : img.alt;
  });
}

const QUALITY_WORDS = { ok: "passed the quality gate", rescanned: "re-scanned", failed: "failed the quality gate", flagged: "flagged: left out of the mosaic" };

/** The quality gate's word on a patch: a coloured frame, and why in its title. */
export function markQuality(grid, index, quality, reason) {
  const cell = grid.querySelector(`[data-index="${index}"]`);
  if (!cell || !quality) return;
  if (quality === "ok" && cell.dataset.quality === "rescanned") return; // its history stays
  cell.dataset.quality = quality;
  cell.dataset.reason = reason ? `${QUALITY_WORDS[quality]}: ${reason}` : QUALITY_WORDS[quality];
  cell.title = `patch ${index}: ${cell.dataset.reason}`;
}
