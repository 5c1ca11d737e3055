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

/** The stored patch's thumbnail in its cell; `act` reports a failure on the page. */
export function showPatch(grid, runId, index, act) {
  const cell = grid.querySelector(`[data-index="${index}"]`);
  if (!cell || cell.tagName === "IMG") return;
  const img = document.createElement("img");
  img.alt = `patch ${index}`;
  img.dataset.index = index;
  cell.replaceWith(img);
  act(async () => {
    const response = await fetch(`/api/runs/${runId}/patches/${index}/preview.png?size=96&bare=true`);
    if (!response.ok) throw new Error(`patch ${index}: preview not available (HTTP ${response.status})`);
    const [lo, hi] = (response.headers.get("X-Height-Range") || "0,0").split(",").map(Number);
    img.src = URL.createObjectURL(await response.blob());
    img.title = img.alt = `patch ${index}: ${lo.toFixed(0)} … ${hi.toFixed(0)} nm (dark … bright)`;
  });
}
