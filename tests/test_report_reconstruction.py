"""The demo's reconstructions figure: spectra of dim scenes plotted with short tick labels."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
from PIL import Image

from hsicam.report.reconstruction import plot_reconstructions, spectra_exponent
from hsicam.spectral import Bands


def test_spectra_exponent_puts_dim_peaks_in_one_to_ten():
    assert spectra_exponent([np.array([0.2, 0.01])]) == 0
    assert spectra_exponent([np.array([0.0014]), np.array([-0.0001])]) == -3
    assert spectra_exponent([np.array([0.0099])]) == -3
    assert spectra_exponent([np.array([3e-5])]) == -5
    assert spectra_exponent([np.zeros(4)]) == 0 and spectra_exponent([]) == 0
    for peak in (0.0014, 0.0099, 3e-5, 0.002):
        assert 1 <= peak / 10.0 ** spectra_exponent([np.array([peak])]) < 10


def test_the_figure_is_written_for_bright_and_dim_scenes(tmp_path, monkeypatch):
    """Spectra ticks sit on the right (clear of the error map's colour bar); a dim scene's spectra are
    plotted scaled into [1, 10) with the scale as the axis label, a bright one's as they are."""
    from hsicam.report import reconstruction

    figures = []
    real_save = reconstruction.save_figure
    monkeypatch.setattr(reconstruction, "save_figure", lambda fig, path: (figures.append(fig), real_save(fig, path)))
    bands = Bands.paper()
    rng = np.random.default_rng(0)
    rows = []
    for name, level in (("bright", 0.5), ("dim", 0.001)):
        truth = (rng.random((len(bands), 32, 32)) * level).astype(np.float32)
        rows.append(SimpleNamespace(name=name, truth=truth, estimate=truth * 1.1,
                                    metrics={"psnr": 40.0, "ssim": 0.9, "sam": 5.0}))
    path = tmp_path / "reconstructions.png"
    plot_reconstructions(rows, bands, path)
    with Image.open(path) as im:
        assert im.format == "PNG" and im.size[0] > im.size[1] > 300
    spectra = [ax for ax in figures[0].axes if ax.get_title().startswith("spectra")]
    assert len(spectra) == 2
    for ax, label, peak in zip(spectra, ("", "× 1e-3"), (0.5 * 1.1, 0.001 * 1.1 * 1e3)):
        assert ax.yaxis.get_ticks_position() == "right" and ax.get_ylabel() == label
        top = max(float(np.max(line.get_ydata())) for line in ax.get_lines())
        assert 0.8 * peak < top <= peak  # three pixels' spectra of uniform noise in [0, level)
