"""``mosaic-afm convert | export | import``: AFM files in, Gwyddion and friends out."""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from backend.cli.common import UsageError, float_pair

if TYPE_CHECKING:
    import merge

FORMATS_HELP = ".gwy, .tif/.tiff, .png, .ply, .stl, .npy (+ .json)"


def _pixel(text: str) -> tuple[float, float]:
    return float_pair(text)


def add_parsers(sub: Any) -> None:
    p = sub.add_parser(
        "convert",
        help="convert an AFM file (.nid, .gwy, .tif, .npy) to another format",
        description=f"Read IN (topography by default) and write OUT in the format of its "
        f"suffix: {FORMATS_HELP}. Like gwyddion --convert-to-gwy.",
    )
    p.add_argument("input", metavar="IN")
    p.add_argument("output", metavar="OUT")
    p.add_argument("--channel", help="channel to read (default: topography)")
    p.add_argument("--pixel-size", type=_pixel, help="dx[,dy] metres, for files without one")
    p.set_defaults(func=convert)

    p = sub.add_parser(
        "export",
        help="export a merge result (mosaic.npy + mosaic.json) to another format",
        description=f"Write a merged mosaic as {FORMATS_HELP}; .gwy carries a mask of "
        "uncovered pixels and the merge's method, parameters and per-patch transforms.",
    )
    p.add_argument("result", metavar="RESULT", help="folder with mosaic.npy and mosaic.json")
    p.add_argument("--format", required=True, choices=["gwy", "tiff", "png", "ply", "stl", "npy"])
    p.add_argument("--out", help="output file (default: RESULT/mosaic.<format>)")
    p.set_defaults(func=export)

    p = sub.add_parser(
        "import",
        help="build a patch-set manifest from AFM files or a folder of them",
        description="Write DIR/manifest.json naming the scans of FILES (files, or folders: "
        "every readable AFM file in them, in natural name order) as patches. Positions come "
        "from the files' scan offsets, else from --grid, --overlap and --order.",
    )
    p.add_argument("files", nargs="+", metavar="FILES", help="AFM files, or folders of them")
    p.add_argument("--out", required=True, metavar="DIR")
    add_scan_options(p)
    p.set_defaults(func=import_files)


def _read(path: str, channel: str | None, pixel: tuple[float, float] | None) -> Any:
    from merge.io.formats import FormatError, read_image

    try:
        return read_image(path, channel=channel, pixel_size=pixel)
    except FormatError as exc:
        raise UsageError(str(exc)) from None


def convert(args: argparse.Namespace) -> int:
    from merge.io.formats import FormatError, export_heights

    image = _read(args.input, args.channel, args.pixel_size)
    try:
        out = export_heights(
            args.output,
            image.heights,
            pixel_size=image.pixel_size,
            origin=image.offset or (0.0, 0.0),
            title=image.channel,
        )
    except (FormatError, OSError) as exc:
        raise UsageError(str(exc)) from None
    ny, nx = image.heights.shape
    print(f"{args.input} [{image.channel}] {nx} x {ny} px -> {out}")
    return 0


def export(args: argparse.Namespace) -> int:
    import merge
    from merge.io.formats import FormatError, export_heights

    try:
        stored = merge.read_result(args.result)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    suffix = {"tiff": ".tif"}.get(args.format, f".{args.format}")
    out = Path(args.out) if args.out else Path(args.result) / f"mosaic{suffix}"
    if out.suffix.lower() not in (suffix, ".tiff" if suffix == ".tif" else suffix):
        raise UsageError(f"--out {out} does not end in {suffix} (the --format asked for)")
    m = stored.mosaic
    try:
        export_heights(
            out, m.heights, pixel_size=m.pixel_size, origin=m.origin, document=stored.document
        )
    except (FormatError, OSError) as exc:
        raise UsageError(str(exc)) from None
    print(f"{args.result} -> {out}")
    return 0


def add_scan_options(p: Any) -> None:
    """The options that say how to read and place a folder of scans (import and merge)."""
    p.add_argument("--grid", help="ROWSxCOLS of the grid the files were scanned in, in order")
    p.add_argument("--overlap", type=float_pair, help="OX,OY fractions between neighbours")
    p.add_argument("--order", choices=["snake", "raster"], default="snake")
    p.add_argument("--channel", help="channel to read (default: topography)")
    p.add_argument("--pixel-size", type=_pixel, help="dx[,dy] metres, for files without one")
    p.add_argument(
        "--skip-bad",
        action="store_true",
        help="leave out files that cannot be read (each named) instead of stopping",
    )


def read_scan_args(sources: list[str], args: argparse.Namespace) -> merge.PatchSet:
    """The patch set of ``sources`` as the scan options say (:func:`merge.read_scans`)."""
    import merge

    grid = None
    if args.grid:
        try:
            rows, cols = (int(v) for v in args.grid.lower().split("x"))
        except ValueError:
            raise UsageError(f"--grid must be ROWSxCOLS, e.g. 5x10, got {args.grid!r}") from None
        grid = (rows, cols)

    def skipped(path: Path, why: str) -> None:
        print(f"skipped {path}: {why}", file=sys.stderr)

    try:
        return merge.read_scans(
            sources,
            grid=grid,
            overlap=args.overlap,
            order=args.order,
            channel=args.channel,
            pixel_size=args.pixel_size,
            on_skip=skipped if args.skip_bad else None,
        )
    except merge.PatchSetError as exc:
        raise UsageError(str(exc)) from None


def import_files(args: argparse.Namespace) -> int:
    patch_set = read_scan_args(args.files, args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    patches = []
    for patch in patch_set:
        entry: dict[str, Any] = {
            "id": patch.id,
            "file": os.path.relpath(Path(patch.source or "").resolve(), out.resolve()),
            "order": patch.order,
            "origin": [float(patch.origin[0]), float(patch.origin[1])],
            "pixel_size": [float(patch.pixel_size[0]), float(patch.pixel_size[1])],
        }
        if args.channel:
            entry["channel"] = args.channel
        if patch.row is not None:
            entry["row"], entry["col"] = patch.row, patch.col
        patches.append(entry)
    manifest = {"format": "mosaic-afm/patchset@1", "units": "m", "patches": patches}
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n", encoding="utf-8")
    print(f"{len(patches)} patches -> {out / 'manifest.json'}")
    return 0
