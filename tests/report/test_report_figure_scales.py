"""Figures of the reports that compare panels: every panel on one scale, clipping said, nothing drawn over a
neighbour. Found by looking at the PNGs of a tiny-scale demo, evaluation and experiments (a review of the
pictures); each test reads the property back from the figure object (axis limits, label text, colour-bar
extension, the rendered text's bounding boxes)."""

from __future__ import annotations

import numpy as np
import pytest

from figure_helpers import drawn_extent
from hsicam.report import html as report_html


@pytest.fixture
def captured(monkeypatch):
    """The figures the report module saves, kept open to be inspected after the save."""
    figures = []
    real_save = report_html.save_figure
    monkeypatch.setattr(report_html, "save_figure", lambda fig, path: (figures.append(fig), real_save(fig, path)))
    return figures


def _grid(levels: dict[str, tuple[float, float]]) -> dict:
    """A noise grid of σ_p 0, 30 nm × σ_s 0, 0.005, 0.01; camera → (PSNR at the clean point, SSIM there)."""
    results = {}
    for name, (psnr, ssim) in levels.items():
        results[name] = [{"sigma_height_nm": sp, "sensor_sigma": ss, "psnr": psnr - 0.1 * sp - 100 * ss,
                          "ssim": ssim - 0.001 * sp - 5 * ss} for sp in (0.0, 30.0) for ss in (0.0, 0.005, 0.01)]
    return {"sigma_height_nm": [0.0, 30.0], "results": results}


def test_noise_grid_panels_share_psnr_and_ssim_scales_and_keep_clear_of_each_other(tmp_path, captured):
    """Two cameras 5 dB and 0.1 SSIM apart: both panels span both cameras' values (on the old figure each
    panel had its own autoscaled axes, so the worse camera looked as good), and the first panel's SSIM axis
    (right) does not run into the second panel's PSNR axis (left): they were drawn over each other."""
    grid = _grid({"trained-clean": (30.0, 0.9), "trained-noisy": (25.0, 0.8)})
    report_html.plot_noise_grid(grid, tmp_path / "noise_grid.png")
    (fig,) = captured
    psnr_axes = [a for a in fig.axes if a.get_ylabel().startswith("PSNR")]
    ssim_axes = [a for a in fig.axes if a.get_ylabel().startswith("SSIM")]
    assert len(psnr_axes) == len(ssim_axes) == 2
    all_psnr = [g["psnr"] for pts in grid["results"].values() for g in pts]
    all_ssim = [g["ssim"] for pts in grid["results"].values() for g in pts]
    for axes, values in ((psnr_axes, all_psnr), (ssim_axes, all_ssim)):
        lims = [a.get_ylim() for a in axes]
        assert lims[0] == pytest.approx(lims[1])
        assert lims[0][0] <= min(values) and lims[0][1] >= max(values)
    assert "fraction of full scale" in psnr_axes[0].get_xlabel()
    left_ssim = min(ssim_axes, key=lambda a: a.get_position().x0)
    right_psnr = max(psnr_axes, key=lambda a: a.get_position().x0)
    assert not drawn_extent(fig, left_ssim.yaxis).overlaps(drawn_extent(fig, right_psnr.yaxis))


def test_band_error_maps_say_when_their_colour_scale_clips_the_largest_errors(tmp_path, captured):
    """One pixel wrong by 0.9, the rest by 0.01: the shared scale ends at the 99.5th percentile (numpy's), so that
    pixel is clipped; the colour bar points beyond its top and the title gives the largest error (on the old
    figure a tiny-scale scene's errors of up to 0.85 were drawn as 0.46 with nothing saying so). Errors within
    the scale: no arrow, no such words."""
    from hsicam.spectral import Bands

    bands = Bands.uniform(420, 510, 10)
    truth = np.zeros((10, 8, 8), np.float32)
    est = truth + np.float32(0.01)
    est[3, 4, 4] = 0.9
    report_html.plot_band_errors(truth, est, bands, tmp_path / "e.png", title="scene_7")
    report_html.plot_band_errors(truth, truth + np.float32(0.01), bands, tmp_path / "f.png")
    (fig, flat) = captured
    images = [ax.images[0] for ax in fig.axes if ax.images]
    top = float(np.percentile(np.abs(est - truth), 99.5))
    assert all(im.get_clim()[1] == pytest.approx(top) for im in images) and top < 0.9
    assert next(im.colorbar for im in images if im.colorbar is not None).extend == "max"
    title = fig.get_suptitle()
    assert title.startswith("scene_7: ") and "clipped" in title and "0.9" in title
    flat_images = [ax.images[0] for ax in flat.axes if ax.images]
    assert next(im.colorbar for im in flat_images if im.colorbar is not None).extend == "neither" and "clipped" not in flat.get_suptitle()


def test_training_curves_with_two_validation_points_draw_psnr_and_ssim_apart_with_markers(tmp_path, monkeypatch):
    """A tiny run validates twice: on the old figure PSNR and SSIM shared one panel on two autoscaled axes, so
    each line ran from corner to corner and the two were drawn exactly over each other, the legend over the last
    point. Read back from the drawn figure: every validation point is drawn with a marker, no PSNR point lies
    within 5 px of an SSIM point, and no legend covers a point."""
    import json

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from hsicam.report import reconstruction

    figures = []
    real_save = reconstruction.save_figure
    monkeypatch.setattr(reconstruction, "save_figure", lambda fig, path: (figures.append(fig), real_save(fig, path)))
    recs = [{"step": 1, "train_loss": 0.1}, {"step": 4, "val_psnr": 27.93, "val_ssim": 0.4596},
            {"step": 8, "train_loss": 0.09}, {"step": 8, "val_psnr": 27.62, "val_ssim": 0.4527},
            {"step": 8, "final": True, "val_psnr": 27.62, "val_ssim": 0.4527}]
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in recs))
    reconstruction.plot_training_curves(tmp_path / "metrics.jsonl", tmp_path / "training.png")
    (fig,) = figures
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()

    def drawn_points(values):
        """Display positions (px) of the markers of the line through ``values`` (steps 4, 8)."""
        for ax in fig.axes:
            for line in ax.get_lines():
                if list(line.get_xdata()) == [4, 8] and np.allclose(line.get_ydata(), values):
                    assert line.get_marker() not in (None, "", "None", " ")
                    return ax.transData.transform(np.column_stack([line.get_xdata(), line.get_ydata()]))
        raise AssertionError(f"no line through {values}")

    psnr, ssim = drawn_points([27.93, 27.62]), drawn_points([0.4596, 0.4527])
    assert np.linalg.norm(psnr[:, None] - ssim[None], axis=-1).min() > 5
    for legend in [ax.get_legend() for ax in fig.axes if ax.get_legend()] + fig.legends:
        box = legend.get_window_extent(renderer)
        assert not any(box.contains(x, y) for x, y in np.vstack([psnr, ssim]))
