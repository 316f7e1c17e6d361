"""Items earlier sessions noticed and left alone (session 59, left9a): each test holds the behaviour a user meets."""

from __future__ import annotations

import json
import types

import pytest
import torch
import yaml

from hsicam.config import ChoiConfig, load_config
from hsicam.errors import InputError
from hsicam.io import mark_complete


def test_the_report_names_the_run_whose_camera_cannot_be_drawn_not_the_results_file(tiny_camera, tmp_path, monkeypatch):
    """A run whose DOE heights are finite but absurd (3e38 m) has a NaN PSF: the report stopped with "corrupt
    results.json (a field holds a value of the wrong kind: cannot convert float NaN to integer)", blaming a sound
    results.json. Now the camera section says which run's camera cannot be drawn and why; the page is written."""
    from hsicam.report.html import _camera_section

    cam = tiny_camera()
    with torch.no_grad():
        cam.optics.doe.height_m.fill_(3e38)
    assert not bool(torch.isfinite(cam.psf_result().psf).all())  # the damage: a PSF of NaN/Inf values
    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.setattr("hsicam.runs.folder.load_run", lambda r: (load_config("tiny"), types.SimpleNamespace(camera=cam)))
    out = tmp_path / "report"
    out.mkdir()
    page = _camera_section(run, out)
    note = page[page.index("<p class='note'>camera figures unavailable"):]
    assert note.startswith(f"<p class='note'>camera figures unavailable: {run}: the camera its weights and config.yaml "
                           "describe cannot be drawn (its PSF holds ")
    assert "NaN/Inf value(s) (DOE heights up to 3e+38 m)): the run's model.safetensors or config.yaml is damaged</p>" in note
    assert "results.json" not in page


def test_the_report_blames_the_run_only_for_a_damaged_camera(tiny_camera, tmp_path, monkeypatch):
    """Only the camera's own refusal (an InputError: a NaN PSF) is reported as a damaged run; another failure while
    drawing (a plotting bug, here a ValueError of the PSF montage) is not turned into "model.safetensors or
    config.yaml is damaged" about a sound run."""
    from hsicam.report.html import _camera_section

    cam = tiny_camera()
    run = tmp_path / "run"
    run.mkdir()
    monkeypatch.setattr("hsicam.runs.folder.load_run", lambda r: (load_config("tiny"), types.SimpleNamespace(camera=cam)))

    def broken_montage(*args, **kwargs):
        raise ValueError("a plotting bug")

    monkeypatch.setattr("hsicam.report.camera.plot_psf_montage", broken_montage)
    out = tmp_path / "report"
    out.mkdir()
    with pytest.raises(ValueError, match="a plotting bug"):
        _camera_section(run, out)


def test_a_data_folder_inside_a_report_inside_an_evaluation_is_refused_as_the_evaluation(tmp_path):
    """check_not_an_output stopped at the first marked folder above the data: EVAL/report/scenes (a report's
    folder, itself inside an evaluate's output) was taken as data, while EVAL/scenes was refused."""
    from hsicam.data.datasets import check_not_an_output

    ev = tmp_path / "eval"
    for d in (ev / "scenes", ev / "report" / "scenes"):
        d.mkdir(parents=True)
    (ev / "results.json").write_text(json.dumps({"data": "DATA"}))
    mark_complete(ev, {"command": "evaluate"})
    mark_complete(ev / "report", {"command": "report"})
    with pytest.raises(InputError) as beside:
        check_not_an_output(ev / "scenes")
    with pytest.raises(InputError) as nested:
        check_not_an_output(ev / "report" / "scenes")
    assert str(nested.value) == str(beside.value).replace(str(ev / "scenes"), str(ev / "report" / "scenes"), 1)
    assert str(nested.value).startswith(f"{ev / 'report' / 'scenes'}: lies inside {ev}, which is the output of hsicam "
                                        "evaluate (which scored DATA)")
    with pytest.raises(InputError, match="is the report folder|is .*report"):  # the report folder itself, as before
        check_not_an_output(ev / "report")


@pytest.fixture(scope="module")
def small_prior(tmp_path_factory, cache_env):
    from hsicam.engine.prior import train_prior

    p = tmp_path_factory.mktemp("left_prior") / "p"
    train_prior(load_config("tiny"), ChoiConfig(features=4, latent=8, train_steps=2, batch_size=1), p, progress=False)
    return p


def test_a_prior_whose_prior_yaml_was_edited_is_told_so_not_that_it_is_an_old_prior(small_prior, tmp_path):
    """Weights of the current 6 + 6 autoencoder beside a prior.yaml whose features were edited by hand got the hint
    "a prior trained by an earlier hsicam has the old 3 + 3 layer autoencoder"; the weights' shapes tell which."""
    import shutil

    from hsicam.engine.prior import load_prior

    bands = load_config("tiny").bands.to_bands()
    p = shutil.copytree(small_prior, tmp_path / "edited")
    settings = yaml.safe_load((p / "prior.yaml").read_text())
    settings["features"] = 8
    (p / "prior.yaml").write_text(yaml.safe_dump(settings))
    with pytest.raises(InputError) as exc:
        load_prior(p, bands)
    assert str(exc.value).endswith(": its prior.yaml says features: 8, but the weights were trained with features: 4 "
                                   "(prior.yaml edited after the training?); put back features: 4 in prior.yaml, or "
                                   "train it again with `hsicam baseline train-prior`")

    # weights of a 3 + 3 layer autoencoder (an earlier hsicam's), the same file format: the old hint stays
    from safetensors import safe_open
    from safetensors.torch import save_file

    from hsicam.models.priors import SpectralAutoencoder

    old = shutil.copytree(small_prior, tmp_path / "old")
    with safe_open(str(old / "prior.safetensors"), "pt") as f:
        meta = f.metadata()
    save_file(SpectralAutoencoder(len(bands), 4, 8, layers=3).state_dict(), str(old / "prior.safetensors"), metadata=meta)
    with pytest.raises(InputError) as exc:
        load_prior(old, bands)
    assert str(exc.value).endswith(": a prior trained by an earlier hsicam has the old 3 + 3 layer autoencoder; train "
                                   "it again with `hsicam baseline train-prior`")


TENT = ["train.epochs=1", "model.kind=mosaic", "model.mosaic.features=8", "model.mosaic.blocks=1",
        "model.mosaic.head_features=4", "model.mosaic.head_layers=1", "model.mosaic.demosaic_kernel=tent"]


@pytest.mark.slow
def test_a_demo_of_a_network_with_a_tent_skip_scores_the_tent_demosaic_too(tmp_path, cache_env):
    """demo.py's tent branch: the network's own start, network-free, is a reference of its own (window 2·3 − 1)."""
    from hsicam.engine.demo import run_demo
    from hsicam.engine.methods import DEMOSAIC_REFERENCE_NAMES

    res = run_demo(load_config("tiny", TENT), tmp_path / "demo")
    names = [r["method"] for r in res["references"]]
    assert names[1:3] == [DEMOSAIC_REFERENCE_NAMES["box"], DEMOSAIC_REFERENCE_NAMES["tent"]]
    box, tent = (r["mean"]["psnr"] for r in res["references"][1:3])
    assert box != tent  # two demosaics (3 px box, 5 px tent), not one scored twice
    md = (tmp_path / "demo" / "results.md").read_text()
    assert f"- {DEMOSAIC_REFERENCE_NAMES['tent']}: " in md
    assert json.loads((tmp_path / "demo" / "results.json").read_text())["references"][2]["method"] == names[2]


def test_a_demo_of_a_cassi_config_scores_the_grey_reference_alone_and_draws_no_optics(tmp_path, cache_env):
    """demo.py's CASSI branch: the demosaic references need a per-band sensor code (refused with ValueError and
    skipped), and the DOE camera's figures (PSF, DOE, CFA) are not drawn."""
    from hsicam.engine.demo import run_demo

    res = run_demo(load_config("tiny", ["train.epochs=1", "camera.kind=dd_cassi"]), tmp_path / "demo")
    assert [r["method"] for r in res["references"]] == ["sensor image x mean training spectrum"]
    files = {p.name for p in (tmp_path / "demo").iterdir()}
    assert {"results.json", "results.md", "reconstructions.png", "training.png", ".complete"} <= files
    assert not files & {"psf.npy", "psf.png", "doe.png", "cfa.png"}
    md = (tmp_path / "demo" / "results.md").read_text()
    assert md.split("References:\n\n")[1].splitlines()[0].startswith("- sensor image x mean training spectrum: ")
    held = [r["method"] for r in res["heldout"]["references"]]  # the held-out scenes' references alike
    assert held == ["sensor image x mean training spectrum"] and md.count("\n- ") == 2


def test_a_capture_through_a_damaged_camera_blames_the_camera_not_the_scene(tiny_camera):
    """`hsicam simulate` with a camera whose PSF is NaN (DOE heights of 3e38 m) told the user to normalise a scene
    of peak 1 ("float overflow: the scene's peak value is 1"); a scene of huge values still gets that advice."""
    cam = tiny_camera()
    h, w = cam.min_scene_size()
    scene = torch.full((1, len(cam.bands), h, w), 0.5)
    scene[..., 0, 0] = 1.0
    assert bool(torch.isfinite(cam.capture(scene)).all())  # the sound camera images it
    with torch.no_grad():
        cam.optics.doe.height_m.fill_(3e38)
    with pytest.raises(InputError) as exc:
        cam.capture(scene, source="s.h5")
    assert str(exc.value).startswith("s.h5: the simulated sensor image is not finite, and so is this camera's image of "
                                     "a uniform scene of 1: the camera's model (its weights or config.yaml")
    assert "normalise the scene" not in str(exc.value)
    with pytest.raises(InputError, match=r"the scene.s peak value is 1e\+38\); normalise the scene first"):
        tiny_camera().capture(scene * 1e38, source="s.h5")  # the scene's overflow: as before
