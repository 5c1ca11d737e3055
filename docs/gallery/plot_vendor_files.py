"""
Scans from an AFM's own files, merged and exported
==================================================

AFM users have folders of vendor files, each placed by the scan offset its file carries.
Here nine overlapping tiles are written as Gwyddion ``.gwy`` files (as Gwyddion itself would
place them), read back as a patch set by :func:`merge.read_scans`, merged, and the mosaic
exported as ``.gwy`` and 32-bit TIFF, the formats Gwyddion and image tools open.
"""

import tempfile
from pathlib import Path

import matplotlib.pyplot as plt

import merge
from hardware.sim.surfaces import surface_by_name
from hardware.sim.synth import synthesize
from merge.io.formats import export_heights, read_image
from merge.report import verdict

folder = Path(tempfile.mkdtemp(prefix="mosaic-gwy-"))
tiles = synthesize(
    surface_by_name("chessboard", seed=2),
    rows=3,
    cols=3,
    patch_size=(1.2e-6, 1.2e-6),
    pixels=(64, 64),
    overlap=(0.3, 0.3),
    seed=2,
)
for tile in tiles:
    export_heights(
        folder / f"{tile.id}.gwy", tile.heights, pixel_size=tile.pixel_size, origin=tile.origin
    )
print(sorted(p.name for p in folder.iterdir()))

# %%
# Read the folder: each file is placed by its offsets; merge.
scans = merge.read_scans(folder)
result = merge.run(scans, merge.MergeConfig(method="default"))
print(verdict(result).line)

# %%
# Export, and read the exported Gwyddion file back as any reader would.
out = folder / "merged"
merge.write_result(result, out, patch_set=scans)
mosaic = result.mosaic
for suffix in ("gwy", "tif"):
    export_heights(
        out / f"mosaic.{suffix}",
        mosaic.heights,
        pixel_size=mosaic.pixel_size,
        origin=mosaic.origin,
    )
image = read_image(out / "mosaic.gwy")
ny, nx = image.heights.shape
x0, y0 = image.offset or (0.0, 0.0)
extent = [x0 * 1e6, (x0 + nx * image.pixel_size[0]) * 1e6, y0 * 1e6,
          (y0 + ny * image.pixel_size[1]) * 1e6]  # fmt: skip
fig, ax = plt.subplots(figsize=(5, 4.2), constrained_layout=True)
shown = ax.imshow(image.heights * 1e9, origin="lower", extent=extent, cmap="afmhot")
ax.set(title="mosaic.gwy, read back", xlabel="x (µm)", ylabel="y (µm)")
fig.colorbar(shown, ax=ax, label="height (nm)")
plt.show()
