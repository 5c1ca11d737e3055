"""Merge a folder of overlapping scans from Python: the API the server and scripts use.

    python examples/merge_folder.py SCANS/ OUT/              # AFM files of any format
    python examples/merge_folder.py PATCHES/manifest.json OUT/

Makes a synthetic patch set first when called without arguments. Prints every iteration's
residual, the worst fit, the warnings and the verdict; exit code 3 when the mosaic is not to be
trusted.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import merge
from merge.report import verdict


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) == 2:
        source, out = Path(args[0]), Path(args[1])
    else:
        from backend.cli import main as cli

        work = Path(tempfile.mkdtemp(prefix="mosaic-example-"))
        cli(["synth", "--out", str(work / "patches"), "--surface", "folded", "--seed", "2"])
        source, out = work / "patches" / "manifest.json", work / "merged"
    if source.suffix == ".json" or (source / "manifest.json").is_file():
        patch_set = merge.read_patch_set(source)
    else:  # a folder of AFM files, placed by their scan offsets
        patch_set = merge.read_scans(source)

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
    said = verdict(result)
    print(said.line)
    return 0 if said.trusted else 3


if __name__ == "__main__":
    sys.exit(main())
