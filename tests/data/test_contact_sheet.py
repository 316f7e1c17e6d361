"""`hsicam data show`'s contact sheet says that each thumbnail is exposed to its own brightness. Found by looking
at the PNGs (a review of the pictures): a held-out scene's thumbnail had a mean sRGB value of 0.30 where the
absolute render of the same cube (srgb_preview at exposure 1) has 0.095, and the title said only
"sRGB renders (CIE 1931 2°, D65)"."""

from __future__ import annotations

import numpy as np

from hsicam.data.formats import write_cube_h5
from hsicam.spectral import Bands


def test_a_dim_scene_and_a_bright_one_look_alike_and_the_title_says_why(tmp_path):
    from hsicam.data.preview import _scene_figures

    bands = Bands.uniform(420.0, 720.0, 10.0)
    rng = np.random.default_rng(0)
    bright = rng.uniform(0.05, 1.0, (len(bands), 16, 16)).astype(np.float32)
    write_cube_h5(tmp_path / "bright.h5", bright, bands)
    write_cube_h5(tmp_path / "dim.h5", bright * np.float32(0.05), bands)  # 20x darker, the same colours
    sheet, _ = _scene_figures(tmp_path, [tmp_path / "bright.h5", tmp_path / "dim.h5"])
    a, b = (np.asarray(ax.images[0].get_array()) for ax in sheet.axes)
    np.testing.assert_allclose(a, b, atol=1e-5)  # the 20x is not shown: each thumbnail has its own exposure
    title = " ".join(sheet.get_suptitle().split())  # (wrapped to the sheet's width)
    assert "exposed to its own brightness" in title and "99th-percentile luminance at 0.8" in title
    one, _ = _scene_figures(tmp_path, [tmp_path / "dim.h5"])  # one column: the two-line title is the widest thing
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(one)
    canvas.draw()
    renderer = canvas.get_renderer()
    (ax,) = one.axes
    assert not one._suptitle.get_window_extent(renderer).overlaps(ax.title.get_window_extent(renderer))
