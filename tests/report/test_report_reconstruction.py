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


def test_the_loss_formula_names_exactly_the_terms_the_training_loss_adds():
    """Each weight alone changes system_loss away from the plain L1 and appears in the formula with
    its weight; all at 0 the loss is the paper's L1 and so is the formula; the quick preset's reads as
    its four terms."""
    import torch
    import torch.nn.functional as F

    from hsicam.config import TrainConfig, load_config
    from hsicam.engine.tasks import system_loss

    g = torch.Generator().manual_seed(0)
    truth = torch.rand(2, 31, 24, 24, generator=g)
    recon = truth + 0.05 * torch.randn(2, 31, 24, 24, generator=g)
    plain = TrainConfig()
    assert plain.loss_formula() == "L1"
    assert float(system_loss(recon, truth, plain, period=4)) == float(F.l1_loss(recon, truth))
    names = {"relative_l1": "0.5·relative L1", "ssim_loss": "0.5·(1 − SSIM)", "sam_loss": "0.5·spectral angle",
             "spectral_grad_loss": "0.5·spectral-gradient L1", "phase_loss": "0.5·CFA-phase trace"}
    for key, term in names.items():
        t = TrainConfig(**{key: 0.5})
        assert t.loss_formula() == f"L1 + {term}", key
        assert abs(float(system_loss(recon, truth, t, period=4)) - float(F.l1_loss(recon, truth))) > 1e-6, key
    assert load_config("quick").train.loss_formula() == (
        "L1 + 0.1·(1 − SSIM) + 0.05·spectral angle + 1·spectral-gradient L1")


def test_the_training_figure_names_the_runs_loss(tmp_path, monkeypatch):
    """The loss panel is labelled as the whole training loss, titled with the formula when given; the
    validation panel says it is measured on patches."""
    import json

    from hsicam.report import reconstruction

    figures = []
    real_save = reconstruction.save_figure
    monkeypatch.setattr(reconstruction, "save_figure", lambda fig, path: (figures.append(fig), real_save(fig, path)))
    metrics = tmp_path / "metrics.jsonl"
    metrics.write_text("".join(json.dumps(r) + "\n" for r in (
        {"step": 20, "epoch": 0, "train_loss": 0.05}, {"step": 32, "epoch": 1, "val_psnr": 40.0, "val_ssim": 0.9},
        {"step": 40, "epoch": 1, "train_loss": 0.04})))
    reconstruction.plot_training_curves(metrics, tmp_path / "a.png", "L1 + 0.1·(1 − SSIM)")
    reconstruction.plot_training_curves(metrics, tmp_path / "b.png")
    with_formula, without = (fig.axes[0] for fig in figures)
    assert with_formula.get_ylabel() == without.get_ylabel() == "training loss (epoch running mean)"
    assert with_formula.get_title() == "L1 + 0.1·(1 − SSIM)" and without.get_title() == ""
    assert list(with_formula.lines[0].get_ydata()) == [0.05, 0.04]
    assert figures[0].axes[1].get_ylabel() == "PSNR on validation patches (dB)"  # not the whole scenes' figure
    assert Image.open(tmp_path / "a.png").size[0] > 100
