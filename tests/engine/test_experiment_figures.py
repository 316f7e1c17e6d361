"""The comparison figures of `hsicam experiment compare|ablation` (review of the pictures, session 62): for our
camera's worst and median scene, the truth and every method's reconstruction as the absolute sRGB render
(:func:`hsicam.color.srgb_preview` at exposure 1, the reference), and each method's mean |error| over
bands on one colour scale. Checked on a stand-in camera whose sensor image is the scene itself and methods that
scale it by known gains, so that every estimate and error map is known in closed form; the scenes chosen are read
back from experiment.json's own per-scene rows, the figures from the drawn figure objects."""

from __future__ import annotations

import json

import numpy as np
import torch

from hsicam.config import load_config

GAINS = {"ours": 0.9, "other-a": 0.6, "other-b": 1.2}  # each method's estimate: the scene times its gain, clamped


class SceneAsSensor(torch.nn.Module):
    """A camera whose sensor image is the scene (no noise): a method's estimate is then a function of the scene."""

    boundary, kind = "same", "stand-in"

    def __init__(self, bands):
        super().__init__()
        self.bands = bands

    def noise_levels(self):
        return {}

    def set_noise(self, **levels):
        pass

    def forward(self, scene, generator=None, sensor_generator=None):
        return scene


def test_compare_figures_show_every_method_on_the_worst_and_median_scene(tmp_path, monkeypatch):
    from hsicam.color import srgb_preview
    from hsicam.engine import experiments
    from hsicam.engine.methods import Method
    from hsicam.io import mark_complete
    from hsicam.report import reconstruction
    from hsicam.report.html import build_report

    cfg = load_config("tiny")
    bands = cfg.bands.to_bands()
    rng = np.random.default_rng(0)
    # three scenes of different brightness: a gain's error grows with it (the brightest is the worst)
    cubes = {n: rng.uniform(lo, hi, (len(bands), 24, 24)).astype(np.float32)
             for n, (lo, hi) in {"dim": (0.05, 0.3), "mid": (0.1, 0.7), "bright": (0.5, 1.0)}.items()}
    names = list(cubes)
    scenes = [torch.from_numpy(c) for c in cubes.values()]
    camera = SceneAsSensor(bands)
    specs = [experiments.RunSpec(n) for n in GAINS]

    def build(kind, run_cfg, run):
        gain = GAINS[run.name]
        return Method(run.name, camera, lambda y, g=gain: y * g, lambda x: x)

    kept = []  # (method, keep_arrays, scenes) of every scoring
    real_evaluate = experiments.evaluate_method

    def evaluate(method, scored, scored_names, *a, keep_arrays=True, **k):
        kept.append((method.name, keep_arrays, set(scored_names)))
        return real_evaluate(method, scored, scored_names, *a, keep_arrays=keep_arrays, **k)

    drawn = []
    real_save = reconstruction.save_figure
    monkeypatch.setattr(reconstruction, "save_figure", lambda fig, path: drawn.append(fig) or real_save(fig, path))
    monkeypatch.setattr(experiments, "ensure_trained", lambda run, cfg: "reused")
    monkeypatch.setattr(experiments, "validation_scenes", lambda cfg: (scenes, names))
    monkeypatch.setattr(experiments, "build_method", build)
    monkeypatch.setattr(experiments, "scored_region", lambda camera: None)
    monkeypatch.setattr(experiments, "evaluate_method", evaluate)
    out = tmp_path / "ex"
    experiments._run_experiment("ablation", "tiny", out, cfg, (0,), specs, {n: cfg for n in GAINS}, ())

    result = json.loads((out / "experiment.json").read_text())
    rows = {r["method"]: {s["name"]: s for s in r["scenes"]} for r in result["rows"]}
    by_psnr = sorted(names, key=lambda n: rows["ours"][n]["psnr"])
    assert [(f["role"], f["scene"]) for f in result["figures"]] == [("worst", by_psnr[0]), ("median", by_psnr[1])]
    chosen = {by_psnr[0], by_psnr[1]}
    # only the chosen scenes' arrays were kept: ours none while it chose them, then its two chosen scenes scored
    # again alone, the others' of those two
    assert kept == [("ours", set(), set(names)), ("ours", True, chosen),
                    *((m, chosen, set(names)) for m in list(GAINS)[1:])]
    assert len(drawn) == 2

    for fig, record in zip(drawn, result["figures"]):
        truth = cubes[record["scene"]]
        assert (out / record["file"]).is_file() and record["methods"] == list(GAINS)
        renders = [ax for ax in fig.axes if ax.images and ax.images[0].get_array().ndim == 3]
        maps = [ax.images[0] for ax in fig.axes if ax.images and ax.images[0].get_array().ndim == 2]
        ests = [np.clip(truth * g, 0, 1) for g in GAINS.values()]
        # the absolute render of reconstruct's *_rgb.png, truth first, then each method
        for ax, cube in zip(renders, [truth, *ests]):
            shown = np.round(np.asarray(ax.images[0].get_array(), dtype=np.float64) * 255)
            assert np.abs(shown - srgb_preview(cube, bands).astype(np.float64)).max() <= 1
        assert len(renders) == 1 + len(GAINS) and len(maps) == len(GAINS)
        # every method's mean |error| over bands, on one colour scale that clips none of them
        errors = [np.abs(e - truth).mean(axis=0) for e in ests]
        for im, err in zip(maps, errors):
            np.testing.assert_allclose(np.asarray(im.get_array()), err, rtol=1e-5, atol=1e-6)
            assert im.get_clim() == maps[0].get_clim() and im.get_clim()[0] == 0
        assert maps[0].get_clim()[1] >= max(float(e.max()) for e in errors) - 1e-6
        assert sum(1 for ax in fig.axes if ax.get_label() == "<colorbar>") == 1
        # each render titled with its method and its PSNR / SSIM on this scene, as experiment.json records them
        for ax, method in zip(renders[1:], GAINS):
            s = rows[method][record["scene"]]
            assert ax.get_title() == f"{method}\n{s['psnr']:.2f} dB / SSIM {s['ssim']:.3f}"

    mark_complete(out, {"command": "experiment", "experiment": "ablation", "scale": "tiny"})
    page = build_report(out).read_text(encoding="utf-8")
    assert all(f"<img src='../{f['file']}'" in page for f in result["figures"])


def test_a_method_scored_on_other_pixels_is_left_out_of_the_comparison_figure(caplog):
    """A method whose truth (the pixels it is scored on) differs in size from the figure's truth (the first method's)
    is left out with a warning instead of drawn beside a truth render of another crop (each panel's own truth and
    estimate agree, so the shape check inside comparison_panel could not catch it: review)."""
    import logging

    from hsicam.spectral.bands import Bands
    from hsicam.engine.evaluate import SceneResult
    from hsicam.engine.experiments import ComparisonFigures

    bands = Bands.paper()
    rng = np.random.default_rng(0)
    cube = rng.uniform(0.1, 0.9, (len(bands), 12, 12)).astype(np.float32)
    other = rng.uniform(0.1, 0.9, (len(bands), 16, 16)).astype(np.float32)
    scores = {"psnr": 30.0, "ssim": 0.9}
    figures = ComparisonFigures(True, bands, 1)
    figures.choose([SceneResult("s", scores, None, None, 0.0)])
    figures.keep("ours", [SceneResult("s", scores, cube, cube * 0.9, 0.0)])
    with caplog.at_level(logging.WARNING, logger="hsicam.engine.experiments"):
        figures.keep("cassi", [SceneResult("s", scores, other, other, 0.0)])
    assert [p.label for p in figures.panels["s"]] == ["ours"]
    assert "cassi left out of the comparison figure of s (scored on 16x16 px, the figure's truth on 12x12)" in caplog.text


class NoisySceneAsSensor(SceneAsSensor):
    """:class:`SceneAsSensor` plus Gaussian noise drawn from the capture's sensor generator: each seed scores apart."""

    def forward(self, scene, generator=None, sensor_generator=None):
        return scene + 0.1 * torch.randn(scene.shape, generator=sensor_generator)


def test_comparison_figure_titles_give_the_mean_over_seeds_as_experiment_json_does(tmp_path, monkeypatch):
    """With several noise seeds, a panel's PSNR / SSIM is its scene's mean over the seeds (experiment.json's
    per-scene row, which also chose the scene; the table's means are of these), not the first seed's alone (review:
    the titles showed seed 0's, 21.10 dB beside experiment.json's 21.06); the figure says whose renders it shows."""
    from hsicam.engine import experiments
    from hsicam.engine.methods import Method
    from hsicam.report import reconstruction

    cfg = load_config("tiny")
    bands = cfg.bands.to_bands()
    rng = np.random.default_rng(0)
    names = ["dim", "mid", "bright"]
    scenes = [torch.from_numpy(rng.uniform(lo, hi, (len(bands), 16, 16)).astype(np.float32))
              for lo, hi in [(0.05, 0.3), (0.1, 0.7), (0.5, 1.0)]]
    camera = NoisySceneAsSensor(bands)
    gains = {"ours": 1.0, "other-a": 0.95}  # errors of the noise more than of the gain: the seeds differ
    drawn = []
    real_save = reconstruction.save_figure
    monkeypatch.setattr(reconstruction, "save_figure", lambda fig, path: drawn.append(fig) or real_save(fig, path))
    monkeypatch.setattr(experiments, "ensure_trained", lambda run, cfg: "reused")
    monkeypatch.setattr(experiments, "validation_scenes", lambda cfg: (scenes, names))
    monkeypatch.setattr(experiments, "build_method", lambda kind, run_cfg, run: Method(
        run.name, camera, lambda y, g=gains[run.name]: y * g, lambda x: x))
    monkeypatch.setattr(experiments, "scored_region", lambda camera: None)
    out = tmp_path / "ex"
    experiments._run_experiment("ablation", "tiny", out, cfg, (0, 1), [experiments.RunSpec(n) for n in gains],
                                {n: cfg for n in gains}, ())

    result = json.loads((out / "experiment.json").read_text())
    rows = {r["method"]: {s["name"]: s for s in r["scenes"]} for r in result["rows"]}
    assert len(drawn) == len(result["figures"]) == 2
    for fig, record in zip(drawn, result["figures"]):
        renders = [ax for ax in fig.axes if ax.images and ax.images[0].get_array().ndim == 3][1:]
        for ax, method in zip(renders, gains):
            s = rows[method][record["scene"]]
            seeds = [p["psnr"] for p in s["per_seed"]]
            assert f"{seeds[0]:.2f}" != f"{s['psnr']:.2f}"  # the seeds differ enough to tell the two apart
            assert s["psnr"] == np.mean(seeds)
            assert ax.get_title() == f"{method}\n{s['psnr']:.2f} dB / SSIM {s['ssim']:.3f}"
        assert fig._suptitle.get_text().endswith(
            "(ablation, tiny scale, noise seed 0)\nrenders and error maps of noise seed 0; PSNR / SSIM: means over "
            "noise seeds 0, 1, as experiment.json records them")
