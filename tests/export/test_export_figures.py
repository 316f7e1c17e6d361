"""The export's DOE figure: continuous and L-level heights on one colour scale, no panel's colour bar drawn over
the next panel's axis. Found by looking at export-optics' doe.png of the shipped standard camera (a review of
the pictures): its continuous heights reach 1481 nm, its 8-level ones (wrapped modulo h_2π = 1282 nm) 1122 nm,
and each map had its own colour scale, so one colour meant two heights."""

from __future__ import annotations

import numpy as np
import pytest

from figure_helpers import drawn_extent
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
