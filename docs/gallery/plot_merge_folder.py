"""
Merge overlapping scans from Python
===================================

A 3 x 3 mosaic of a folded surface, scanned as the simulated instrument scans it (stage
errors of tens of nanometres, a Z offset per patch, noise), merged with :func:`merge.run`.
Left: the patches where the stage put them; right: the merged mosaic.
"""

import matplotlib.pyplot as plt

import merge
from backend.synthetic import patch_set_from_synth
from hardware.sim.surfaces import surface_by_name
from hardware.sim.synth import synthesize
from merge.report import verdict

# %%
# Scan: 9 patches of 1 µm, 64 x 64 pixels, 25 % overlaps, in snake order.
scans = synthesize(
    surface_by_name("folded", seed=3),
    rows=3,
    cols=3,
    patch_size=(1e-6, 1e-6),
    pixels=(64, 64),
    overlap=(0.25, 0.25),
    seed=3,
)
patch_set = patch_set_from_synth(scans)

# %%
# Merge all patches at once; every iteration reports its residual.
residuals = []
result = merge.run(
    patch_set, merge.MergeConfig(method="default"), progress=lambda i, r: residuals.append(r)
)
print(f"{result.iterations} iterations, last residual {residuals[-1] * 1e9:.2f} nm")
for report in result.patches[:3]:
    dx, dy = report.translation[:2] * 1e9
    print(
        f"{report.id}: moved ({dx:.1f}, {dy:.1f}) nm, residual {report.residual_rms * 1e9:.2f} "
        f"nm, XY sigma {report.xy_sigma * 1e9:.2f} nm"
    )
print(verdict(result).line)

# %%
# The mosaic as the stage placed the patches, and as merged.
nominal = merge.render_mosaic(patch_set.patches)
merged = result.mosaic
fig, axes = plt.subplots(1, 2, figsize=(9, 4.2), constrained_layout=True)
for ax, mosaic, title in ((axes[0], nominal, "as placed"), (axes[1], merged, "merged")):
    ny, nx = mosaic.heights.shape
    x0, y0 = mosaic.origin
    extent = [
        x0 * 1e6,
        (x0 + nx * mosaic.pixel_size[0]) * 1e6,
        y0 * 1e6,
        (y0 + ny * mosaic.pixel_size[1]) * 1e6,
    ]
    shown = ax.imshow(mosaic.heights * 1e9, origin="lower", extent=extent, cmap="afmhot")
    ax.set(title=title, xlabel="x (µm)", ylabel="y (µm)")
fig.colorbar(shown, ax=axes, label="height (nm)")
plt.show()
