"""Guards found by mutation testing of scoring (engine/evaluate.py) and of the linear step
(engine/linear_step.py): each test kills a hand-made mutant (a wrong constant, an off-by-one, a dropped
normalisation, a skipped branch) that the rest of the suite let through, and checks the behaviour against a
reference computed here (numpy on the scored pixels, least squares by hand), not against the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hsicam.errors import InputError
from hsicam.spectral import Bands


# --------------------------------------------------------------------------------------------
# engine/evaluate.py
# --------------------------------------------------------------------------------------------
class _ToyCamera(torch.nn.Module):
    """A camera for scoring tests: the sensor image is the band sum; it remembers the scene it imaged, the seeds
    of its two generators and its noise levels at each capture."""

    boundary, margin, kind = "same", 0, "toy"

    def __init__(self, n_bands: int, levels: dict[str, float] | None = None) -> None:
        super().__init__()
        self.bands = Bands.uniform(420, 420 + 10 * (n_bands - 1), 10)
        self.levels = dict(levels or {"sensor_sigma": 0.0})
        self.captures: list[dict] = []

    def noise_levels(self) -> dict[str, float]:
        return dict(self.levels)

    def set_noise(self, **levels: float) -> None:
        self.levels.update(levels)

    def forward(self, scene, generator=None, sensor_generator=None):
        self.captures.append({"scene": scene, "seed": generator.initial_seed(),
                              "sensor_seed": sensor_generator.initial_seed(), "levels": dict(self.levels)})
        return scene.sum(dim=1, keepdim=True)


def _toy_method(cam, offset, border_px=0):
    from hsicam.engine.methods import Method

    def reconstruct(sensor):  # the scene imaged last, plus an offset that may depend on the capture's seed
        last = cam.captures[-1]
        return last["scene"] + offset(last["seed"], last["scene"])

    return Method("toy", cam, reconstruct, lambda s: s, border_px=border_px)


def _toy_scenes(n, hw=(20, 24), c=3, seed=0):
    rng = np.random.default_rng(seed)
    return [torch.from_numpy((0.5 + 0.3 * rng.random((c, *hw))).astype(np.float32)) for _ in range(n)]


def test_scores_cover_the_scene_less_the_border_and_the_estimate_is_clipped_to_one():
    """border_px = 3: truth and estimate are the scene less 3 px a side, and the RMSE is that of the estimate clipped
    to [0, 1] on those pixels (numpy); the border, 0.4 off, is not scored; an estimate above 1 counts as 1."""
    from hsicam.engine.evaluate import evaluate_method

    b = 3
    scenes = _toy_scenes(2)

    def offset(seed, scene):
        d = torch.full_like(scene, 0.4)
        d[..., b:-b, b:-b] = 0.05
        d[..., b:-b, b:b + 4] = 0.5  # above 1 (scene values 0.5-0.8): clipped
        return d

    cam = _ToyCamera(3)
    res = evaluate_method(_toy_method(cam, offset, border_px=b), scenes, ["a", "b"])
    for r, scene in zip(res, scenes):
        s = scene.numpy()
        est = np.clip(s + offset(0, scene).numpy(), 0.0, 1.0)[:, b:-b, b:-b]
        assert r.truth.shape == r.estimate.shape == (3, s.shape[1] - 2 * b, s.shape[2] - 2 * b)
        np.testing.assert_allclose(r.truth, s[:, b:-b, b:-b], rtol=0, atol=0)
        np.testing.assert_allclose(r.estimate, est, rtol=0, atol=1e-6)
        np.testing.assert_allclose(r.metrics["rmse"], np.sqrt(np.mean((est - s[:, b:-b, b:-b]) ** 2)), rtol=1e-5)


def test_several_seeds_give_the_mean_and_spread_over_seeds_and_keep_the_first_seeds_estimate():
    """Seeds (3, 7) with an estimate off by 0.01 · (seed + 1): RMSE 0.04 and 0.08 per seed, mean 0.06, spread
    (np.std over the seeds) 0.02; the estimate kept is seed 3's, and the result says so."""
    from hsicam.engine.evaluate import TestNoise, evaluate_method

    scenes = _toy_scenes(1)
    cam = _ToyCamera(3)
    method = _toy_method(cam, lambda seed, scene: torch.full_like(scene, 0.01 * (seed + 1)))
    (r,) = evaluate_method(method, scenes, ["a"], TestNoise(seeds=(3, 7)))
    per = [0.01 * (s + 1) for s in (3, 7)]
    np.testing.assert_allclose([m["rmse"] for m in r.metrics_per_seed], per, rtol=1e-5)
    assert [m["seed"] for m in r.metrics_per_seed] == [3, 7]
    np.testing.assert_allclose(r.metrics["rmse"], np.mean(per), rtol=1e-5)
    np.testing.assert_allclose(r.metrics_std["rmse"], np.std(per), rtol=1e-4)
    assert r.seed == 3
    np.testing.assert_allclose(r.estimate, scenes[0].numpy() + per[0], rtol=0, atol=1e-6)


def test_test_noise_levels_reach_the_camera_while_scoring_and_are_restored_after():
    """TestNoise σ_p = 20 nm and σ_s = 0: every capture is made under them and the result records them; the camera's
    own levels (5 nm, 0.01) are back afterwards."""
    from hsicam.engine.evaluate import TestNoise, evaluate_method

    own = {"sensor_sigma": 0.01, "sigma_height_nm": 5.0}
    cam = _ToyCamera(3, own)
    method = _toy_method(cam, lambda seed, scene: torch.zeros_like(scene))
    (r,) = evaluate_method(method, _toy_scenes(1), ["a"], TestNoise(sigma_height_nm=20.0, sensor_sigma=0.0, seeds=(0, 1)))
    want = {"sensor_sigma": 0.0, "sigma_height_nm": 20.0}
    assert [c["levels"] for c in cam.captures] == [want, want]
    assert r.noise == want
    assert cam.noise_levels() == own


def test_each_scenes_capture_seed_is_its_own_and_the_same_for_every_method():
    """Under one noise seed, scenes of the same size get different sensor-noise seeds (their own fields), the same
    scene gets the same one for another method, and the DOE draw's seed is the noise seed itself."""
    from hsicam.engine.evaluate import TestNoise, evaluate_method

    seeds = {}
    for run in range(2):
        cam = _ToyCamera(3)
        evaluate_method(_toy_method(cam, lambda seed, scene: torch.zeros_like(scene) + 0.01 * run), _toy_scenes(3),
                        ["a", "b", "c"], TestNoise(seeds=(4,)))
        assert [c["seed"] for c in cam.captures] == [4, 4, 4]
        seeds[run] = [c["sensor_seed"] for c in cam.captures]
    assert len(set(seeds[0])) == 3 and seeds[0] == seeds[1]


def test_the_grey_reference_is_the_sensor_times_the_pixel_mean_training_spectrum():
    """Training scenes of different sizes: the mean spectrum is over all their pixels (numpy on the pixels laid
    side by side), and the estimate is the sensor image times that spectrum over its mean."""
    from types import SimpleNamespace

    from hsicam.engine.evaluate import grey_reference

    rng = np.random.default_rng(1)
    scenes = [torch.from_numpy(rng.random((4, h, w)).astype(np.float32) * (i + 1))
              for i, (h, w) in enumerate([(5, 6), (12, 10), (3, 3)])]
    pixels = np.concatenate([s.numpy().reshape(4, -1) for s in scenes], axis=1).astype(np.float64)
    spectrum = pixels.mean(axis=1)
    cam = _ToyCamera(4)
    method = grey_reference(SimpleNamespace(camera=cam, target=lambda s: s), scenes)
    np.testing.assert_allclose(method.info["mean_spectrum"], spectrum, rtol=1e-6)
    sensor = torch.from_numpy(rng.random((1, 1, 7, 8)).astype(np.float32))
    want = sensor.numpy() * (spectrum / spectrum.mean())[None, :, None, None]
    np.testing.assert_allclose(method.reconstruct(sensor).numpy(), want, rtol=1e-6)


def test_the_mean_sam_leaves_out_scenes_without_a_spectral_angle_and_names_them():
    """A scene whose SAM is NaN (its truth all zero) is listed under sam_undefined and the mean SAM is that of the
    other scenes (numpy nanmean); the other means are over every scene."""
    from hsicam.engine.evaluate import SceneResult, summarize

    rows = [SceneResult(n, {"psnr": p, "ssim": 0.9, "sam": s}, None, None, 1.0)
            for n, p, s in [("a", 30.0, 4.0), ("dark", 40.0, float("nan")), ("c", 20.0, 6.0)]]
    out = summarize(rows)
    assert out["sam_undefined"] == ["dark"]
    np.testing.assert_allclose(out["mean"]["sam"], np.nanmean([4.0, np.nan, 6.0]))
    np.testing.assert_allclose(out["mean"]["psnr"], np.mean([30.0, 40.0, 20.0]))


def test_a_scored_area_of_exactly_the_ssim_window_is_scored_and_one_pixel_less_is_refused_before_any_work():
    """SSIM needs 11×11 px: a scene whose area less the border is exactly that is scored; one whose area is a pixel
    short is refused with its one-line message before any scene is reconstructed (the first, good, scene
    included)."""
    from hsicam.engine.evaluate import evaluate_method
    from hsicam.metrics import SSIM_WINDOW_PX

    b, w = 2, SSIM_WINDOW_PX
    cam = _ToyCamera(3)
    calls = []
    method = _toy_method(cam, lambda seed, scene: calls.append(1) or torch.zeros_like(scene), border_px=b)
    (r,) = evaluate_method(method, _toy_scenes(1, (w + 2 * b, w + 2 * b + 3)), ["ok"])
    assert r.truth.shape[-2:] == (w, w + 3)
    calls.clear()
    scenes = _toy_scenes(1, (w + 2 * b, w + 2 * b)) + _toy_scenes(1, (w + 2 * b - 1, 40))
    with pytest.raises(InputError, match=rf"small: scene of {w + 2 * b - 1}×40 px leaves {w - 1}×{40 - 2 * b} px"):
        evaluate_method(method, scenes, ["ok", "small"])
    assert calls == []


def test_pixels_whose_truth_is_all_zero_are_counted_as_left_out_of_sam():
    """A scene with 7 scored pixels whose spectrum is zero in every band (and one pixel zero in one band only, which
    keeps its angle): sam_excluded_px is 7, counted by numpy on the scored truth."""
    from hsicam.engine.evaluate import evaluate_method

    scene = _toy_scenes(1, (16, 16))[0]
    rng = np.random.default_rng(4)
    for y, x in rng.choice(16, size=(7, 2), replace=False):
        scene[:, y, x] = 0.0
    scene[1, 15, 15] = 0.0
    cam = _ToyCamera(3)
    (r,) = evaluate_method(_toy_method(cam, lambda seed, s: torch.zeros_like(s)), [scene], ["dark spots"])
    assert r.sam_excluded_px == int(np.count_nonzero(np.all(r.truth == 0, axis=0))) == 7


def test_the_300_db_note_is_given_only_where_a_band_dark_in_the_truth_is_estimated_exactly_zero(tmp_path, caplog):
    """A scene whose band 1 is zero at every pixel has no ERGAS, whatever the estimate. Estimated exactly 0 there,
    that band scores 300 dB (the mean PSNR over 3 bands is then above 100 dB) and the scene is listed in
    exact_zero_bands, with the note in results.md and on the console; estimated 0.01 there (a finite PSNR, 40 dB),
    no band is exact and no note tells of one (session 76's hunt: the note came with every undefined ERGAS, beside a
    mean PSNR of 9.14 dB), while the ERGAS line stays."""
    import argparse
    import logging

    from hsicam.cli.evaluate import _print_means
    from hsicam.engine.evaluate import evaluate_method, summarize, write_results

    dark = _toy_scenes(1, (16, 16))[0]
    dark[1] = 0.0
    lit = _toy_scenes(1, (16, 16), seed=1)[0]
    for name, in_band in (("exact", 0.0), ("close", 0.01)):
        def offset(seed, scene, in_band=in_band):  # +0.02 on bands 0 and 2; band 1 (zero in the truth) set to in_band
            out = torch.full_like(scene, 0.02)
            out[:, 1] = in_band - scene[:, 1]
            return out

        results = evaluate_method(_toy_method(_ToyCamera(3), offset), [dark, lit], ["dark", "lit"])
        want = [int(np.sum(np.all(r.truth == 0, axis=(1, 2)) & np.all(r.estimate == 0, axis=(1, 2)))) for r in results]
        assert [r.exact_zero_bands for r in results] == want == ([1, 0] if name == "exact" else [0, 0])
        psnr_dark = results[0].metrics["psnr"]
        assert psnr_dark > 100.0 if name == "exact" else psnr_dark < 100.0
        summary = summarize(results, method=name)
        assert summary["ergas_undefined"] == ["dark"]
        assert summary.get("exact_zero_bands") == (["dark"] if name == "exact" else None)
        out = tmp_path / name
        out.mkdir()
        write_results(out, summary)
        md = (out / "results.md").read_text(encoding="utf-8")
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            _print_means(argparse.Namespace(method=name), summary, 2, out)
        note = "- PSNR of dark: a band whose truth is zero at every scored pixel scores 300 dB"
        assert "- ERGAS undefined (a band of the truth is zero at every scored pixel) for dark;" in md
        assert (note in md) == (name == "exact")
        assert ("scores 300 dB" in caplog.text) == (name == "exact")


# --------------------------------------------------------------------------------------------
# engine/linear_step.py
# --------------------------------------------------------------------------------------------
def _linear_fit_setup(tiny_camera):
    from types import SimpleNamespace

    cam = tiny_camera().double()
    r = cam.margin // 2

    def target(scene):
        return scene[..., r: scene.shape[-2] - r, r: scene.shape[-1] - r]

    rng = np.random.default_rng(0)
    size = cam.margin + 18
    scenes = [torch.from_numpy(rng.random((len(cam.bands), size, size)).astype(np.float32)).double() for _ in range(3)]
    return cam, SimpleNamespace(camera=cam, target=target), scenes, target


def _residual(cam, target, scenes, weight):
    from hsicam.models.demosaic import phase_linear

    psf = cam.snapshot(nominal=True).psf
    total = 0.0
    for s in scenes:
        with torch.no_grad():
            sensor = cam.A(s[None], psf)
            total += float((phase_linear(sensor, weight.double()) - target(s[None])).square().sum())
    return total


def test_the_linear_map_is_fitted_through_the_nominal_psfs_whatever_the_height_noise(tiny_camera):
    """The filters are fitted on noise-free images through the nominal DOE: a camera with σ_p = 80 nm of height
    noise gives the filters of the same camera at σ_p = 0, every time (no PSF draw enters the fit)."""
    from hsicam.engine.linear_step import fit_linear_map

    cam, model, scenes, _ = _linear_fit_setup(tiny_camera)
    ref = fit_linear_map(model, scenes, window=5)
    cam.set_noise(sigma_height_nm=80.0)
    torch.manual_seed(0)
    a = fit_linear_map(model, scenes, window=5)
    b = fit_linear_map(model, scenes, window=5)
    torch.testing.assert_close(a, ref, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(b, ref, rtol=1e-6, atol=1e-9)


def test_without_the_flat_field_constraint_the_fit_is_the_unconstrained_least_squares_optimum(tiny_camera):
    """flat_field=False is the plain least-squares fit: its error on the training pairs is below that of the
    constrained fit (which gives up some of it to keep flat areas flat), and a small move of any of its taps
    does not lower it (the optimum, up to the 1e-6 ridge); the constrained fit maps a uniform scene to a uniform
    estimate."""
    from hsicam.engine.linear_step import fit_linear_map
    from hsicam.models.demosaic import phase_linear

    cam, model, scenes, target = _linear_fit_setup(tiny_camera)
    free = fit_linear_map(model, scenes, window=5, flat_field=False)
    flat = fit_linear_map(model, scenes, window=5, flat_field=True)
    e_free, e_flat = _residual(cam, target, scenes, free), _residual(cam, target, scenes, flat)
    assert e_free < e_flat * (1 - 1e-3)
    rng = np.random.default_rng(1)
    for _ in range(3):
        step = torch.from_numpy(rng.standard_normal(free.shape)) * 1e-3
        assert _residual(cam, target, scenes, free.double() + step) > e_free
    uniform = torch.full((1, len(cam.bands), cam.margin + 18, cam.margin + 18), 0.5, dtype=torch.float64)
    with torch.no_grad():
        sensor = cam.A(uniform, cam.snapshot(nominal=True).psf)
        est = phase_linear(sensor, flat.double())
        # the filters are float32: each tap off by at most half an ulp, 2⁻²⁴ relative, so an output pixel by at most
        # Σ|w|·|g|·2⁻²⁴ (~4e-6 of the estimate here; the constraint's own error in float64 is far below)
        rounding = phase_linear(sensor.abs(), flat.double().abs()) * 2.0 ** -24
    inner = est[..., 4:-4, 4:-4]  # away from the replicated border
    spread = float((inner - inner.mean(dim=(-2, -1), keepdim=True)).abs().max())
    assert spread <= 2.0 * float(rounding[..., 4:-4, 4:-4].max()) < 1e-4 * float(inner.abs().max())


@pytest.mark.slow
def test_a_linear_consistency_step_of_zero_iterations_is_not_fitted(tmp_path, cache_env):
    """model.consistency kind linear with 0 iterations applies no step, so the run gets no filter file (its fit
    images the whole training split); with 1 iteration the same training fits it."""
    from hsicam.cli import main
    from hsicam.runs.linear_step import LINEAR_STEP_FILE

    for it in (0, 1):
        out = tmp_path / f"run{it}"
        assert main(["train", "--config", "tiny", "--out", str(out), "--set", "train.epochs=1", "--set",
                     "model.consistency.kind=linear", "--set", f"model.consistency.iterations={it}"]) == 0
        assert (out / LINEAR_STEP_FILE).is_file() == (it == 1)
