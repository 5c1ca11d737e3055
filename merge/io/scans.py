"""A folder of overlapping scans as AFM users have them: files of any vendor format
(:mod:`merge.io.formats`), placed by their own scan offsets or by a grid, as a patch set.

Every problem names the file: one that cannot be read stops the whole (or, with
``on_skip``, is left out and told); one without a scan offset, or scanned rotated, is refused
unless a grid is given; two that share an offset are refused as a layout they cannot be
(:func:`merge.io.formats.layout.scan_places`).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from merge.core.errors import PatchSetError
from merge.core.patchset import Patch, PatchSet
from merge.io.formats import AfmImage, FormatError, read_image, reader_for
from merge.io.formats.layout import LayoutError, scan_places

#: Files a folder holds that are never scans (a patch set's own manifest, a merge's result).
NOT_SCANS = frozenset({"manifest.json", "mosaic.npy", "mosaic.json"})


def _natural(path: Path) -> list[object]:
    """Sort key: ``scan2`` before ``scan10``."""
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", path.name)]


def scan_files(source: str | Path | Iterable[str | Path]) -> list[Path]:
    """The scan files of ``source``: a folder (every file of a readable format in it, in
    natural name order: their acquisition order), or files and folders listed in order."""
    items = [source] if isinstance(source, str | Path) else list(source)
    files: list[Path] = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            inside = [
                p
                for p in sorted(path.iterdir(), key=_natural)
                if p.is_file() and p.name not in NOT_SCANS and reader_for(p) is not None
            ]
            if not inside:
                raise PatchSetError(f"{path}: the folder holds no file of a readable AFM format")
            files.extend(inside)
        elif not path.exists():
            raise PatchSetError(f"{path}: no such file or folder")
        else:
            files.append(path)
    return files


def read_scans(
    source: str | Path | Iterable[str | Path],
    *,
    grid: tuple[int, int] | None = None,
    overlap: tuple[float, float] | None = None,
    order: str = "snake",
    channel: str | None = None,
    pixel_size: tuple[float, float] | None = None,
    on_skip: Callable[[Path, str], None] | None = None,
) -> PatchSet:
    """The scans of ``source`` (a folder, or files and folders: :func:`scan_files`) as a
    patch set, each patch named by its file and placed by its scan offset, or by ``grid``
    ``(rows, cols)`` with ``overlap`` (fractions) in ``order`` ("snake" or "raster").

    ``channel`` picks the channel (topography by default); ``pixel_size`` (metres) is for
    formats that carry none. A file that cannot be read raises :class:`PatchSetError` naming
    it, unless ``on_skip(path, why)`` is given: then it is left out and told.
    """
    images: list[AfmImage] = []
    paths: list[Path] = []
    for path in scan_files(source):
        try:
            images.append(read_image(path, channel=channel, pixel_size=pixel_size))
        except FormatError as exc:
            if on_skip is None:
                raise PatchSetError(str(exc)) from None
            on_skip(path, str(exc))
            continue
        paths.append(path)
    if len(images) < 2:
        raise PatchSetError(f"{len(images)} readable scan(s): a mosaic needs two at least")
    try:
        places = scan_places(
            images, grid, overlap=overlap, order=order, names=[p.name for p in paths]
        )
    except LayoutError as exc:
        raise PatchSetError(str(exc)) from None
    ids = _ids(paths)
    return PatchSet(
        Patch(
            id=ids[k],
            heights=image.heights,
            origin=origin,
            pixel_size=image.pixel_size,
            order=k,
            row=row,
            col=col,
            source=str(path),
        )
        for k, (path, image, (origin, row, col)) in enumerate(
            zip(paths, images, places, strict=True)
        )
    )


def _ids(paths: Sequence[Path]) -> list[str]:
    """A patch id per file: its name without the suffix, made unique where two share it."""
    out: list[str] = []
    for path in paths:
        stem, k = path.stem or path.name, 2
        name = stem
        while name in out:
            name, k = f"{stem}~{k}", k + 1
        out.append(name)
    return out
