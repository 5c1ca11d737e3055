"""
The live merge, patch by patch
==============================

While a run scans, each stored patch is merged at once with its neighbours
(:class:`merge.live.LiveMerge`) and judged (:class:`merge.live.Gate`): a patch that does not
lie on its neighbours is scanned again. Here a 3 x 4 mosaic arrives one patch at a time, and
patch ``p005`` comes in spoiled, as a tip that jumped over a particle mid-scan spoils it: its
lower half 40 nm too high. The gate sends it back; its re-scan fits.
"""

import dataclasses

import matplotlib.pyplot as plt
import numpy as np

from backend.synthetic import patch_set_from_synth
from hardware.sim.surfaces import surface_by_name
from hardware.sim.synth import synthesize
from merge.core.noise import estimate_noise
from merge.live import Gate, LiveMerge

scans = synthesize(
    surface_by_name("folded", seed=5),
    rows=3,
    cols=4,
    patch_size=(1e-6, 1e-6),
    pixels=(48, 48),
    overlap=(0.25, 0.25),
    seed=5,
)
patches = patch_set_from_synth(scans).patches

# %%
# Merge and judge each patch as it comes; the spoiled one first, then its re-scan.
live, gate, snapshots = LiveMerge(), Gate(), {}
for patch in patches:
    tries = [patch]
    if patch.id == "p005":
        spoiled = patch.heights.copy()
        spoiled[: spoiled.shape[0] // 2] += 40e-9
        tries = [dataclasses.replace(patch, heights=spoiled), patch]
    for attempt, scan in enumerate(tries):
        update = live.add(scan)
        verdict = gate.judge(update, noise=estimate_noise(scan.heights))[scan.id]
        said = "kept" if verdict.ok else f"scan again: {verdict.reason}"
        print(f"{scan.id} (try {attempt + 1}): {said}")
        if not verdict.ok:
            live.remove(scan.id)
            gate.forget(scan.id)
    if len(live.ids) in (4, 8, 12):
        snapshots[len(live.ids)] = live.mosaic()

# %%
# The live mosaic after 4, 8 and 12 patches.
fig, axes = plt.subplots(1, 3, figsize=(11, 3.6), constrained_layout=True)
low, high = np.nanpercentile(snapshots[12].heights, [1, 99]) * 1e9
for ax, (count, mosaic) in zip(axes, snapshots.items(), strict=True):
    ax.imshow(mosaic.heights * 1e9, origin="lower", cmap="afmhot", vmin=low, vmax=high)
    ax.set(title=f"{count} patches", xticks=[], yticks=[])
plt.show()
