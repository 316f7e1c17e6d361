"""Packing and figures of designs other than the demo's (session 53 audit of non-default designs): a learned
DD-CASSI run packs with its own method's scores, its card names no PSF kernel, a singlet's card its real focal
length, and a camera without a DOE gets no height map."""

from __future__ import annotations

import json

import pytest

from hsicam.cli import main
from hsicam.config import load_config


@pytest.fixture(scope="module")
def cassi_run(tmp_path_factory, cache_env):
    run = tmp_path_factory.mktemp("cassi") / "run"
    assert main(["train", "--config", "tiny", "--set", "camera.kind=dd_cassi", "--set", "train.epochs=1",
                 "--out", str(run)]) == 0
    return run


def test_a_learned_cassi_run_packs_with_its_own_methods_scores(cassi_run, tmp_path, capsys):
    """`evaluate --run` of a DD-CASSI run names `--method dd-cassi-rdn`; pack --results then refused those scores as
    "not of the run's own network (doe-learned)" and sent the user back to the refused command."""
    ev = tmp_path / "ev"
    assert main(["evaluate", "--run", str(cassi_run), "--method", "dd-cassi-rdn", "--out", str(ev)]) == 0
    assert main(["pretrained", "pack", str(cassi_run), "--name", "dd", "--results", str(ev / "results.json"),
                 "--dest", str(tmp_path / "root")]) == 0
    card = json.loads((tmp_path / "root" / "dd" / "card.json").read_text())
    res = json.loads((ev / "results.json").read_text())
    assert card["metrics"]["validation"]["mean"]["psnr"] == res["mean"]["psnr"]
    md = (tmp_path / "root" / "dd" / "card.md").read_text()
    assert "PSF kernel" not in md and "None" not in md.split("## Camera and network")[1].split("\n\n")[1]
    # another method's scores are still refused, naming the run's own
    box = tmp_path / "gap"
    assert main(["evaluate", "--run", str(cassi_run), "--method", "dd-cassi-gaptv", "--set",
                 "baselines.gaptv.iterations=2", "--out", str(box)]) == 0
    capsys.readouterr()
    assert main(["pretrained", "pack", str(cassi_run), "--name", "dd2", "--results", str(box / "results.json"),
                 "--dest", str(tmp_path / "root")]) == 2
    err = capsys.readouterr().err
    assert "not of the run's own network (dd-cassi-rdn)" in err and "--method dd-cassi-rdn --out DIR" in err


def test_a_singlets_card_records_the_focal_length_it_has(tmp_path, cache_env):
    """A singlet ignores camera.lens.focal_length_mm (f = R / (n(λ0) − 1), 34.9 mm here): its card recorded the
    ignored 5 mm, against the 34.9 mm of its spec.json and psf.json."""
    from hsicam.engine.pretrained import card_fields

    run = tmp_path / "singlet"
    assert main(["train", "--config", "tiny", "--set", "camera.lens.model=singlet", "--set", "data.synthetic_size=160",
                 "--set", "train.epochs=1", "--set", "data.patches_per_epoch=4", "--out", str(run)]) == 0
    lens = load_config(run / "config.yaml").camera.lens
    card = card_fields(run, "s")
    assert card["camera"]["lens_model"] == "singlet"
    assert card["camera"]["focal_length_mm"] == pytest.approx(lens.design_focal_length_mm()) == pytest.approx(34.899,
                                                                                                               abs=1e-3)
    assert lens.focal_length_mm != pytest.approx(34.899, abs=1)


def test_a_camera_without_a_doe_gets_no_height_map(tmp_path, tiny_camera):
    """`camera.doe.enabled: false` drew "DOE height map" of a flat 0 nm element; export-optics exports no DOE."""
    from hsicam.report.camera import write_optics_figures

    written = write_optics_figures(tiny_camera("camera.doe.enabled=false"), tmp_path)
    assert "doe.png" not in written and not (tmp_path / "doe.png").exists() and "cfa.png" in written


def test_a_trained_sd_cassi_run_is_scored_by_its_own_method(tmp_path, cache_env, capsys):
    """`evaluate --run` of an SD-CASSI run told the user to use "the learned method of its camera", and none
    existed (`dd-cassi-unrolled` refused it, `sd-cassi-unrolled` was not a method): the run could not be scored."""
    run = tmp_path / "sd"
    assert main(["train", "--config", "tiny", "--set", "camera.kind=sd_cassi", "--set", "model.kind=unrolled",
                 "--set", "model.unrolled.prior_features=8", "--set", "model.unrolled.prior_blocks=1",
                 "--set", "train.epochs=1", "--out", str(run)]) == 0
    capsys.readouterr()
    assert main(["evaluate", "--run", str(run), "--out", str(tmp_path / "refused")]) == 2
    assert "use --method sd-cassi-unrolled" in capsys.readouterr().err
    assert main(["evaluate", "--run", str(run), "--method", "sd-cassi-unrolled", "--out", str(tmp_path / "ev")]) == 0
    res = json.loads((tmp_path / "ev" / "results.json").read_text())
    assert res["method"] == "sd-cassi-unrolled" and len(res["scenes"]) >= 1
    assert all(0 < r["psnr"] < 100 for r in res["scenes"])
    assert main(["evaluate", "--run", str(run), "--method", "dd-cassi-unrolled", "--out", str(tmp_path / "no")]) == 2
    assert "needs a run trained with camera.kind=dd_cassi" in capsys.readouterr().err


def test_a_cassi_captures_pixel_wise_flat_is_not_taken_for_a_cfa(cassi_run, tmp_path, caplog):
    """A CASSI config keeps the defaults' cfa section (enabled) though the camera has no CFA: reconstruct checked a
    CASSI run's pixel-wise flat against "the CFA's m×m phases" and could advise --flat-mode cfa (the review of
    session 73). A flat with an m-periodic pattern is not warned about on a CASSI run."""
    import logging

    import numpy as np

    cfg = load_config(str(cassi_run / "config.yaml"))
    m = cfg.camera.cfa.period
    assert cfg.camera.kind == "dd_cassi" and cfg.camera.cfa.enabled and m > 1
    rng = np.random.default_rng(0)
    h = w = 36
    flat = 1000.0 * np.tile(rng.uniform(0.5, 1.5, (m, m)), (h // m + 1, w // m + 1))[:h, :w]
    np.save(tmp_path / "flat.npy", flat.astype(np.float32))
    np.save(tmp_path / "cap.npy", rng.uniform(300, 900, (h, w)).astype(np.float32))
    with caplog.at_level(logging.WARNING):
        code = main(["reconstruct", str(tmp_path / "cap.npy"), "--run", str(cassi_run), "--out",
                     str(tmp_path / "c.h5"), "--flat", str(tmp_path / "flat.npy"), "--white-level", "4095"])
    assert code == 0
    assert "CFA's" not in caplog.text, caplog.text
