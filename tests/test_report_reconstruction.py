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


def test_the_figure_is_written_for_bright_and_dim_scenes(tmp_path):
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
