"""``preview.png``: the mosaic before (nominal placement) and after the merge, side by side,
in one colour map with a nm colour bar and an L-shaped scale bar (x and y), at the true aspect
of the sample (non-square pixels drawn square on the sample) and +y up."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from merge.io.png import draw_text, encode_png
from merge.render import Mosaic

FloatArray = NDArray[np.float64]
UInt8Array = NDArray[np.uint8]

BACKGROUND = (245, 245, 245)
NO_DATA = (64, 64, 64)
INK = (20, 20, 20)


def afm_colors(values: FloatArray) -> UInt8Array:
    """The gold "AFM hot" colour map of values in [0, 1] (NaN -> dark grey), ``(..., 3)`` uint8.

    One channel at a time, in place: the three channels as floats at once were the largest
    temporaries of writing a small mosaic's result.
    """
    v = np.asarray(values, dtype=np.float64)
    out: UInt8Array = np.empty((*v.shape, 3), dtype=np.uint8)
    scaled = np.nan_to_num(v, nan=0.0)  # a copy
    np.clip(scaled, 0.0, 1.0, out=scaled)
    scaled *= 2.0
    channel = np.empty_like(scaled)
    for k, offset in enumerate((0.0, 0.5, 1.0)):
        np.subtract(scaled, offset, out=channel)
        np.clip(channel, 0.0, 1.0, out=channel)
        channel *= 255
        channel += 0.5
        out[..., k] = channel  # truncated, as a cast to uint8 rounds these
    out[np.isnan(v)] = NO_DATA
    return out


def _nice_step(span: float, target: int) -> float:
    raw = span / max(target, 1)
    mag = 10 ** np.floor(np.log10(raw)) if raw > 0 else 1.0
    for m in (1, 2, 5, 10):
        if m * mag >= raw:
            return float(m * mag)
    return float(10 * mag)


def fit_size(
    heights: FloatArray, size: int, *, pixel_size: tuple[float, float] = (1.0, 1.0)
) -> FloatArray:
    """Nearest-neighbour resample so that the longer side is ``size`` pixels and every pixel
    shown is square on the sample: a map of ``pixel_size`` (dx, dy) pixels keeps its true
    aspect (a 2 x 1 µm area drawn twice as wide as tall, whatever its pixel counts)."""
    ny, nx = heights.shape
    width, height = nx * pixel_size[0], ny * pixel_size[1]
    f = size / max(width, height)
    out_nx, out_ny = max(1, round(width * f)), max(1, round(height * f))
    rows = np.minimum((np.arange(out_ny) * ny / out_ny).astype(int), ny - 1)
    cols = np.minimum((np.arange(out_nx) * nx / out_nx).astype(int), nx - 1)
    out: FloatArray = heights[np.ix_(rows, cols)]
    return out


def _fmt(v: float) -> str:
    return f"{v:.0f}" if abs(v) >= 10 or v == 0 else f"{v:.1f}"


def render_preview(before: Mosaic, after: Mosaic, *, size: int = 420) -> UInt8Array:
    """An RGB image: before | after | colour bar (nm), with titles and a scale bar."""
    return render_panels([("NOMINAL", before), ("MERGED", after)], size=size)


def render_panels(panels_in: list[tuple[str, Mosaic]], *, size: int = 420) -> UInt8Array:
    """Height maps side by side in one colour map (1-99 % of their heights), each titled and
    with a scale bar, then a colour bar in nm. ``size``: longer side of a panel, pixels."""
    if not panels_in:
        raise ValueError("need at least one height map")
    mosaics = [m for _, m in panels_in]
    # +y up, as on the sample (and in Gwyddion): the last row of a map is the picture's top
    panels = [fit_size(m.heights, size, pixel_size=m.pixel_size)[::-1] for m in mosaics]
    # the colour scale from what the panels show (not a copy of every mosaic's heights)
    both = np.concatenate([p[np.isfinite(p)] for p in panels])
    lo, hi = np.percentile(both, [1, 99], overwrite_input=True) if both.size else (0.0, 1.0)
    del both
    hi = hi if hi > lo else lo + 1e-9
    ph = max(p.shape[0] for p in panels)
    margin, title_h, bar_w, label_w = 16, 30, 18, 70
    width = margin + sum(p.shape[1] + margin for p in panels) + bar_w + label_w
    height = title_h + ph + 44
    img = np.empty((height, width, 3), dtype=np.uint8)
    img[:] = BACKGROUND
    col = margin
    titles = [t for t, _ in panels_in]
    for title, panel, mosaic in zip(titles, panels, mosaics, strict=True):
        h, w = panel.shape
        img[title_h : title_h + h, col : col + w] = afm_colors((panel - lo) / (hi - lo))
        draw_text(img, title, 8, col, color=INK)
        # an L-shaped scale bar, a round length near a quarter of the panel's shorter side
        # along x (below it) and along y (left of it): the pixels shown are square
        per_x = mosaic.pixel_size[0] * mosaic.heights.shape[1] / w
        per_y = mosaic.pixel_size[1] * mosaic.heights.shape[0] / h
        length = _nice_step(0.25 * min(w * per_x, h * per_y), 1)
        bar_x, bar_y = max(1, round(length / per_x)), max(1, round(length / per_y))
        y = title_h + ph + 12
        img[y : y + 4, col : col + bar_x] = INK
        img[title_h + h - bar_y : title_h + h, col - 8 : col - 4] = INK
        img[title_h + h : y + 4, col - 8 : col - 4] = INK  # the corner of the L
        label = f"{length * 1e6:g} µm" if length >= 1e-6 else f"{length * 1e9:g} nm"
        draw_text(img, label, y + 8, col, color=INK)
        col += w + margin
    # colour bar with ticks in nm
    ramp = np.linspace(1.0, 0.0, ph)[:, None] * np.ones((1, bar_w))
    img[title_h : title_h + ph, col : col + bar_w] = afm_colors(ramp)
    lo_nm, hi_nm = lo * 1e9, hi * 1e9
    step = _nice_step(hi_nm - lo_nm, 5)
    for tick in np.arange(np.ceil(lo_nm / step) * step, hi_nm + 1e-9, step):
        y = title_h + round((hi_nm - tick) / (hi_nm - lo_nm) * (ph - 1))
        img[y, col + bar_w : col + bar_w + 4] = INK
        draw_text(img, _fmt(float(tick)), max(y - 7, 0), col + bar_w + 6, color=INK)
    draw_text(img, "nm", 8, col, color=INK)
    return img


def write_preview(path: str, before: Mosaic, after: Mosaic, *, size: int = 420) -> None:
    """Write :func:`render_preview` as a PNG file (``size``: a panel's longer side, pixels)."""
    with open(path, "wb") as fh:
        fh.write(encode_png(render_preview(before, after, size=size)))
