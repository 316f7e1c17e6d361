"""Mutation guards that finish mut8a's and mut8b's lists (probe mut9a) for the data previews (the camera system's
reconstructor and linear step from the same probe are in models/test_camera_system_edge_cases.py).

Each test kills a hand-made mutant that the other tests let through, asserting against a reference computed here:
a figure's data read back from its axes.
"""

from __future__ import annotations

import numpy as np
import pytest

from hsicam.errors import InputError


# ------------------------------------------------------------------------------------------------
# data/preview.py
# ------------------------------------------------------------------------------------------------
def _h5_scenes(folder, n, bands=None, hw=(6, 8), seed=0, scale=1.0):
    """``n`` random cubes (C, H, W) written as our HDF5 files scene_00.h5 … in ``folder``; returns (paths, cubes)."""
    from hsicam.data.formats import write_cube_h5
    from hsicam.spectral import Bands

    bands = bands if bands is not None else Bands.uniform(420.0, 720.0, 30.0)
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    paths, cubes = [], []
    for k in range(n):
        cube = (scale * (0.1 + rng.random((len(bands), *hw)))).astype(np.float32)
        paths.append(write_cube_h5(folder / f"scene_{k:02d}.h5", cube, bands))
        cubes.append(cube)
    return paths, cubes


@pytest.mark.parametrize("n, rows, cols", [(3, 1, 3), (4, 1, 4), (5, 2, 4), (9, 3, 4)])
def test_contact_sheet_has_four_columns_at_most(tmp_path, n, rows, cols):
    """The contact sheet lays its renders out in rows of 4 (fewer scenes: one row of them), read back from its axes."""
    from hsicam.data.preview import _scene_figures

    paths, _ = _h5_scenes(tmp_path, n)
    sheet, _ = _scene_figures(tmp_path, paths)
    assert len(sheet.axes) == n
    assert {ax.get_subplotspec().get_geometry()[:2] for ax in sheet.axes} == {(rows, cols)}
    assert [ax.get_title() for ax in sheet.axes] == [p.name for p in paths]


@pytest.mark.parametrize("n, legend", [(16, True), (17, False)])
def test_mean_spectra_legend_names_up_to_sixteen_scenes(tmp_path, n, legend):
    """The mean-spectra plot has a legend naming every scene for up to 16 scenes, none beyond."""
    from hsicam.data.preview import _scene_figures

    paths, _ = _h5_scenes(tmp_path, n, hw=(2, 2))
    _, plot = _scene_figures(tmp_path, paths)
    got = plot.axes[0].get_legend()
    assert (got is not None) is legend
    if legend:
        assert [t.get_text() for t in got.get_texts()] == [p.name for p in paths]
        # each legend entry names one curve: no two drawn alike (matplotlib's 10 colours named two curves each for
        # 6 of 16 entries: session 74's figure hunt)
        from matplotlib.colors import to_hex

        styles = [(to_hex(ln.get_color()), ln.get_linestyle()) for ln in plot.axes[0].get_lines()]
        assert len(styles) == n and len(set(styles)) == n, styles


def test_mean_spectra_are_divided_by_each_cubes_maximum(tmp_path):
    """Each plotted mean spectrum is the cube's band means divided by its maximum (per-cube max = 1), read back
    from the plot's lines against numpy, for cubes of peak 4 and 0.25."""
    from hsicam.data.preview import _scene_figures

    paths, cubes = _h5_scenes(tmp_path / "a", 1, scale=4.0)
    more, more_cubes = _h5_scenes(tmp_path / "b", 1, seed=1, scale=0.25)
    _, plot = _scene_figures(tmp_path, paths + more)
    lines = plot.axes[0].get_lines()
    assert len(lines) == 2
    for line, cube in zip(lines, cubes + more_cubes):
        want = cube.astype(np.float64).mean(axis=(1, 2)) / cube.max()
        np.testing.assert_allclose(line.get_xdata(), np.arange(420.0, 721.0, 30.0))
        np.testing.assert_allclose(line.get_ydata(), want, rtol=1e-5)


def test_spectral_shapes_drop_only_spectra_a_thousand_times_dimmer_than_the_brightest():
    """_shapes: unit-norm spectra, dropping those whose norm is at most 1e-3 of the largest: a spectrum at 1 % is
    kept (its shape does not depend on its brightness), one at 0.05 % is dropped."""
    from hsicam.data.preview import _shapes

    x = np.array([[3.0, 4.0, 0.0], [0.0, 0.006, 0.008], [0.0, 0.0, 0.0025], [1e-4, 0.0, 0.0]])
    got = _shapes(x)
    np.testing.assert_allclose(got, [[0.6, 0.8, 0.0], [0.0, 0.6, 0.8]], rtol=1e-12)


def test_pixel_spectra_sample_distinct_pixels(tmp_path):
    """Pixel spectra are drawn without replacement: asking for as many as a scene has gives each of its pixels
    once; asking for fewer gives that many distinct ones (all pixels distinct here, compared as rows)."""
    from hsicam.data.preview import pixel_spectra
    from hsicam.spectral import Bands

    bands = Bands.uniform(420.0, 720.0, 30.0)
    paths, cubes = _h5_scenes(tmp_path, 1, bands=bands, hw=(5, 6))
    every = {tuple(r) for r in cubes[0].reshape(len(bands), -1).T.tolist()}
    assert len(every) == 30
    for k in (30, 100, 20):
        pix, grid = pixel_spectra(paths, bands, per_scene=k)
        rows = [tuple(r) for r in pix.astype(np.float32).tolist()]
        assert len(rows) == min(k, 30) and len(set(rows)) == len(rows) and set(rows) <= every


@pytest.mark.parametrize("n, tail", [(5, ""), (6, " and 1 more")])
def test_refusal_lists_five_scenes_whose_bands_miss_the_grid_then_counts_the_rest(tmp_path, n, tail):
    """No scene covers the asked grid: the refusal names the first five scenes with their grids, then counts the
    others (the exact text a user sees)."""
    from hsicam.data.preview import pixel_spectra
    from hsicam.spectral import Bands

    paths, _ = _h5_scenes(tmp_path, n, bands=Bands.uniform(500.0, 600.0, 50.0), hw=(2, 2))
    with pytest.raises(InputError) as err:
        pixel_spectra(paths, Bands.uniform(420.0, 720.0, 30.0), source=tmp_path)
    shown = ", ".join(f"scene_{k:02d}.h5: 3 bands, 500-600 nm" for k in range(5))
    assert str(err.value) == (f"{tmp_path}: no scenes to sample spectra from: their bands ({shown}{tail}) do not "
                              "cover the plot's grid (11 bands, 420-720 nm) and are not extrapolated")


def test_held_out_pixels_are_resampled_onto_the_datasets_grid(tmp_path):
    """A held-out set on a finer grid than the dataset's: its pixel spectra are put on the dataset's grid (11 bands)
    and drawn beside the dataset's, each group with its count in the legend."""
    from hsicam.data.preview import _gamut_figure
    from hsicam.spectral import Bands

    paths, _ = _h5_scenes(tmp_path / "data", 2, hw=(4, 5))
    held, _ = _h5_scenes(tmp_path / "held", 1, bands=Bands.uniform(420.0, 720.0, 10.0), hw=(3, 4), seed=2)
    fig = _gamut_figure(tmp_path / "data", paths, tmp_path / "held", held)
    [ax] = fig.axes
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["dataset pixels (40)", "held-out pixels (held) (12)"]
    assert [c.get_offsets().shape for c in ax.collections] == [(40, 2), (12, 2)]


def _library_set(tmp_path):
    """A folder with a synthetic set's manifest (held-out sources nist-philips and rawtoaces, 420-720 nm in 10-nm
    bands) and two scenes."""
    import json

    from hsicam.spectral import Bands

    bands = Bands.uniform(420.0, 720.0, 10.0)
    folder = tmp_path / "train-set"
    paths, _ = _h5_scenes(folder, 2, bands=bands, hw=(4, 4))
    holdout = ["nist-philips", "rawtoaces"]
    (folder / "manifest.json").write_text(json.dumps({"parameters": {"holdout_sources": holdout,
                                                                     "bands": bands.to_dict()}}), encoding="utf-8")
    return folder, paths, bands, holdout


def test_library_panel_derives_its_training_spectra_from_the_training_library_only(tmp_path):
    """The 'derived' spectra of the library panel come from the training library: some are its measured spectra as
    they are (the palette's 'measured' kind), none is a held-out spectrum (brute-force nearest distances)."""
    pytest.importorskip("colour")
    from hsicam.data.preview import _library_shapes

    folder, _, _, _ = _library_set(tmp_path)
    measured, derived, held, _ = _library_shapes(folder)

    def nearest(a, b):
        return np.sqrt(((a[:, None, :] - b[None, :, :]) ** 2).sum(axis=2)).min(axis=1)

    assert (nearest(derived, measured) < 1e-6).sum() >= 10
    assert (nearest(derived, held) < 1e-6).sum() == 0


def test_library_panel_draws_the_held_out_library_in_red(tmp_path):
    """The library panel's red crosses are the held-out library's spectral shapes: their count in the legend and
    their points, read back from the axes, against the held-out split's spectra projected by hand on the panel's
    first two principal components (compared by pairwise distances, which do not depend on the axes' signs)."""
    pytest.importorskip("colour")
    from hsicam.data.preview import _gamut_figure, _library_shapes, _shapes
    from hsicam.data.synthetic import spectral_library

    folder, paths, bands, holdout = _library_set(tmp_path)
    ax = _gamut_figure(folder, paths, None, []).axes[0]
    held = _shapes(spectral_library(bands, holdout, "heldout").reflectances)
    measured = _shapes(spectral_library(bands, holdout, "train").reflectances)
    assert len(held) != len(measured)
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels[1:] == [f"training: measured ({len(measured)})",
                          f"held out (nist-philips, rawtoaces) ({len(held)})"]
    _, derived, _, _ = _library_shapes(folder)
    everything = np.concatenate([derived, measured, held])
    mean = everything.mean(axis=0)
    _, _, vt = np.linalg.svd(everything - mean, full_matrices=False)
    want = (held - mean) @ vt[:2].T
    got = ax.collections[2].get_offsets()
    assert got.shape == want.shape
    np.testing.assert_allclose(np.linalg.norm(got[:, None] - got[None], axis=-1),
                               np.linalg.norm(want[:, None] - want[None], axis=-1), atol=1e-9)


def test_save_figures_writes_at_120_dpi(tmp_path):
    """Figures are saved at 120 dpi: a 2 × 1 inch figure filled by one axes is, with the 0.1-inch tight-bbox pad,
    264 × 144 px in the PNG read back."""
    from matplotlib.figure import Figure
    from PIL import Image

    from hsicam.data.preview import save_figures

    fig = Figure(figsize=(2, 1))
    ax = fig.add_axes((0, 0, 1, 1))
    ax.imshow(np.zeros((4, 8)), aspect="auto")
    ax.axis("off")
    [png] = save_figures({"f.png": fig}, tmp_path)
    with Image.open(png) as im:
        assert abs(im.size[0] - 264) <= 1 and abs(im.size[1] - 144) <= 1


def test_render_of_a_cube_dark_but_for_a_highlight_shows_the_highlight(tmp_path):
    """A cube black but for one pixel in 400 (its 99th-percentile luminance is 0): no exposure is applied (×1),
    so that pixel keeps its colour, the sRGB of the normalised cube there; the rest stays black."""
    from hsicam.color import cube_to_srgb
    from hsicam.data.preview import preview_rgb
    from hsicam.spectral import Bands

    bands = Bands.uniform(420.0, 720.0, 30.0)
    cube = np.zeros((len(bands), 20, 20), dtype=np.float32)
    cube[:, 7, 11] = np.linspace(0.2, 1.0, len(bands))
    rgb = preview_rgb(cube, bands)
    want = cube_to_srgb(cube[:, 7:8, 11:12], bands)[:, 0, 0]
    assert want.max() > 0.1
    np.testing.assert_allclose(rgb[7, 11], want, rtol=1e-5, atol=1e-6)
    mask = np.ones((20, 20), dtype=bool)
    mask[7, 11] = False
    assert np.abs(rgb[mask]).max() < 1e-6
