"""The export's DOE figure: continuous and L-level heights on one colour scale, no panel's colour bar drawn over
the next panel's axis. Found by looking at export-optics' doe.png of the shipped standard camera (a review of
the pictures): its continuous heights reach 1481 nm, its 8-level ones (wrapped modulo h_2π = 1282 nm) 1122 nm,
and each map had its own colour scale, so one colour meant two heights."""

from __future__ import annotations

import numpy as np
import pytest

from figure_helpers import drawn_extent
from hsicam.export import cfa as export_cfa
from hsicam.export import doe as export_doe


def test_doe_export_figure_draws_both_height_maps_on_one_scale_clear_of_each_other(tmp_path, monkeypatch):
    figures = []
    real_save = export_doe.save_figure
    monkeypatch.setattr(export_doe, "save_figure", lambda fig, path: (figures.append(fig), real_save(fig, path)))
    n, top, levels = 41, 1282.0, 8
    yy, xx = np.mgrid[:n, :n] - n // 2
    aperture = (np.hypot(yy, xx) <= n // 2).astype(np.float64)
    height = 1500.0 * (xx + n // 2) / (n - 1)  # a ramp 0..1500 nm, above h_2π at one side
    step = top / levels
    quantized = np.mod(np.round(height / step), levels) * step  # wrapped L-level heights, by hand
    export_doe.plot_doe_export(height, quantized, aperture, 30.0, levels, top, tmp_path / "doe.png")
    (fig,) = figures
    maps = [ax.images[0] for ax in fig.axes if ax.images and "height" in ax.get_title()][:2]
    inside = aperture > 0
    both = np.concatenate([height[inside], quantized[inside]])
    for im in maps:
        assert im.get_clim() == pytest.approx((both.min(), both.max()))
    first_bar = maps[0].colorbar.ax.yaxis
    second_map = next(ax for ax in fig.axes if ax.images and ax.images[0] is maps[1])
    assert not drawn_extent(fig, first_bar).overlaps(drawn_extent(fig, second_map.yaxis))


def test_cfa_fit_figure_has_wavelength_axes_readable_text_and_whole_fits(tmp_path, monkeypatch):
    """export-optics' cfa_fit.png (a review of the pictures: the tiny run's 3×3 CFA): no axes, 5-pt labels, and
    the fitted curves clipped at 1.2 (two fits peak at 1.49 and 1.54: drawn with flat tops). Read back from the
    figure: each panel has wavelength tick labels (bottom row) in nm and a y axis, the axis labels name
    wavelength (nm) and transmission, no text is below 7 pt, and each fit is drawn whole inside its panel: its
    drawn maximum is that of offset + Σ Gaussians evaluated here from the fit's parameters (CSV fields)."""
    from hsicam.spectral import Bands

    figures = []
    real_save = export_cfa.save_figure
    monkeypatch.setattr(export_cfa, "save_figure", lambda fig, path: (figures.append(fig), real_save(fig, path)))
    bands = Bands.from_centers(np.arange(420.0, 721.0, 50.0))
    tile = np.random.default_rng(1).uniform(0, 1, (7, 3, 3))
    tile /= tile.sum(axis=0)
    # fits of κ's band values as samples (fit_tile's before session 66: they overshoot between the bands), so that
    # an overshooting fit is drawn; fit_tile's fits of the model filter are drawn by the same code
    fits = [{"filter": name, **export_cfa.fit_filter(bands.centers_nm, curve)}
            for name, curve in zip(export_cfa.filter_names(3, 3), tile.reshape(7, 9).T)]
    export_cfa.plot_fits(tile, bands, fits, tmp_path / "cfa_fit.png")
    (fig,) = figures

    grid, applied = export_cfa.model_filter_curves(tile, bands)
    fine = np.linspace(grid[0], grid[-1], 4001)  # the fits are drawn over the model filters' grid
    def reference(f):  # the fit written to cfa_fit.csv: offset + amplitude · exp(-(λ - centre)² / (2 σ²))
        sigma = [c["fwhm_nm"] / (2 * np.sqrt(2 * np.log(2))) for c in f["components"]]
        return f["offset"] + sum(c["amplitude"] * np.exp(-0.5 * ((fine - c["centre_nm"]) / s) ** 2)
                                 for c, s in zip(f["components"], sigma))

    peaks = [float(reference(f).max()) for f in fits]
    assert max(peaks) > 1.3  # the case that was cut flat at 1.2
    panels = [ax for ax in fig.axes if len(ax.get_lines()) == 3]
    assert len(panels) == 9
    for k, (ax, f, peak) in enumerate(zip(panels, fits, peaks)):
        fit_line, model_line = ax.get_lines()[1:]
        assert float(np.max(fit_line.get_ydata())) == pytest.approx(peak, rel=2e-3)
        assert ax.get_ylim()[1] > peak and ax.get_ylim()[0] < float(reference(f).min())
        # the filter the model applies, whole: its 1 nm grid inside the panel, scaled to a peak of 1, under the fit
        np.testing.assert_allclose(model_line.get_ydata(), applied[:, k] / applied[:, k].max())
        assert ax.get_xlim()[0] < grid[0] and ax.get_xlim()[1] > grid[-1]
        assert model_line.get_zorder() < fit_line.get_zorder()
        assert ax.axison
    bottom = panels[-1]
    ticks = [float(t.get_text().replace("\u2212", "-")) for t in bottom.get_xticklabels() if t.get_text()]
    lo, hi = bottom.get_xlim()
    assert lo < 420 and hi > 720 and len([v for v in ticks if lo <= v <= hi]) >= 2  # the band range, in nm
    assert drawn_extent(fig, bottom.xaxis).width > 0 and drawn_extent(fig, panels[0].yaxis).height > 0
    labels = " ".join(t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text") and hasattr(a, "get_fontsize")))
    assert "wavelength (nm)" in labels and "transmission" in labels
    sizes = [t.get_fontsize() for t in fig.findobj(lambda a: hasattr(a, "get_fontsize") and hasattr(a, "get_text"))
             if t.get_text() and t.get_visible()]
    assert min(sizes) >= 7
