"""Merge a folder of overlapping scans from Python: the API the server and scripts use.

    python examples/merge_folder.py PATCHES/manifest.json OUT/

Makes a synthetic patch set first when called without arguments.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import merge


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) == 2:
        manifest, out = Path(args[0]), Path(args[1])
    else:
        from backend.cli import main as cli

        work = Path(tempfile.mkdtemp(prefix="mosaic-example-"))
        cli(["synth", "--out", str(work / "patches"), "--surface", "folded", "--seed", "2"])
        manifest, out = work / "patches" / "manifest.json", work / "merged"
    patch_set = merge.read_patch_set(manifest)

    def progress(iteration: int, residual: float) -> None:
        print(f"iteration {iteration:3d}: residual {residual * 1e9:.3f} nm")

    result = merge.run(patch_set, merge.MergeConfig(method="default"), progress=progress)
    merge.write_result(result, out, patch_set=patch_set)
    worst = max(result.patches, key=lambda p: p.residual_rms)
    print(
        f"{len(result.patches)} patches, converged={result.converged}; worst fit: {worst.id} "
        f"({worst.residual_rms * 1e9:.2f} nm); result in {out}"
    )
    for w in result.warnings:
        print("warning:", w)
    return 0


if __name__ == "__main__":
    sys.exit(main())
