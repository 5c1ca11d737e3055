"""Pictures that tell the truth: the sample's true aspect, scale bars along both axes, and a
font with every character it draws."""

from __future__ import annotations

import string

import numpy as np

from merge.io.png import _GLYPHS, _MISSING, text_mask
from merge.io.preview import INK, fit_size, render_panels
from merge.render import Mosaic


def test_every_letter_digit_and_sign_the_titles_use_has_a_glyph() -> None:
    for ch in string.ascii_letters + string.digits + "-+.,:()/%_'=#[]×°±Åµ ":
        assert ch in _GLYPHS, ch
    blank = np.zeros((7, 5), dtype=bool)
    for ch in string.ascii_letters + string.digits:
        glyph = np.array([[c == "#" for c in r] for r in _GLYPHS[ch]])
        assert glyph.shape == (7, 5) and not (glyph == blank).all(), ch
    # "Height" is six drawn glyphs (it once came out as "EIG T"), distinct from a box
    shown = text_mask("Height", scale=1)
    assert shown[:, 0:5].any() and shown[:, 24:29].any()
    box = np.array([[c == "#" for c in r] for r in _MISSING])
    for k, ch in enumerate("Height"):
        assert not (shown[:, 6 * k : 6 * k + 5] == box).all(), ch
    assert (text_mask("☃", scale=1)[:, :5] == box).all()  # a missing one shows as a box


def test_non_square_pixels_are_shown_at_the_samples_aspect() -> None:
    heights = np.zeros((100, 100))  # 100 x 100 px of 20 nm x 10 nm: 2 µm wide, 1 µm tall
    shown = fit_size(heights, 200, pixel_size=(20e-9, 10e-9))
    assert shown.shape == (100, 200)
    tall = fit_size(np.zeros((256, 512)), 256, pixel_size=(7.76e-9, 15.52e-9))  # mos2: square
    assert tall.shape == (256, 256)


def test_the_scale_bar_runs_along_both_axes() -> None:
    heights = np.random.default_rng(0).normal(size=(100, 100))
    mosaic = Mosaic(heights, (0.0, 0.0), (20e-9, 10e-9), np.ones((100, 100), np.int32))
    img = render_panels([("Height", mosaic)], size=200)
    ink = np.all(img == INK, axis=-1)
    title_h, margin = 30, 16
    # the panel is 200 x 100 px (2 x 1 µm, 10 nm a pixel shown); below it a bar along x,
    # left of it a bar along y, each 0.5 µm: 50 px
    below = ink[title_h + 100 + 12, margin : margin + 200]
    left = ink[title_h : title_h + 100, margin - 6]
    assert below.sum() == 50 and left.sum() == 50


def test_the_picture_has_y_up_as_the_sample_and_gwyddion() -> None:
    heights = np.zeros((40, 40))
    heights[-5:] = 1.0  # the last rows: the top of the sample (rows along +y)
    mosaic = Mosaic(heights, (0.0, 0.0), (1e-8, 1e-8), np.ones((40, 40), np.int32))
    img = render_panels([("y up", mosaic)], size=40).astype(int)
    title_h, margin = 30, 16
    top, bottom = img[title_h + 1, margin + 20], img[title_h + 38, margin + 20]
    assert top.sum() > bottom.sum()  # the high rows bright, at the top of the picture
