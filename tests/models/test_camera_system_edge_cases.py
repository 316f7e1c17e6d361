"""Mutation guards for the camera system, the camera contract, the reconstruction/tolerance reports and the optics
export (probe mut8b).

Each test kills a hand-made mutant that the other tests let through, asserting against a reference computed here:
the noise drawn from a seeded generator by hand, an adjoint identity with a deliberately wrong adjoint, the power
method's fixed point on a diagonal operator, a state dict's keys, a figure's plotted data, a file read back as JSON.
"""

from __future__ import annotations

import json
import math
import logging
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from conftest import TINY_CAMERA_OVERRIDES
from fab_runs import fab_run  # noqa: F401 - shared fixture
from test_consistency import _Oracle  # a "network" returning a fixed cube
from hsicam.cameras import build_camera
from hsicam.cameras.base import Camera
from hsicam.config import load_config
from hsicam.errors import InputError
from hsicam.models import CameraSystem
from hsicam.sensor import SensorNoise
from hsicam.spectral import Bands


def _cassi(*overrides: str, dtype=torch.float64):
    cfg = load_config(overrides=[*TINY_CAMERA_OVERRIDES, "camera.kind=dd_cassi", *overrides])
    return build_camera(cfg).to(dtype)


# ------------------------------------------------------------------------------------------------
# cameras/base.py
# ------------------------------------------------------------------------------------------------
def test_forward_draws_the_sensor_noise_from_sensor_generator_when_given():
    """Camera.forward(x, generator, sensor_generator=g): the noise is σ·randn drawn from g (by hand here), whatever
    ``generator`` is; without it the noise comes from ``generator``."""
    cam = _cassi("camera.sensor.noise=gaussian", "camera.sensor.sigma=0.05")
    x = torch.rand(1, len(cam.bands), 12, 13, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    clean = cam.A(x)

    def by_hand(seed):
        return clean + 0.05 * torch.randn(clean.shape, generator=torch.Generator().manual_seed(seed), dtype=clean.dtype)

    got = cam(x, torch.Generator().manual_seed(1), sensor_generator=torch.Generator().manual_seed(2))
    torch.testing.assert_close(got, by_hand(2), rtol=0, atol=1e-12)
    torch.testing.assert_close(cam(x, torch.Generator().manual_seed(1)), by_hand(1), rtol=0, atol=1e-12)


class _SumCamera(Camera):
    """y = Σ_c w_c x_c (a band-weighted sum), cropped by ``crop`` px per side (boundary valid when crop > 0), with an
    adjoint scaled by ``adjoint_scale`` (1: the exact adjoint)."""

    kind = "sum_test"

    def __init__(self, adjoint_scale: float = 1.0, crop: int = 0) -> None:
        super().__init__()
        self.bands = Bands.uniform(500, 600, 50)
        self.weights = torch.tensor([0.2, 0.5, 0.3], dtype=torch.float64)
        self.scale, self.crop = adjoint_scale, crop
        self.boundary = "valid" if crop else "same"
        self.noise = SensorNoise("none")

    @property
    def margin(self) -> int:
        return 2 * self.crop

    def A(self, x):  # noqa: N802
        c = self.crop
        y = (x * self.weights[:, None, None]).sum(dim=1, keepdim=True)
        return y[..., c : y.shape[-2] - c, c : y.shape[-1] - c]

    def A_adjoint(self, y):  # noqa: N802
        c = self.crop
        return self.scale * torch.nn.functional.pad(y, (c, c, c, c)) * self.weights[:, None, None]


def test_adjointness_error_is_the_size_of_the_mismatch_whichever_its_sign():
    """⟨Ax, y⟩ − ⟨x, Aᵀy⟩ = (1 − s)·⟨Ax, y⟩ for an adjoint scaled by s: the error is |1 − s|·⟨Ax, y⟩/(‖Ax‖‖y‖),
    recomputed here from the same draws; an adjoint too large (s > 1, a negative difference) is no adjoint either."""
    for s in (1.0, 2.0, 0.5):
        cam = _SumCamera(s)
        g = torch.Generator().manual_seed(4)
        x = torch.rand((1, 3, 6, 7), generator=g, dtype=torch.float64)
        ax = cam.A(x)
        y = torch.rand(ax.shape, generator=g, dtype=torch.float64)
        want = abs(1 - s) * float((ax * y).sum() / (ax.norm() * y.norm()))
        got = cam.adjointness_error((6, 7), generator=torch.Generator().manual_seed(4))
        assert got == pytest.approx(want, rel=1e-9, abs=1e-15)
        assert (got > 0.1) == (s != 1.0)


@pytest.mark.parametrize("period", [1, 3, 5])
def test_capture_needs_a_sensor_image_of_one_cfa_period(tiny_camera, period):
    """The smallest sensor image capture makes is max(2, CFA period) px per side: the scene needs that plus the
    kernel margin (valid); one pixel less is refused with the user's message naming the CFA period."""
    cam = tiny_camera(f"camera.cfa.period={period}")
    n = max(2, period)
    assert cam.min_sensor_px() == n
    assert cam.min_scene_size() == (n + cam.margin, n + cam.margin)
    cam.check_capture_size((n + cam.margin, n + cam.margin))
    with pytest.raises(InputError) as err:
        cam.check_capture_size((n + cam.margin - 1, n + cam.margin + 4), "s.npy")
    msg = str(err.value)
    assert msg.startswith(f"s.npy: the scene is {n + cam.margin - 1}×{n + cam.margin + 4} px, too small: this camera "
                          f"needs {n + cam.margin}×{n + cam.margin} px, a sensor image of at least {n}×{n} px")
    assert ("(one CFA period)" in msg) == (period > 2)


def test_default_snapshot_maps_the_cube_its_scene_size_names_onto_the_sensor_window():
    """OperatorSnapshot.scene_size(h, w) is the cube that A maps onto an (h, w) sensor window: for a valid camera
    cropping 2 px per side, (h + 4, w + 4) (A applied to it gives (h, w)), and Aᵀ of the window has that size."""
    snap = _SumCamera(crop=2).snapshot()
    hw = (5, 9)
    assert snap.scene_size(hw) == (9, 13)
    x = torch.rand(1, 3, *snap.scene_size(hw), dtype=torch.float64)
    assert tuple(snap.A(x).shape[-2:]) == hw
    assert tuple(snap.A_adjoint(torch.ones(1, 1, *hw, dtype=torch.float64)).shape[-2:]) == snap.scene_size(hw)


@pytest.mark.parametrize("peak, warns", [(3.9, False), (4.5, True)])
def test_capture_warns_for_a_scene_peak_just_above_two_stops_over_full_scale(peak, warns, caplog):
    """A scene whose peak is above 4 (two stops over full scale, SCENE_PEAK_WARN) is warned about, naming the source
    and the peak; 3.9 is a highlight, not warned about."""
    cam = _SumCamera()
    x = torch.full((1, 3, 4, 4), 0.5, dtype=torch.float64)
    x[0, 1, 2, 2] = peak
    with caplog.at_level(logging.WARNING, logger="hsicam.cameras.base"):
        cam.capture(x, source="s.npy")
    msgs = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert bool(msgs) == warns
    if warns:
        assert msgs[0].startswith(f"s.npy: the scene's peak value is {peak:.4g}, far above 1")


def test_capture_size_refusal_offers_boundary_same_only_when_it_would_help(tiny_camera):
    """A scene of at least n px per side (n = the smallest sensor image) fits boundary=same, so the refusal offers
    it; a scene below n px fits neither, and the refusal says only "use a larger scene"."""
    cam = tiny_camera("camera.cfa.period=3")
    n, m = cam.min_sensor_px(), cam.margin
    assert m > 0
    with pytest.raises(InputError) as err:
        cam.check_capture_size((n, n + m))
    assert str(err.value).endswith(f"to the {m + 1}-px PSF kernel; use a larger scene or boundary=same")
    with pytest.raises(InputError) as err:
        cam.check_capture_size((n - 1, n + m))
    assert str(err.value).endswith(f"to the {m + 1}-px PSF kernel; use a larger scene")


# ------------------------------------------------------------------------------------------------
# report/reconstruction.py, report/tolerance.py
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("peak", [0.05, 0.0099, 0.005, 0.00125, 3e-7, 0.5, 2.0])
def test_spectra_exponent_divides_only_spectra_peaking_below_one_percent(peak):
    """Spectra peaking below 0.01 are divided by 10^e so that their peak lies in [1, 10) (e = ⌊log10 peak⌋); a peak
    of 0.01 or more keeps e = 0 (the ticks of 0.05 are short already)."""
    from hsicam.report.reconstruction import spectra_exponent

    spectra = [np.array([0.0, -peak / 3, peak / 2]), np.array([peak, 0.0])]
    e = spectra_exponent(spectra)
    if peak >= 0.01:
        assert e == 0
    else:
        assert 1 <= peak / 10.0**e < 10


def _scene_result(name, seed, c=3, h=8, w=12):
    g = np.random.default_rng(seed)
    truth = g.random((c, h, w))
    return SimpleNamespace(name=name, truth=truth, estimate=truth + 0.1 * g.standard_normal((c, h, w)),
                           metrics={"psnr": 30.0, "ssim": 0.9})


def test_reconstruction_figure_plots_the_mean_error_and_the_spectra_at_its_marked_pixels(monkeypatch, tmp_path):
    """The figure's data, read back from its axes: the error map is mean_c |est − gt| (computed here), the spectra
    panel plots gt[:, y, x] and est[:, y, x] at (h/4, w/4), (h/2, w/2), (3h/4, 3w/4) of a non-square scene, and only
    ``max_rows`` rows are drawn, the title naming the total."""
    import hsicam.report.reconstruction as rec

    figs = []
    monkeypatch.setattr(rec, "save_figure", lambda fig, path: figs.append(fig))
    bands = Bands.uniform(500, 600, 50)
    results = [_scene_result(f"s{i}", i) for i in range(3)]
    rec.plot_reconstructions(results, bands, tmp_path / "r.png", max_rows=2)
    (fig,) = figs
    rows = np.array(fig.axes[: 8]).reshape(2, 4)  # the 2 × 4 grid first, then the colour bars
    assert fig._suptitle.get_text().startswith("the first 2 of 3 scenes")
    for r, row in zip(results, rows):
        gt, est = r.truth, r.estimate
        np.testing.assert_allclose(row[2].images[0].get_array(), np.abs(est - gt).mean(axis=0), rtol=1e-12)
        h, w = gt.shape[1:]
        lines = row[3].get_lines()
        pts = [(h // 4, w // 4), (h // 2, w // 2), (3 * h // 4, 3 * w // 4)]
        assert len(lines) == 6
        for k, (y, x) in enumerate(pts):
            np.testing.assert_allclose(lines[2 * k].get_ydata(), gt[:, y, x])
            np.testing.assert_allclose(lines[2 * k + 1].get_ydata(), est[:, y, x])
            np.testing.assert_allclose(lines[2 * k].get_xdata(), bands.centers_nm)


def test_training_curves_plot_the_validations_during_training_not_the_final_record(monkeypatch, tmp_path):
    """metrics.jsonl read back: the loss panel plots every train_loss, the validation panel the val_psnr / val_ssim
    of the records without ``final`` (the final record repeats the best step's scores, not a point of the curve)."""
    import hsicam.report.reconstruction as rec

    recs = [{"step": 1, "train_loss": 0.5}, {"step": 2, "train_loss": 0.25},
            {"step": 2, "val_psnr": 20.0, "val_ssim": 0.5},
            {"step": 4, "train_loss": 0.125}, {"step": 4, "val_psnr": 22.0, "val_ssim": 0.6},
            {"step": 4, "val_psnr": 99.0, "val_ssim": 0.99, "final": True}]
    path = tmp_path / "metrics.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in recs))
    figs = []
    monkeypatch.setattr(rec, "save_figure", lambda fig, p: figs.append(fig))
    rec.plot_training_curves(path, tmp_path / "c.png")
    a0, a1, b = figs[0].axes
    np.testing.assert_array_equal(a0.get_lines()[0].get_xdata(), [1, 2, 4])
    np.testing.assert_array_equal(a0.get_lines()[0].get_ydata(), [0.5, 0.25, 0.125])
    np.testing.assert_array_equal(a1.get_lines()[0].get_xdata(), [2, 4])
    np.testing.assert_array_equal(a1.get_lines()[0].get_ydata(), [20.0, 22.0])
    np.testing.assert_array_equal(b.get_lines()[0].get_ydata(), [0.5, 0.6])


def test_levels_text_of_a_study_that_does_not_record_bracketing_states_the_requirement():
    """A tolerance.json written before ``levels_bracketed`` was recorded: its levels within 1 dB are the requirement
    (as then); the key only ever withholds it when recorded False."""
    from hsicam.report.tolerance import levels_text

    assert levels_text({"sweeps": {"levels": {}}, "summary": {"min_levels_within_1db": 8}}) == "levels ≥ 8"
    assert levels_text({"sweeps": {"levels": {}}, "summary": {"min_levels_within_1db": 8, "levels_bracketed": False}}) \
        == "levels: 8 within 1 dB, not bracketed"
    assert levels_text({"sweeps": {"sigma_height_nm": {}}, "summary": {"min_levels_within_1db": 8}}) == ""


def _sweep(values, psnr):
    return {"values": values, "psnr": psnr, "psnr_std": [0.0] * len(values)}


def _tolerance_figure(monkeypatch, tmp_path, result):
    import hsicam.io
    from hsicam.report.tolerance import plot_tolerance

    figs = []
    monkeypatch.setattr(hsicam.io, "save_figure", lambda fig, p: figs.append(fig))
    plot_tolerance(result, tmp_path / "t.png")
    return figs[0].axes


def _hline(ax, label):
    (line,) = [ln for ln in ax.get_lines() if ln.get_label() == label]
    return float(line.get_ydata()[0])


def test_tolerance_figure_draws_the_one_db_line_below_each_panels_reference(monkeypatch, tmp_path):
    """The −1 dB line lies 1 dB below the panel's reference: the nominal PSNR, or for the shift panel the no-shift
    reference model's (``shift_reference``), drawn with the nominal as a separate line."""
    result = {"metric": "PSNR, per band", "nominal": {"psnr": 30.0},
              "shift_reference": {"psnr": 31.5, "pupil_oversample": 3},
              "sweeps": {"sigma_height_nm": _sweep([0, 10], [30.0, 29.0]), "levels": _sweep([4, 8], [28.0, 29.9]),
                         "shift_x_cells": _sweep([0, 0.5], [31.5, 30.0]),
                         "sensor_distance_um": _sweep([0, 5], [30.0, 29.5])}}
    ax = _tolerance_figure(monkeypatch, tmp_path, result)
    for i in (0, 1, 3):
        assert _hline(ax[i], "−1 dB") == 29.0 and _hline(ax[i], "nominal") == 30.0
    assert _hline(ax[2], "−1 dB") == 30.5
    assert _hline(ax[2], "nominal (trained model)") == 30.0
    assert _hline(ax[2], "no shift, 3 samples/cell") == 31.5


def test_tolerance_figure_says_why_a_skipped_shift_sweep_was_not_studied(monkeypatch, tmp_path):
    """tolerance.json records a camera without a DOE under ``skipped`` by sweep family (``shift`` for both shift
    sweeps): the panel says "not studied:" and the reason, and plots nothing."""
    why = "the camera has no DOE"
    result = {"metric": "PSNR", "nominal": {"psnr": 30.0},
              "skipped": {"sigma_height_nm": why, "levels": why, "shift": why},
              "sweeps": {"sensor_distance_um": _sweep([0, 5], [30.0, 29.5])}}
    ax = _tolerance_figure(monkeypatch, tmp_path, result)
    for i in (0, 1, 2):
        assert [t.get_text() for t in ax[i].texts] == ["not studied:\n" + why]
        assert len(ax[i].get_lines()) == 0
    assert len(ax[3].texts) == 0 and _hline(ax[3], "−1 dB") == 29.0


# ------------------------------------------------------------------------------------------------
# models/system.py
# ------------------------------------------------------------------------------------------------
def _consistency(*overrides: str):
    return load_config(overrides=["model.consistency.iterations=1", *overrides]).model.consistency


def test_with_camera_keeps_the_network_and_its_settings_but_not_the_step_camera(tiny_camera):
    """with_camera: the same network object, consistency, autocast dtype, linear step and its missing-note, imaging
    through the new camera; the step camera (a nominal design for another camera) is not carried over."""
    cam, other = tiny_camera(), tiny_camera("camera.cfa.period=5")
    c = _consistency()
    model = CameraSystem(cam, _Oracle(torch.zeros(1)), c)
    model.autocast_dtype = torch.bfloat16
    model.linear_step = torch.ones(9, 3, 5, 5)
    model.linear_step_missing = "run r has no linear step"
    model.step_camera = tiny_camera()
    out = model.with_camera(other)
    assert out.camera is other and out.net is model.net and out.consistency is c
    assert out.autocast_dtype is torch.bfloat16
    assert out.linear_step is model.linear_step and out.linear_step_missing == "run r has no linear step"
    assert out.step_camera is None


def test_step_camera_is_a_reference_not_a_submodule(tiny_camera):
    """A step camera set on the model is neither a submodule nor in the state dict (the checkpoint holds the
    imaging camera and the network only), and .to() leaves it alone."""
    cam = tiny_camera()
    model = CameraSystem(cam, _Oracle(torch.zeros(1)), _consistency())
    keys = set(model.state_dict())
    step = tiny_camera()
    model.step_camera = step
    assert model.step_camera is step
    assert set(model.state_dict()) == keys and "step_camera" not in dict(model.named_children())
    model.to(torch.float64)
    assert next(step.parameters()).dtype == torch.float32


@pytest.mark.parametrize("kind, takes", [("dd_cassi", True), ("sd_cassi", False)])
def test_consistency_applies_to_cassi_cameras_whose_scene_grid_is_the_sensors(kind, takes, caplog):
    """DD-CASSI images a scene on the sensor's grid, so the step applies; SD-CASSI's scene grid is wider than the
    sensor (the dispersion), so its reconstructions skip the step, warning once."""
    cam = build_camera(load_config(overrides=[*TINY_CAMERA_OVERRIDES, f"camera.kind={kind}"]))
    model = CameraSystem(cam, _Oracle(torch.zeros(1)), _consistency())
    assert model.camera_takes_consistency is takes
    with caplog.at_level(logging.WARNING, logger="hsicam.models.system"):
        assert model.consistency_on is takes
        assert model.consistency_on is takes
    warned = [r.getMessage() for r in caplog.records if "scene grid is not the sensor's" in r.getMessage()]
    assert len(warned) == (0 if takes else 1)


# ------------------------------------------------------------------------------------------------
# export/tolerance.py, export/__init__.py
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("run", [None, {}, {"path": "old", "weights_sha256": ""}, {"weights_sha256": None}])
def test_a_study_without_a_recorded_weights_hash_is_cited_unchecked(run, tmp_path, caplog):
    """A tolerance.json whose ``run`` records no weights hash (absent, empty, null) cannot be checked against the run
    exported: it is cited as given, ``run_checked`` false, with a warning, and the run is not looked at."""
    from hsicam.export.tolerance import TOLERANCE_FORMAT, read_tolerance_study

    data = {"format": TOLERANCE_FORMAT, "nominal": {"psnr": 31.25}, "summary": {"x": 1}}
    if run is not None:
        data["run"] = run
    path = tmp_path / "tolerance.json"
    path.write_text(json.dumps(data))
    with caplog.at_level(logging.WARNING, logger="hsicam.export.tolerance"):
        got = read_tolerance_study(path, tmp_path / "no-such-run")
    assert got == {"source": str(path), "nominal_psnr_db": 31.25, "summary": {"x": 1}, "run_checked": False}
    assert any("does not record which run it studied" in r.getMessage() for r in caplog.records)


def test_spec_json_read_back_states_the_runs_optics(fab_run, tmp_path):
    """spec.json, read back as JSON, against the run's resolved config: aperture diameter = 2 × radius, sensor
    distance (the focal length at the design wavelength for an object at infinity) in mm, band FWHMs, sensor noise
    and bit depth, the noise trained with, the stop at the DOE, and the files listed without the hidden marker."""
    from hsicam.export import export_optics
    from hsicam.runs.folder import load_run

    cfg, model = load_run(fab_run, "cpu")
    out = tmp_path / "fab"
    export_optics(fab_run, out, levels=4)
    spec = json.loads((out / "spec.json").read_text(encoding="utf-8"))
    radius_mm = cfg.camera.aperture_radius_mm
    assert spec["aperture"]["radius_mm"] == pytest.approx(radius_mm)
    assert spec["aperture"]["diameter_mm"] == pytest.approx(2 * radius_mm)
    assert spec["aperture"]["stop"] == "at the DOE, centred on the lens axis"
    assert spec["sensor_distance_mm"] == pytest.approx(cfg.camera.lens.focal_length_mm)
    assert spec["bands"]["fwhm_nm"] == pytest.approx(list(model.camera.bands.fwhm_nm))
    assert spec["bands"]["fwhm_nm"] != spec["bands"]["centers_nm"]
    assert spec["sensor"]["noise"] == cfg.camera.sensor.noise
    assert spec["sensor"]["bit_depth"] == cfg.camera.sensor.bit_depth
    assert spec["tolerances"]["trained_with"] == {"sigma_height_nm": list(cfg.train.sigma_height_nm),
                                                  "sensor_sigma": list(cfg.train.sensor_sigma),
                                                  "camera_sigma_height_nm": cfg.camera.doe.sigma_height_nm}
    assert spec["files"] == sorted(p.name for p in out.iterdir() if not p.name.startswith("."))


def test_export_levels_bounds_are_those_of_the_config_inclusive(fab_run, tmp_path):
    """--levels takes 2..2^16, both ends included (camera.doe.quantization_levels' range): 2^16 levels are exported
    (16 binary masks), 1 and 2^16 + 1 are refused with the range in the message, before any file is written."""
    from hsicam.export import export_optics

    spec = export_optics(fab_run, tmp_path / "top", levels=2**16)
    assert spec["doe"]["quantized"]["levels"] == 2**16
    assert json.loads((tmp_path / "top" / "spec.json").read_text())["doe"]["quantized"]["levels"] == 65536
    for bad in (1, 2**16 + 1):
        with pytest.raises(InputError) as err:
            export_optics(fab_run, tmp_path / f"bad{bad}", levels=bad)
        assert str(err.value) == ("--levels must be in 2..65536 (the range of camera.doe.quantization_levels), "
                                  f"got {bad}")
        assert not (tmp_path / f"bad{bad}").exists()


def test_spec_trained_with_keeps_the_cameras_own_height_noise_apart_from_the_training_range(fab_run):
    """``tolerances.trained_with``: the training's σ_p range and σ_s range as configured, and the camera's own
    σ_p (camera.doe.sigma_height_nm), each from its own key."""
    from hsicam.export import _tolerances

    cfg = load_config(overrides=[*TINY_CAMERA_OVERRIDES, "train.sigma_height_nm=[5, 10]",
                                 "train.sensor_sigma=[0, 0.01]",
                                 "camera.doe.sigma_height_nm=3"])
    got = _tolerances(fab_run, cfg, None)["trained_with"]
    assert got == {"sigma_height_nm": [5.0, 10.0], "sensor_sigma": [0.0, 0.01], "camera_sigma_height_nm": 3.0}


def test_reconstruct_takes_the_landweber_steps_in_eval_mode_only(tiny_camera):
    """In training mode reconstruct is the network's output as it is; in eval mode the Landweber step moves it, to
    consistency_step's result from the same estimate (computed here through the camera's nominal snapshot)."""
    from hsicam.models.consistency import consistency_step

    cam = tiny_camera(dtype=torch.float64)
    x0 = torch.full((1, len(cam.bands), 24, 24), 0.3, dtype=torch.float64)
    c = _consistency("model.consistency.psf_energy=1")
    model = CameraSystem(cam, _Oracle(x0), c)
    y = torch.rand(1, 1, 24, 24, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    with torch.no_grad():
        assert torch.equal(model.train().reconstruct(y), x0)
        got = model.eval().reconstruct(y)
        want = consistency_step(cam.snapshot(nominal=True), y, x0, damping=c.damping, iterations=1, psf_energy=1.0,
                                extend="replicate", spectral_prior=c.spectral_prior, tv_weight=c.tv_weight)
    assert (got - x0).abs().max() > 1e-3
    torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-12)


def test_spec_of_a_singlet_states_its_focal_length_at_the_design_wavelength(tmp_path):
    """E13 (left open by mut8b): a singlet's spec.json focal length is R / (n(λ0) − 1) at the design wavelength
    587.6 nm, n from Malitson's Sellmeier formula for fused silica written out here, not the first band's (420 nm,
    0.3 mm shorter); the per-band list follows the same formula at each band."""
    from hsicam.config import dump_yaml
    from hsicam.export import export_optics
    from hsicam.models import CameraSystem
    from hsicam.runs.checkpoint import save_weights

    def n_fused_silica(nm: float) -> float:
        um2 = (nm / 1000.0) ** 2
        return math.sqrt(1 + 0.6961663 * um2 / (um2 - 0.0684043 ** 2) + 0.4079426 * um2 / (um2 - 0.1162414 ** 2)
                         + 0.8974794 * um2 / (um2 - 9.896161 ** 2))

    run = tmp_path / "singlet"
    run.mkdir()
    cfg = load_config("tiny", [*TINY_CAMERA_OVERRIDES, "camera.lens.model=singlet"])
    (run / "config.yaml").write_text(dump_yaml(cfg), encoding="utf-8")
    model = CameraSystem.from_config(cfg)
    save_weights(run / "model.safetensors", model, model.bands)
    export_optics(run, tmp_path / "fab", levels=4)
    lens = json.loads((tmp_path / "fab" / "spec.json").read_text(encoding="utf-8"))["lens"]
    radius = cfg.camera.lens.radius_of_curvature_mm
    assert lens["model"] == "singlet" and lens["design_wavelength_nm"] == 587.6
    assert lens["focal_length_mm"] == pytest.approx(radius / (n_fused_silica(587.6) - 1), rel=1e-6)
    assert lens["focal_length_per_band_mm"] == pytest.approx(
        [radius / (n_fused_silica(nm) - 1) for nm in model.camera.bands.centers_nm], rel=1e-6)
    assert lens["focal_length_mm"] - lens["focal_length_per_band_mm"][0] > 0.2  # the first band's is not the design's
