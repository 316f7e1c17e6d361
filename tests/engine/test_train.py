"""Training: overfitting, checkpoints, deterministic resume, SIGKILL resume, DDP, CLI."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from conftest import KEEP_THE_GROUP, torchrun_tmp
from cli_helpers import assert_clean_error, run_cli, run_cli_in_process, signal_a_training
from hsicam.config import load_config
from hsicam.runs.checkpoint import load_weights, read_weights, save_weights
from hsicam.engine.train import build_optimizer, train
from hsicam.models import CameraSystem


def tiny_cfg(*overrides: str):
    return load_config("tiny", list(overrides))


def smooth_cube(b: int, c: int, h: int, w: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    low = torch.rand(b, c, h // 8 + 1, w // 8 + 1, generator=g)
    return F.interpolate(low, size=(h, w), mode="bilinear", align_corners=True)


def test_tiny_model_overfits_one_batch_and_optics_learn():
    torch.manual_seed(0)
    cfg = tiny_cfg("model.rdn.features=16", "model.rdn.growth=8", "train.grad_clip=null")
    model = CameraSystem.from_config(cfg)
    opt = build_optimizer(cfg, model)
    for g in opt.param_groups:
        g["lr"] = {"net": 3e-3, "doe": 20e-9, "cfa": 1e-2}[g["name"]]
    m = model.camera.margin
    scene = smooth_cube(2, 7, 24 + m, 24 + m)
    h0 = model.camera.optics.doe.height_m.detach().clone()
    w0 = model.camera.cfa.weights.detach().clone()
    losses = []
    for step in range(500):
        recon, _ = model(scene)
        loss = F.l1_loss(recon, model.target(scene))
        opt.zero_grad()
        loss.backward()
        if step == 0:
            for p in (model.camera.optics.doe.height_m, model.camera.cfa.weights):
                assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0
        opt.step()
        losses.append(loss.item())
    # The network starts as the grey image (RDN init), which already fits somewhat: the loss must
    # fall well below that start and to under a tenth of the signal (L1 of predicting zeros).
    signal = model.target(scene).abs().mean().item()
    assert losses[-1] < losses[0] / 3, (losses[0], losses[-1])
    assert losses[-1] < signal / 10, (signal, losses[-1])
    assert not torch.equal(model.camera.optics.doe.height_m.detach(), h0)
    assert not torch.equal(model.camera.cfa.weights.detach(), w0)


def test_checkpoint_round_trip_reproduces_outputs(tmp_path):
    torch.manual_seed(1)
    cfg = tiny_cfg()
    a = CameraSystem.from_config(cfg)
    with torch.no_grad():
        a.camera.optics.doe.height_m.add_(1e-7 * torch.rand_like(a.camera.optics.doe.height_m))
    save_weights(tmp_path / "m.safetensors", a, a.bands)
    torch.manual_seed(2)  # a differently initialised network
    b = CameraSystem.from_config(cfg)
    load_weights(tmp_path / "m.safetensors", b, b.bands)
    scene = smooth_cube(1, 7, 40, 40)
    with torch.no_grad():
        ra, _ = a(scene, torch.Generator().manual_seed(0))
        rb, _ = b(scene, torch.Generator().manual_seed(0))
    assert torch.equal(ra, rb)


def _weights(run: Path) -> dict[str, torch.Tensor]:
    return read_weights(run / json.loads((run / "checkpoints.json").read_text())["last"]["dir"] / "model.safetensors")[0]


def test_resume_matches_uninterrupted_run(tmp_path, cache_env):
    cfg = tiny_cfg("train.epochs=3")
    full = train(cfg, tmp_path / "full", progress=False)
    part = train(cfg, tmp_path / "part", progress=False, stop_after_steps=5)  # mid-epoch 2 (4 steps/epoch)
    assert part == {"stopped_at_step": 5}
    resumed = train(cfg, tmp_path / "part", resume=True, progress=False)
    assert resumed["step"] == full["step"] == 12
    wa, wb = _weights(tmp_path / "full"), _weights(tmp_path / "part")
    assert wa.keys() == wb.keys()
    for k in wa:
        torch.testing.assert_close(wa[k], wb[k], rtol=0, atol=1e-6, msg=k)
    assert resumed["val_psnr"] == pytest.approx(full["val_psnr"], abs=1e-4)
    # metrics.jsonl holds one record per step: the interrupted steps are not duplicated
    steps = [json.loads(x)["step"] for x in (tmp_path / "part" / "metrics.jsonl").read_text().splitlines()
             if "train_loss" in json.loads(x)]
    assert steps == list(range(1, 13))
    # each training session (the first and the resume) records the software it ran with, where it began
    sessions = [json.loads(x) for x in (tmp_path / "part" / "metrics.jsonl").read_text().splitlines()
                if "session" in json.loads(x)]
    assert [(r["step"], r["epoch"]) for r in sessions] == [(0, 0), (5, 1)]
    for r in sessions:
        _assert_is_this_software(r["session"])
        assert "config_changed" not in r["session"]  # (resumed as it began)
        # the cached synthetic set it read (which $HSICAM_CACHE chose: config.yaml does not say)
        folder = Path(r["session"]["synthetic_set"]["folder"])
        assert (folder / "manifest.json").is_file() and str(folder).startswith(os.environ["HSICAM_CACHE"])


def test_a_resume_that_changes_the_config_records_what_it_changed(tmp_path, cache_env):
    """A resume with --set rewrites config.yaml to the config it goes on with, so config.yaml alone no longer said how
    the steps before it trained (session 74's records hunt): the resume's session record lists what it changed."""
    train(tiny_cfg("train.epochs=2"), tmp_path / "r", progress=False, stop_after_steps=3)
    train(tiny_cfg("train.epochs=3", "train.lr=0.002"), tmp_path / "r", resume=True, progress=False,
          stop_after_steps=5)
    sessions = [json.loads(x)["session"] for x in (tmp_path / "r" / "metrics.jsonl").read_text().splitlines()
                if "session" in json.loads(x)]
    before_lr = tiny_cfg().train.lr
    assert "config_changed" not in sessions[0]
    assert sessions[1]["config_changed"] == ["train.epochs: 2 → 3", f"train.lr: {before_lr!r} → 0.002"]


def _assert_is_this_software(session: dict) -> None:
    """A run's session record names this process's software: its versions, device, and the checkout's commit."""
    import datetime
    import platform

    import hsicam

    assert session["torch"] == torch.__version__ and session["numpy"] == np.__version__
    assert session["python"] == platform.python_version() and session["executable"] == sys.executable
    assert session["hsicam"] == hsicam.__version__  # the code running (a wheel's metadata takes it too: pyproject)
    assert session["device"] == "cpu" and session["world_size"] == 1
    assert session["threads"] == torch.get_num_threads()  # (other thread counts: other last bits of the weights)
    started = datetime.datetime.fromisoformat(session["started_utc"])
    assert abs((datetime.datetime.now(datetime.timezone.utc) - started).total_seconds()) < 3600
    checkout = Path(hsicam.__file__).resolve().parents[2]
    head = subprocess.run(["git", "-C", str(checkout), "rev-parse", "HEAD"], capture_output=True, text=True)
    if (checkout / ".git").exists() and head.returncode == 0:
        assert session["git_commit"] in (head.stdout.strip(), head.stdout.strip() + "+dirty")
    else:  # an installed package: no commit to name
        assert session["git_commit"] is None


def test_resume_with_changed_keys_records_them_in_config_yaml(tmp_path, cache_env):
    """`hsicam train --resume --set train.epochs=2`: the run goes on with the new length and its
    config.yaml says so (it describes what the run did, e.g. for a shipped camera's card)."""
    from hsicam.config import load_config

    run = tmp_path / "run"
    assert not torch.are_deterministic_algorithms_enabled()
    assert train(tiny_cfg("train.epochs=3"), run, progress=False, stop_after_steps=5) == {"stopped_at_step": 5}
    # the tiny preset trains with train.deterministic; torch is left as the caller had it (later tests here run on)
    assert tiny_cfg().train.deterministic and not torch.are_deterministic_algorithms_enabled()
    res = run_cli_in_process("train", "--out", str(run), "--resume", "--set", "train.epochs=2",
                             env={"HSICAM_CACHE": str(cache_env)})
    assert res.returncode == 0, res.stderr
    assert load_config(run / "config.yaml").train.epochs == 2
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["final"] and records[-1]["step"] == 8  # 4 steps per epoch


@pytest.mark.parametrize("changes,named", [
    (["data.split_seed=3"], "data.split_seed: 0 → 3"),
    (["camera.doe.seed=7", "data.synthetic_seed=2"], "camera.doe.seed: 0 → 7; data.synthetic_seed: 0 → 2"),
    (["data.root=/elsewhere"], "data.root: None → '/elsewhere'"),
])
def test_a_resume_may_not_change_what_the_run_is(tmp_path, cache_env, changes, named):
    """`train --resume --set data.split_seed=3` trained on, rewrote config.yaml with the other split, and `evaluate
    --run` then scored a scene the network had trained on as validation; a DOE seed or the scenes changed the same
    way. Refused, naming the keys; the run is left as it was."""
    run = tmp_path / "run"
    assert train(tiny_cfg("train.epochs=2"), run, progress=False, stop_after_steps=2) == {"stopped_at_step": 2}
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    sets = [a for c in ["train.epochs=3", *changes] for a in ("--set", c)]
    res = run_cli_in_process("train", "--out", str(run), "--resume", *sets, env={"HSICAM_CACHE": str(cache_env)})
    assert_clean_error(res, f"not its bands, camera, network, scenes or split: {named}; nothing was changed")
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before


def test_sigkilled_training_resumes(tmp_path, cache_env):
    run = tmp_path / "run"
    code, _ = signal_a_training(run, cache_env, lambda proc: proc.send_signal(signal.SIGKILL), ready="checkpoints.json")
    assert code == -signal.SIGKILL
    man = json.loads((run / "checkpoints.json").read_text())
    assert 0 < man["state"]["global_step"] < 160
    read_weights(run / man["last"]["dir"] / "model.safetensors")  # intact
    res = run_cli_in_process("train", "--out", str(run), "--resume", env={"HSICAM_CACHE": str(cache_env)})
    assert res.returncode == 0, res.stderr
    records = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert records[-1]["final"] and records[-1]["step"] == 160
    assert not list((run / "checkpoints").glob(".step-*")), "temporary checkpoint left behind"


DDP_SCRIPT = KEEP_THE_GROUP + """
import sys, torch
from hsicam.config import load_config
from hsicam.engine.train import train
torch.set_num_threads(1)
cfg = load_config("tiny", ["train.epochs=1", "data.val_fraction=0.0", *sys.argv[2:]])
train(cfg, sys.argv[1], progress=False)
import os, pathlib
pathlib.Path(sys.argv[1] + ".rank" + os.environ.get("RANK", "0")).write_text(
    f"{torch.distributed.is_initialized()} {group_references()}")
release_the_group()
"""


# optics_steps=2 of 4: the fixed-optics steps leave the optics without gradients (DDP must allow it).
# "joint" trains without train.deterministic, so that the optimizer is what imports torch._dynamo first
@pytest.mark.parametrize("extra", [("train.deterministic=false",), ("train.optics_steps=2",)],
                         ids=["joint", "optics-then-net"])
def test_ddp_two_processes_matches_single_process(tmp_path, cache_env, extra):
    script = tmp_path / "ddp_train.py"
    script.write_text(DDP_SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env),
           "TMPDIR": str(torchrun_tmp(tmp_path))}
    single = subprocess.run([sys.executable, str(script), str(tmp_path / "single"), *extra], env=env, capture_output=True, text=True, timeout=300)
    assert single.returncode == 0, single.stderr
    ddp = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                          str(script), str(tmp_path / "ddp"), *extra], env=env, capture_output=True, text=True, timeout=300)
    assert ddp.returncode == 0, ddp.stderr[-3000:]
    # the group fit created is destroyed when it ends, and nothing refers to it any more (else gloo can abort
    # at exit: pytorch#190489; torch._dynamo imported while the group existed kept 10 references)
    assert [(tmp_path / f"ddp.rank{r}").read_text() for r in (0, 1)] == ["False 0", "False 0"]
    ws, wd = read_weights(tmp_path / "single" / "model.safetensors")[0], read_weights(tmp_path / "ddp" / "model.safetensors")[0]
    init = CameraSystem.from_config(load_config("tiny")).state_dict()
    for k in ws:
        # Same global batch (4 = 2 × 2): equal up to float summation order (tolerance 1e-5).
        torch.testing.assert_close(wd[k], ws[k], rtol=1e-4, atol=1e-5, msg=k)
    moved = max((ws[k] - init[k]).abs().max().item() for k in ws if k in init)
    assert moved > 1e-4  # training changed the weights, so the comparison means something

    def losses(run):
        return [r["train_loss"] for r in map(json.loads, (run / "metrics.jsonl").read_text().splitlines())
                if "train_loss" in r]

    # the logged loss is the global batch's (it was rank 0's half of it: 12 % off)
    assert losses(tmp_path / "ddp") == pytest.approx(losses(tmp_path / "single"), rel=1e-4)


DDP_ERROR_SCRIPT = KEEP_THE_GROUP + """
import os, sys, torch
from hsicam.config import load_config
from hsicam.engine.tasks import SystemTask
from hsicam.engine.train import train
from hsicam.errors import InputError
overrides = ["train.batch_size=3"] if sys.argv[2] == "batch" else []  # a batch the 2 processes cannot share
if sys.argv[2] == "step":  # an error once DDP wraps the model: after the first step's forward
    forward = SystemTask.training_step
    def training_step(self, model, batch, g):
        forward(self, model, batch, g)
        raise InputError("the step failed")
    SystemTask.training_step = training_step
torch.set_num_threads(1)
cfg = load_config("tiny", ["train.epochs=1", "data.val_fraction=0.0", *overrides])
try:
    train(cfg, sys.argv[1], progress=False)
    outcome = "trained"
except InputError as exc:
    error = exc  # kept while the group's references are counted, as an uncaught error is kept to the exit
    msg = str(exc)
    outcome = "step" if msg == "the step failed" else "batch" if "divisible by the 2 processes" in msg else msg
open(sys.argv[1] + ".rank" + os.environ.get("RANK", "0"), "w").write(
    f"{outcome} {torch.distributed.is_initialized()} {group_references()}")
release_the_group()
"""


@pytest.mark.parametrize("where", ["batch", "step"])
def test_ddp_error_destroys_the_process_group(tmp_path, cache_env, where):
    """An error in fit under torchrun (a batch the 2 processes cannot share, before DDP; or a step that fails,
    once DDP wraps the model) destroys the group fit created, as a finished or stopped training does, and the
    error's traceback no longer holds it (through the DDP wrapper in its frames): left to the interpreter's exit,
    its gloo threads can abort the process ("terminate called without an active exception", exit -6,
    docs/training.md). Without the destroy: "batch True 8"; without clearing the frames: "step False 1"."""
    script = tmp_path / "ddp_error.py"
    script.write_text(DDP_ERROR_SCRIPT)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "HSICAM_CACHE": str(cache_env),
           "TMPDIR": str(torchrun_tmp(tmp_path))}
    res = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                          str(script), str(tmp_path / "run"), where], env=env, capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert [(tmp_path / f"run.rank{r}").read_text() for r in (0, 1)] == [f"{where} False 0"] * 2


def test_train_and_reconstruct_cli(tmp_path, cache_env):
    run = tmp_path / "run"
    env = {"HSICAM_CACHE": str(cache_env)}
    res = run_cli_in_process("train", "--config", "tiny", "--out", str(run), env=env)
    assert res.returncode == 0, res.stderr
    assert "val PSNR" in res.stdout
    for name in ("config.yaml", "model.safetensors", "metrics.jsonl", "checkpoints.json"):
        assert (run / name).is_file(), name
    # simulate through the trained optics, then reconstruct the sensor image
    np.save(tmp_path / "scene.npy", smooth_cube(1, 7, 50, 60)[0].numpy())
    sim = run_cli_in_process("simulate", "--run", str(run), "--scene", str(tmp_path / "scene.npy"), "--out", str(tmp_path / "sim"), env=env)
    assert sim.returncode == 0, sim.stderr
    out = tmp_path / "rec.h5"
    rec = run_cli_in_process("reconstruct", str(tmp_path / "sim" / "sensor.png"), "--run", str(run), "--out", str(out), "--tile", "32", env=env)
    assert rec.returncode == 0, rec.stderr
    from hsicam.data import read_cube

    cube, bands, _ = read_cube(out)
    assert cube.shape == (7, 50, 60) and len(bands) == 7
    assert (tmp_path / "rec_rgb.png").is_file()
    # ENVI by extension (under its own name: a folder holds one cube per name, tests/cli/test_cli_bad_paths.py)
    rec2 = run_cli_in_process("reconstruct", str(tmp_path / "sim" / "sensor.npy"), "--run", str(run), "--out", str(tmp_path / "rec_envi.hdr"), env=env)
    assert rec2.returncode == 0, rec2.stderr
    assert (tmp_path / "rec_envi_rgb.png").is_file()
    cube2, _, _ = read_cube(tmp_path / "rec_envi.hdr")
    np.testing.assert_allclose(cube2, cube, atol=2e-4)  # PNG quantisation only

    # bad input: missing run, corrupt weights, another band grid, existing run folder
    assert_clean_error(run_cli_in_process("reconstruct", str(tmp_path / "sim" / "sensor.npy"), "--run", str(tmp_path / "nope"), "--out", str(out)), "no such run folder")
    assert_clean_error(run_cli_in_process("train", "--config", "tiny", "--out", str(run), env=env), "not empty")
    broken = tmp_path / "broken"
    shutil.copytree(run, broken)
    # a root weights file that differs from the manifest is never used: the manifest's checkpoint is
    shutil.rmtree(broken / "checkpoints")  # so the corrupt root file is all this folder has
    (broken / "checkpoints.json").unlink()
    data = (broken / "model.safetensors").read_bytes()
    (broken / "model.safetensors").write_bytes(data[: len(data) // 2])
    assert_clean_error(run_cli_in_process("reconstruct", str(tmp_path / "sim" / "sensor.npy"), "--run", str(broken), "--out", str(out)), "corrupt")
    other = tmp_path / "other"
    shutil.copytree(run, other)
    text = (other / "config.yaml").read_text().replace("step_nm: 50.0", "step_nm: 60.0")
    (other / "config.yaml").write_text(text)
    assert_clean_error(run_cli_in_process("reconstruct", str(tmp_path / "sim" / "sensor.npy"), "--run", str(other), "--out", str(out)), "trained on")


def test_training_on_one_scene_warns_that_nothing_is_validated(tmp_path, cache_env):
    """`data.root` = one cube file: the split holds no scene out, so training says at its start that
    it runs without validation and keeps its last checkpoint, and how to get validation."""
    from hsicam.data.formats import write_cube_h5
    from hsicam.spectral import Bands

    cube = tmp_path / "one.h5"
    write_cube_h5(cube, smooth_cube(1, 7, 64, 64)[0].numpy(), Bands.uniform(420, 720, 50))
    run = tmp_path / "run"
    res = run_cli_in_process("train", "--config", "tiny", "--set", f"data.root={cube}", "--out", str(run),
                  env={"HSICAM_CACHE": str(cache_env)})
    assert res.returncode == 0, res.stderr
    lines = [x for x in res.stderr.splitlines() if "no validation scenes" in x]
    assert len(lines) == 1, res.stderr
    for words in ("a split of 1 scene(s)", "without validation", "last checkpoint, not the best",
                  "2 or more scenes", "data.val_fraction=0.34"):
        assert words in lines[0], (words, lines[0])
    assert res.stderr.index(lines[0]) < res.stderr.index("step 1/")  # said before training starts
    assert json.loads((run / "checkpoints.json").read_text())["best"] is None


def test_one_synthetic_scene_is_told_to_raise_synthetic_n_not_to_point_data_root(tmp_path, cache_env, caplog):
    """The same warning for the synthetic data of one scene told the user to point data.root to a folder of 2 or more
    scenes, where the fix is data.synthetic_n (a helper's hunt, session 71)."""
    import logging

    from hsicam.config import load_config
    from hsicam.data.pipeline import build_datasets

    cfg = load_config("tiny", ["data.synthetic_n=1", "data.synthetic_size=64", f"data.cache_dir={tmp_path}"])
    with caplog.at_level(logging.WARNING, logger="hsicam"):
        build_datasets(cfg.data, cfg.bands.to_bands(), 20)
    [line] = [r.getMessage() for r in caplog.records if "no validation scenes" in r.getMessage()]
    assert line.endswith("raise data.synthetic_n to 2 or more (data.val_fraction=0.34 sets the share held out)"), line
    assert "data.root" not in line


def test_metrics_truncation_drops_records_the_checkpoint_never_saw(tmp_path):
    from hsicam.runs.folder import MetricsLog

    log = MetricsLog(tmp_path / "metrics.jsonl", True)
    for rec in ({"step": 4, "epoch": 0, "train_loss": 1.0}, {"step": 8, "epoch": 1, "train_loss": 0.5},
                {"step": 8, "epoch": 2, "val_psnr": 20.0}, {"step": 9, "epoch": 2, "train_loss": 0.4}):
        log.write(rec)
    with open(tmp_path / "metrics.jsonl", "a") as fh:
        fh.write('{"step": 10, "epo')  # a record cut by SIGKILL
    log.truncate_after(8, 1)  # checkpoint at step 8 taken before epoch 2's validation finished
    recs = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert recs == [{"step": 4, "epoch": 0, "train_loss": 1.0}, {"step": 8, "epoch": 1, "train_loss": 0.5}]


def test_checkpoint_at_an_existing_step_updates_the_state(tmp_path):
    from hsicam.runs.checkpoint import CheckpointManager

    cfg = tiny_cfg()
    model = CameraSystem.from_config(cfg)
    opt = build_optimizer(cfg, model)
    mgr = CheckpointManager(tmp_path)
    mgr.save(model, opt, {"global_step": 8, "epoch": 1, "step_in_epoch": 4}, model.bands)
    mgr.save(model, opt, {"global_step": 8, "epoch": 2, "step_in_epoch": 0}, model.bands, ("last", "best"))
    state = mgr.load("last", model, opt, model.bands)
    assert state["epoch"] == 2 and state["step_in_epoch"] == 0
    assert mgr.path("best") == mgr.path("last")


def test_grey_reference_is_the_sensor_times_the_mean_training_spectrum():
    from hsicam.engine.evaluate import grey_reference

    model = CameraSystem.from_config(tiny_cfg())
    g = torch.Generator().manual_seed(0)
    train_scenes = [torch.rand(7, 10, 12, generator=g), torch.rand(7, 6, 5, generator=g) * 2]
    ref = grey_reference(model, train_scenes)
    pixels = np.concatenate([s.numpy().reshape(7, -1) for s in train_scenes], axis=1)
    spectrum = pixels.mean(axis=1)
    sensor = torch.rand(2, 1, 4, 3, generator=g)
    expected = sensor.numpy() * (spectrum / spectrum.mean())[None, :, None, None]
    np.testing.assert_allclose(ref.reconstruct(sensor).numpy(), expected, rtol=1e-5)
    assert ref.camera is model.camera


def test_demosaic_reference_is_the_networks_input(tiny_config):
    from hsicam.engine.evaluate import demosaic_reference

    model = CameraSystem.from_config(tiny_config("model.rdn.demosaic_input=true"))
    sensor = torch.rand(1, 1, 12, 10)
    torch.testing.assert_close(demosaic_reference(model).reconstruct(sensor),
                               model.net.network_input(sensor, model.camera)[:, 1:])
    # the reference needs the camera's sensor code, not a particular network
    plain = CameraSystem.from_config(tiny_config())
    torch.testing.assert_close(demosaic_reference(plain).reconstruct(sensor),
                               model.net.network_input(sensor, model.camera)[:, 1:])
    with pytest.raises(ValueError, match="sensor code"):
        demosaic_reference(CameraSystem.from_config(load_config("dd_cassi_rdn")))


def test_tent_demosaic_reference_is_the_mosaic_networks_start(tiny_config):
    """demosaic_reference(model, "tent") is what an untrained mosaic network with the tent skip
    returns (its start), and differs from the box reference."""
    from hsicam.engine.evaluate import demosaic_reference

    torch.manual_seed(0)
    model = CameraSystem.from_config(tiny_config("model.kind=mosaic", "model.mosaic.demosaic_kernel=tent",
                                                 "camera.cfa.init=bandpass")).eval()
    sensor = torch.rand(1, 1, 16, 14)
    tent = demosaic_reference(model, "tent")
    assert tent.name == "CFA tent demosaic, weighted bilinear (no network)"
    with torch.no_grad():
        torch.testing.assert_close(tent.reconstruct(sensor), model.net(sensor, model.camera), atol=1e-6, rtol=0)
        assert not torch.allclose(demosaic_reference(model).reconstruct(sensor), tent.reconstruct(sensor), atol=1e-4)
    # an explicit window is the network's too; the unrolled network's mosaic front end is found
    from hsicam.engine.methods import network_skip

    wide = CameraSystem.from_config(tiny_config("model.kind=mosaic", "model.mosaic.demosaic_kernel=tent",
                                                "model.mosaic.demosaic_window=9", "camera.cfa.init=bandpass")).eval()
    skip = network_skip(wide.net)
    assert skip is wide.net and skip.demosaic_window == 9
    with torch.no_grad():
        torch.testing.assert_close(demosaic_reference(wide, "tent", skip.demosaic_window).reconstruct(sensor),
                                   wide.net(sensor, wide.camera), atol=1e-6, rtol=0)
    unrolled = CameraSystem.from_config(tiny_config("model.kind=unrolled", "model.unrolled.init=mosaic"))
    assert network_skip(unrolled.net) is unrolled.net.front
    assert network_skip(CameraSystem.from_config(tiny_config()).net) is None  # the RDN has no mosaic skip
    with pytest.raises(ValueError, match="tent"):
        demosaic_reference(model, "gauss")


def test_demo_cli_trains_reports_and_draws(tmp_path, cache_env):
    out = tmp_path / "demo"
    proc = run_cli("demo", "--config", "tiny", "--out", str(out), "--set", "model.rdn.demosaic_input=true",
                   env={"HSICAM_CACHE": str(cache_env)})
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "results.json").read_text())
    n_val = len(summary["scenes"])
    assert n_val >= 1 and all(np.isfinite(summary["mean"][k]) for k in ("psnr", "ssim", "sam"))
    refs = {r["method"]: r["mean"] for r in summary["references"]}
    assert set(refs) == {"sensor image x mean training spectrum", "CFA box demosaic (no network)",
                         "CFA linear demosaic, least squares on the training scenes (no network)"}
    assert all(np.isfinite(m[k]) for m in refs.values() for k in ("psnr", "ssim", "sam"))
    held = summary["heldout"]  # the held-out-sources block, named as such
    assert held["data"].startswith("held-out spectral sources") and len(held["scenes"]) >= 1
    assert all(np.isfinite(held["mean"][k]) for k in ("psnr", "ssim", "sam"))
    assert f"PSNR {summary['mean']['psnr']:.2f} dB" in proc.stdout
    assert proc.stdout.count("reference, ") == 6  # validation and held-out sources, 3 each
    md = (out / "results.md").read_text()  # both tables and both reference lists, each named once
    assert md.count(held["data"]) == 1 and md.count("CFA box demosaic (no network): PSNR") == 2
    assert "| scene | psnr | ssim | sam |" in md and md.count("**mean**") == 2
    import imageio.v3 as iio

    for name in ("reconstructions.png", "psf.png", "cfa.png", "doe.png", "training.png"):
        img = iio.imread(out / name)
        assert img.ndim == 3 and min(img.shape[:2]) > 50, name
    # a second call reuses the finished run instead of training again
    # (the measurement-consistency step is an inference setting: switching it on reuses the run too,
    # and the network without it becomes a third reference)
    again = run_cli("demo", "--config", "tiny", "--out", str(out), "--set", "model.rdn.demosaic_input=true",
                    "--set", "model.consistency.iterations=1", env={"HSICAM_CACHE": str(cache_env)})
    assert again.returncode == 0 and "reusing the trained run" in again.stdout, again.stderr
    summary2 = json.loads((out / "results.json").read_text())
    refs2 = {r["method"]: r["mean"] for r in summary2["references"]}
    alone = refs2["network alone (no consistency step)"]
    assert all(alone[k] == pytest.approx(summary["mean"][k], rel=1e-6) for k in ("psnr", "ssim", "sam"))
    assert abs(summary2["mean"]["psnr"] - summary["mean"]["psnr"]) > 1e-4
    # the demosaic-input run reconstructs a capture in tiles exactly as in one piece (CFA phase per tile)
    env = {"HSICAM_CACHE": str(cache_env)}
    np.save(tmp_path / "scene.npy", smooth_cube(1, 7, 70, 64, seed=3)[0].numpy())
    sim = run_cli("simulate", "--run", str(out / "run"), "--scene", str(tmp_path / "scene.npy"), "--out", str(tmp_path / "sim"), env=env)
    assert sim.returncode == 0, sim.stderr
    from hsicam.data import read_cube

    cubes = []
    for tile, steps in (("16", "0"), ("4096", "0"), ("16", "1"), ("4096", "1")):
        dst = tmp_path / f"rec{tile}-{steps}.h5"
        rec = run_cli("reconstruct", str(tmp_path / "sim" / "sensor.npy"), "--run", str(out / "run"), "--out", str(dst),
                      "--tile", tile, "--consistency-steps", steps, env=env)
        assert rec.returncode == 0, rec.stderr
        cubes.append(read_cube(dst)[0])
    np.testing.assert_allclose(cubes[0], cubes[1], atol=1e-5)
    # with the measurement-consistency step too (its halo is added to the network's), and it acts
    np.testing.assert_allclose(cubes[2], cubes[3], atol=1e-5)
    assert np.abs(cubes[2] - cubes[0]).max() > 1e-4
    bad = run_cli("reconstruct", str(tmp_path / "sim" / "sensor.npy"), "--run", str(out / "run"), "--out",
                  str(tmp_path / "bad.h5"), "--consistency-steps", "-1", env=env)
    assert_clean_error(bad, "--consistency-steps must be >= 0")
    assert not (tmp_path / "bad.h5").exists()


def test_weights_files_are_byte_identical_for_the_same_weights(tmp_path):
    """The safetensors writer orders metadata at random (a Rust hash map): the same weights gave files
    of other bytes and SHA-256s. Written through save_safetensors, they are the same bytes every time,
    and read back as written."""
    import hashlib

    from safetensors import safe_open

    from hsicam.runs.checkpoint import read_weights, save_safetensors

    tensors = {"b.weight": torch.arange(12, dtype=torch.float32).reshape(3, 4), "a": torch.ones(5)}
    meta = {"format": "hsicam-checkpoint-1", "bands": '{"centers_nm": [420.0, 720.0]}', "kind": "x", "run": "r/ü"}
    digests = set()
    for i in range(12):
        save_safetensors(tmp_path / f"w{i}.safetensors", tensors, meta)
        digests.add(hashlib.sha256((tmp_path / f"w{i}.safetensors").read_bytes()).hexdigest())
    assert len(digests) == 1
    got, got_meta = read_weights(tmp_path / "w0.safetensors")
    assert got_meta == meta and got.keys() == tensors.keys()
    assert all(torch.equal(got[k], tensors[k]) for k in tensors)
    raw = (tmp_path / "w0.safetensors").read_bytes()
    header = json.loads(raw[8:8 + int.from_bytes(raw[:8], "little")])
    assert list(header["__metadata__"]) == sorted(meta)
    with safe_open(str(tmp_path / "w0.safetensors"), framework="pt") as fh:  # the reader itself accepts it
        assert fh.metadata() == meta


def test_a_camera_noise_level_that_training_does_not_draw_is_warned_about(caplog):
    """camera.sensor.sigma=0.01 alone trained noise-free (each step draws σ_s from train.sensor_sigma, [0, 0]) and
    validated noisy, without a word."""
    import logging

    from hsicam.engine.train import warn_camera_noise_not_trained

    with caplog.at_level(logging.WARNING, logger="hsicam"):
        lines = warn_camera_noise_not_trained(tiny_cfg("camera.sensor.sigma=0.01", "camera.doe.sigma_height_nm=20"))
    assert len(lines) == 2 and [r.getMessage() for r in caplog.records] == lines
    assert "sensor noise σ_s 0.01 is used by the validation and the evaluation only" in lines[0]
    assert "--set train.sensor_sigma=[0.01,0.01]" in lines[0] and "train.sigma_height_nm=[20,20]" in lines[1]
    assert tiny_cfg("camera.sensor.sigma=0.01", "train.sensor_sigma=[0.01,0.01]").train.sensor_sigma == [0.01, 0.01]
    assert warn_camera_noise_not_trained(tiny_cfg("camera.sensor.sigma=0.01", "train.sensor_sigma=[0,0.02]")) == []
    assert warn_camera_noise_not_trained(tiny_cfg()) == []
    assert warn_camera_noise_not_trained(tiny_cfg("camera.sensor.noise=none", "camera.sensor.sigma=0.01")) == []
