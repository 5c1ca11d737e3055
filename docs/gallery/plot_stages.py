"""
What each method of the merge buys, against the truth
======================================================

A TGX1-like grating (3 µm period, 0.6 µm steps) scanned as 3 x 4 drifting patches of 1 µm by
the simulator, merged four ways and scored against the true surface after the gauge no
overlap can see (a common rigid motion and Z plane): as the stage placed the patches
(``nominal``), Z offsets only (``zlevel``), the published GPA-ICP on down-sampled points
(``paper``), and this project's merge (``default``: the robust start, then the simultaneous
refinement at full resolution). See :doc:`/method`.
"""

import matplotlib.pyplot as plt
import numpy as np

import merge
from backend.synthetic import patch_set_from_synth, scored
from hardware.sim.surfaces import surface_by_name
from hardware.sim.synth import synthesize

scans = synthesize(
    surface_by_name("chessboard", seed=4),
    rows=3,
    cols=4,
    patch_size=(1e-6, 1e-6),
    pixels=(64, 64),
    overlap=(0.3, 0.3),
    seed=4,
)
patch_set = patch_set_from_synth(scans)

# %%
# Merge four ways; score each against the truth.
results, errors = {}, {}
for method in ("nominal", "zlevel", "paper", "default"):
    results[method] = merge.run(patch_set, merge.MergeConfig(method=method))
    score = scored(scans, [p.transform for p in results[method].patches])
    errors[method] = (score.xy * 1e9, score.z * 1e9)
    print(f"{method:8s} XY {score.xy * 1e9:7.2f} nm   Z {score.z * 1e9:7.2f} nm")

fig, ax = plt.subplots(figsize=(6, 3.2), constrained_layout=True)
x = np.arange(len(errors))
ax.bar(x - 0.2, [e[0] for e in errors.values()], 0.4, label="XY")
ax.bar(x + 0.2, [e[1] for e in errors.values()], 0.4, label="Z")
ax.set(xticks=x, xticklabels=list(errors), yscale="log", ylabel="RMS error (nm)")
ax.legend()
plt.show()

# %%
# Each patch's XY error as the stage placed it (arrows 5 x) and after the merge (500 x).
nominal = scored(scans, [p.transform for p in results["nominal"].patches]).patches
merged = scored(scans, [p.transform for p in results["default"].patches]).patches
centres = np.array([[s.origin[0] + 0.5e-6, s.origin[1] + 0.5e-6] for s in scans]) * 1e6
fig, axes = plt.subplots(1, 2, figsize=(9, 3.4), constrained_layout=True, sharey=True)
for ax, err, title, scale in ((axes[0], nominal, "as placed", 5), (axes[1], merged, "merged", 500)):
    ax.quiver(centres[:, 0], centres[:, 1], err[:, 0] * 1e6 * scale, err[:, 1] * 1e6 * scale,
              angles="xy", scale_units="xy", scale=1, color="C3")  # fmt: skip
    ax.set(title=f"{title} (arrows x{scale})", xlabel="x (µm)", aspect="equal")
axes[0].set_ylabel("y (µm)")
plt.show()

# %%
# The refinement's residual per iteration, and the report's sigmas against the errors.
default = results["default"]
sigmas = np.array([p.xy_sigma for p in default.patches]) * 1e9
fig, axes = plt.subplots(1, 2, figsize=(9, 3.2), constrained_layout=True)
axes[0].semilogy(np.arange(1, len(default.history) + 1), np.array(default.history) * 1e9, "o-")
axes[0].set(xlabel="iteration", ylabel="residual (nm)")
axes[1].scatter(sigmas, np.hypot(merged[:, 0], merged[:, 1]) * 1e9)
top = max(sigmas.max(), 1e-3) * 3
axes[1].plot([0, top], [0, top], "k--", lw=1, label="error = sigma")
axes[1].set(xlabel="reported XY sigma (nm)", ylabel="true XY error (nm)")
axes[1].legend()
plt.show()
