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


def test_a_one_band_cube_is_shown_with_its_spectrum_a_point_and_the_gamut_said_to_need_two_bands(tmp_path):
    """`data show` of a one-band cube (an ENVI file of one band) failed with "IndexError: index 1 is out of bounds" in
    the gamut's PCA (unit-norm spectra of one band are all 1: no second component), and its mean spectrum, a line
    through one point, drew nothing. Now the three PNGs are written: the spectrum a marker at its wavelength, the
    gamut panel a sentence saying why there is none; two bands still make a PCA panel."""
    import imageio.v3 as iio

    from hsicam.data.preview import _gamut_figure, _scene_figures, write_preview

    one = Bands.from_centers([550.0])
    cube = np.random.default_rng(0).uniform(0.1, 1.0, (1, 12, 14)).astype(np.float32)
    write_cube_h5(tmp_path / "one.h5", cube, one)
    written = write_preview(tmp_path / "one.h5", tmp_path / "show")
    assert sorted(p.name for p in written) == ["contact_sheet.png", "mean_spectra.png", "spectral_gamut.png"]
    assert all(iio.imread(p).ndim == 3 for p in written)  # real PNGs
    _, plot = _scene_figures(tmp_path, [tmp_path / "one.h5"])
    [line] = plot.axes[0].lines
    assert line.get_marker() == "o" and list(line.get_xdata()) == [550.0]
    np.testing.assert_allclose(line.get_ydata(), [cube.mean() / cube.max()], rtol=1e-5)
    gamut = _gamut_figure(tmp_path / "one.h5", [tmp_path / "one.h5"], None, [])
    [ax] = gamut.axes
    assert [t.get_text() for t in ax.texts] == ["no spectral gamut: the data have one band (550 nm),\n"
                                                "and a spectral shape needs two or more"]
    two = Bands.from_centers([500.0, 600.0])
    write_cube_h5(tmp_path / "two.h5", np.concatenate([cube, cube[:, ::-1]]), two)
    [ax] = _gamut_figure(tmp_path / "two.h5", [tmp_path / "two.h5"], None, []).axes
    assert ax.get_xlabel().startswith("PC1") and not ax.texts


def test_a_one_band_synthetic_set_with_held_out_sources_draws_no_library_panel_either(tmp_path):
    """The same for a synthetic set of one band whose manifest names held-out sources: the reflectance library's
    panel, on the same one-band grid, failed with the IndexError after the scene panel was left out (a review,
    session 71)."""
    import pytest

    pytest.importorskip("colour")
    from hsicam.data.preview import _gamut_figure
    from hsicam.data.synthetic import generate_dataset

    one = Bands.from_centers([550.0])
    generate_dataset(tmp_path / "set", n=1, size=32, bands=one, progress=False, holdout_sources=["cie-tcs"])
    [ax] = _gamut_figure(tmp_path / "set", sorted((tmp_path / "set").glob("scene_*.h5")), None, []).axes
    assert [t.get_text() for t in ax.texts] == ["no spectral gamut: the data have one band (550 nm),\n"
                                                "and a spectral shape needs two or more"]


def test_scenes_are_labelled_by_their_path_and_a_capped_sheet_says_how_many_it_shows(tmp_path, caplog, monkeypatch):
    """Two files named a.h5 in two sub-folders had the same label on the sheet and in the spectra's legend; a folder
    of 5 scenes shown with --max-scenes 3 read as the whole set. Now each is labelled by its path below the folder,
    and both figures' titles (and the log) say "the first 3 of 5 scenes"."""
    import logging

    from hsicam.data.preview import write_preview
    import hsicam.data.preview as preview

    bands = Bands.uniform(420.0, 720.0, 30.0)
    rng = np.random.default_rng(0)
    for name in ("day1/a.h5", "day2/a.h5", "b.h5", "c.h5", "d.h5"):
        write_cube_h5(tmp_path / "data" / name, rng.uniform(0.1, 1, (len(bands), 12, 12)).astype(np.float32), bands)
    made = {}
    real = preview._scene_figures
    monkeypatch.setattr(preview, "_scene_figures", lambda *a, **k: made.setdefault("figs", real(*a, **k)))
    with caplog.at_level(logging.INFO, logger="hsicam"):
        write_preview(tmp_path / "data", tmp_path / "show", max_scenes=3)
    sheet, plot = made["figs"]
    assert [ax.get_title() for ax in sheet.axes] == ["b.h5", "c.h5", "d.h5"]  # sorted: the sub-folders' come after
    everything = real(tmp_path / "data", [tmp_path / "data" / "day1" / "a.h5", tmp_path / "data" / "day2" / "a.h5"])
    assert [ax.get_title() for ax in everything[0].axes] == ["day1/a.h5", "day2/a.h5"]
    assert [line.get_label() for line in everything[1].axes[0].lines] == ["day1/a.h5", "day2/a.h5"]
    assert "(the first 3 of 5 scenes)" in " ".join(sheet.get_suptitle().split())
    assert plot.axes[0].get_title().endswith("(the first 3 of 5 scenes)")
    assert f"(the first 3 of the 5 scenes of {tmp_path / 'data'})" in caplog.text
    whole, whole_plot = real(tmp_path / "data", [tmp_path / "data" / "b.h5"], of=1)
    assert "first" not in whole.get_suptitle() and "first" not in whole_plot.axes[0].get_title()
