"""Packed cameras whose card and weights disagree, broken camera folders, and a spectral prior
given where a camera run is needed (probe 22, findings 5, 11 and 14).

The module fixture trains the tiny preset for one epoch, packs it as ``camC`` and makes from it a
root of packed cameras with one of each kind of damage: ``camA`` holds other weights than its card
records (as a mixed-up package or a partial update leaves it), ``camB``'s card.json does not parse,
``camD`` is a run's files without a card.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from cli_helpers import assert_clean_error, run_cli_in_process
from hsicam.errors import InputError
from hsicam.runs import pretrained as shipped


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def other_weights(path: Path) -> None:
    """Replace the weights at ``path`` with others that load as well (one tensor changed)."""
    from safetensors.torch import save_file

    from hsicam.runs.checkpoint import read_weights

    tensors, meta = read_weights(path)
    key = next(k for k, t in tensors.items() if t.is_floating_point() and t.numel() > 1)
    tensors[key] = tensors[key] + 0.01
    save_file(tensors, str(path), metadata=meta)


@pytest.fixture(scope="module")
def made(tmp_path_factory, cache_env):
    """(run folder, root of packed cameras camA (other weights), camB (bad card), camC (sound), camD (no card))."""
    from hsicam.config import load_config
    from hsicam.engine.pretrained import pack_pretrained
    from hsicam.engine.train import train

    base = tmp_path_factory.mktemp("card_paths")
    run, root = base / "run", base / "root"
    train(load_config("tiny", ["train.epochs=1"]), run, progress=False)
    pack_pretrained(run, "camC", root)
    shutil.copytree(root / "camC", root / "camA")
    other_weights(root / "camA" / "model.safetensors")
    shutil.copytree(root / "camC", root / "camB")
    (root / "camB" / "card.json").write_text("{")
    (root / "camD").mkdir()
    for f in ("config.yaml", "model.safetensors"):
        shutil.copyfile(run / f, root / "camD" / f)
    return run, root


@pytest.fixture
def root(made, monkeypatch):
    monkeypatch.setenv(shipped.ENV_VAR, str(made[1]))
    return made[1]


def mismatch_fragments(root: Path) -> tuple[str, ...]:
    weights = root / "camA" / "model.safetensors"
    recorded = json.loads((root / "camA" / "card.json").read_text())["weights"]["sha256"]
    return (f"{weights}: does not match its card (sha256 {sha256(weights)[:12]}…, card.json records {recorded[:12]}…)",
            f"re-pack it (`hsicam pretrained pack RUN --name camA --dest {root} --force`)")


# ------------------------------------------------------------------------------------------------
# 5: the weights are checked against the card's sha256
# ------------------------------------------------------------------------------------------------
def test_run_pretrained_refuses_weights_that_are_not_the_cards(root, tmp_path):
    out = tmp_path / "ev"
    assert_clean_error(run_cli_in_process("evaluate", "--run", "pretrained:camA", "--out", str(out)),
                       "argument --run", *mismatch_fragments(root))
    assert not out.exists()
    with pytest.raises(InputError, match="does not match its card"):
        shipped.resolve_run("pretrained:camA")
    from hsicam.runs.folder import load_run

    with pytest.raises(InputError, match="does not match its card"):
        load_run("pretrained:camA")
    assert_clean_error(run_cli_in_process("export-optics", "--run", "pretrained:camB", "--out", str(out)),
                       f"{root / 'camB' / 'card.json'}: unreadable model card (Expecting property name", "re-pack it")
    assert shipped.resolve_run("pretrained:camC") == root / "camC"  # its own weights: used


def test_copy_refuses_weights_that_are_not_the_cards_and_copies_nothing(root, tmp_path):
    dest = tmp_path / "mine"
    assert_clean_error(run_cli_in_process("pretrained", "copy", "camA", str(dest)), *mismatch_fragments(root))
    assert list(tmp_path.iterdir()) == []  # neither the folder nor a temporary of it
    res = run_cli_in_process("pretrained", "copy", "camC", str(dest))
    assert res.returncode == 0, res.stderr
    assert sha256(dest / "model.safetensors") == json.loads((dest / "card.json").read_text())["weights"]["sha256"]


def test_show_prints_the_card_and_says_the_weights_are_not_its(root):
    res = run_cli_in_process("pretrained", "show", "camA")
    assert res.returncode == 0, res.stderr
    card_md = (root / "camA" / "card.md").read_text()
    assert res.stdout.startswith(card_md)
    note = res.stdout[len(card_md):].strip()
    assert note.startswith("WARNING: ") and "\n" not in note
    assert all(f in note for f in mismatch_fragments(root))
    assert "`--run pretrained:camA` and `hsicam pretrained copy camA` refuse this camera" in note
    good = run_cli_in_process("pretrained", "show", "camC")
    assert good.returncode == 0 and good.stdout == (root / "camC" / "card.md").read_text()


def test_show_of_a_camera_whose_card_md_is_lost_or_damaged_prints_the_card_from_card_json(root, tmp_path):
    """card.md is made from card.json alone (card_markdown): a camera without it, or with a card.md that is not UTF-8
    text, was usable by --run and copy while `show` failed ("card.md: No such file", or "unreadable input: not UTF-8
    text" naming no file); it prints the card made again, under a line naming the file."""
    from hsicam.engine.pretrained import card_markdown

    want = card_markdown(shipped.parse_card(root / "camC")[0])
    assert want == (root / "camC" / "card.md").read_text()  # what card.md holds when sound
    for name, damage, why in (("camE", lambda f: f.unlink(), "no such file or directory"),
                              ("camF", lambda f: f.write_bytes(b"\xff\xfe card"), "not UTF-8 text")):
        shutil.copytree(root / "camC", root / name)
        try:
            damage(root / name / "card.md")
            res = run_cli_in_process("pretrained", "show", name)
            assert res.returncode == 0, res.stderr
            assert res.stdout == f"({root / name / 'card.md'}: {why}; the card below is made from card.json)\n\n" + want
        finally:
            shutil.rmtree(root / name)


def test_a_cameras_weights_are_hashed_once_per_file_version(root, tmp_path, monkeypatch):
    """Resolving a camera again (the CLI's --run, then load_run, then a method) does not hash its
    weights again; new weights in the same place are hashed anew."""
    from hsicam.runs import checkpoint

    cam = tmp_path / "pre" / "camE"
    shutil.copytree(root / "camC", cam)
    monkeypatch.setenv(shipped.ENV_VAR, str(cam.parent))
    reads = []
    real_open = open
    monkeypatch.setattr("builtins.open", lambda f, *a, **k: (reads.append(Path(f)) if str(f).endswith(
        "model.safetensors") else None) or real_open(f, *a, **k))
    weights = cam / "model.safetensors"
    for _ in range(3):
        assert shipped.resolve_run("pretrained:camE") == cam
    assert reads == [weights]
    other_weights(weights)
    reads.clear()
    with pytest.raises(InputError, match="does not match its card"):
        shipped.resolve_run("pretrained:camE")
    assert reads == [weights]
    assert checkpoint.file_sha256(weights) == hashlib.sha256(weights.read_bytes()).hexdigest()


# ------------------------------------------------------------------------------------------------
# 11: a broken camera folder hides no other camera, and is not "available"
# ------------------------------------------------------------------------------------------------
def test_list_reports_each_broken_camera_and_lists_the_others(root):
    res = run_cli_in_process("pretrained", "list")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    summary = json.loads((root / "camC" / "card.json").read_text())["summary"]
    assert [x.split(":", 1)[0] for x in lines[:4]] == ["camA", "camB", "camC", "camD"], lines
    # camA's weights are not its card's: --run and copy refuse it, so the list says so (it was listed as usable)
    assert lines[0].startswith("camA: ") and "does not match its card" in lines[0] and lines[0].endswith(": not usable")
    assert lines[2].startswith(f"camC: {summary} |")
    assert lines[1] == "camB: unreadable model card (Expecting property name enclosed in double quotes): not usable"
    assert lines[3] == "camD: not a packed camera (card.json missing): not usable"
    assert lines[4].startswith("use one with --run pretrained:NAME")
    assert shipped.available() == ["camA", "camC"]


def test_show_of_a_folder_without_a_card_says_what_it_is(root):
    assert_clean_error(run_cli_in_process("pretrained", "show", "camD"),
                       f"{root / 'camD'}: not a packed camera (card.json missing)")
    assert_clean_error(run_cli_in_process("pretrained", "show", "nope"),
                       "no pre-trained camera 'nope' (available: camA, camC; broken: camB, camD;")


# ------------------------------------------------------------------------------------------------
# 14: a spectral prior where a camera run is needed
# ------------------------------------------------------------------------------------------------
def test_a_spectral_prior_as_a_camera_run_says_what_it_is_and_how_to_use_it(made, tmp_path):
    from hsicam.config import ChoiConfig, load_config
    from hsicam.engine.methods import build_method
    from hsicam.engine.prior import train_prior

    prior = tmp_path / "prior"
    train_prior(load_config("tiny"), ChoiConfig(train_steps=2, features=4, latent=2, batch_size=4), prior, progress=False)
    capture = tmp_path / "sensor.npy"
    np.save(capture, np.full((40, 40), 0.1, np.float32))
    want = (f"hsicam: error: {prior}: a spectral prior (hsicam baseline train-prior), not a camera run: use it with "
            f"`hsicam evaluate --method dd-cassi-choi --run {prior} --out DIR`; this command needs a camera run")
    for args in (("reconstruct", str(capture), "--run", str(prior), "--out", str(tmp_path / "c.h5")),
                 ("simulate", "--run", str(prior), "--scene", str(capture), "--out", str(tmp_path / "sim"))):
        res = run_cli_in_process(*args)
        assert_clean_error(res)
        assert res.stderr.strip().startswith(want), res.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["prior", "sensor.npy"]
    # the advice works: the Choi method takes the folder as its --run (with the folder's config.yaml)
    assert build_method("dd-cassi-choi", load_config(prior / "config.yaml"), prior).name == "dd-cassi-choi"


# ------------------------------------------------------------------------------------------------
# A results.json a card cannot cite: refused for its own fields first, with no warning before
# ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("mean, extra, fragment", [
    ('{"psnr": NaN, "ssim": 0.9, "sam": 5.0}', "", "has a mean PSNR that is not a finite number (psnr: nan)"),
    ('{"psnr": 30.0, "ssim": 0.9, "sam": Infinity}', "", "has a mean SAM that is not a finite number (sam: inf)"),
    ('{"psnr": 30.0, "ssim": 0.9, "sam": NaN}', ', "sam_undefined": ["dark_0"]',
     "has no mean SAM: the spectral angle is undefined on every scene (the truth is zero at every scored pixel: "
     "dark_0)"),
    ('{"psnr": 1' + '0' * 400 + ', "ssim": 0.9, "sam": 5.0}', "", "has a mean PSNR that is not a finite number"),
    ('{"psnr": true, "ssim": 0.9, "sam": 5.0}', "", "has no mean PSNR/SSIM/SAM as numbers"),
    ('{}', "", "has no mean PSNR/SSIM/SAM as numbers"),
])
def test_pack_refuses_results_without_finite_means_before_any_warning(made, tmp_path, mean, extra, fragment):
    """JSON NaN/Infinity parse as floats: a card citing them would print 'nan dB' (and its card.json would not be
    standard JSON); `hsicam evaluate` writes a NaN mean SAM (and lists the scenes) when no scene has a spectral
    angle. A file that names no run would also get the 'cited as given' warning; it is refused for its means
    first, so the user reads one line."""
    run, _ = made
    results = tmp_path / "results.json"
    results.write_text('{"scenes": [], "mean": ' + mean + extra + '}')
    dest = tmp_path / "root"
    res = run_cli_in_process("pretrained", "pack", str(run), "--name", "camN", "--dest", str(dest),
                             "--results", str(results))
    assert_clean_error(res, f"{results}: 'mean' {fragment}")
    assert "cited as given" not in res.stderr
    assert not (dest / "camN").exists()
