"""Items earlier sessions noticed and left alone (session 60): the held-out-sources scenes' capture noise,
the checkpoint hash cache and root sync, ``stage_kernel_px`` on CASSI cameras, an empty job's progress line."""

from __future__ import annotations

import dataclasses
import json
import zlib

import pytest
import torch

from cli_helpers import module_cache, run_cli_in_process
from damage import flip_byte_in_place
from hsicam.io import _HASHES as hashes_read  # the file hashes read in this process


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    yield from module_cache(tmp_path_factory)


def test_a_scene_set_gets_its_own_capture_noise_and_the_default_set_keeps_its_seeds():
    """evaluate_method's capture noise under noise seed s: a scene of the default set (the validation split) from
    crc32("s:name"), as before; the same scene name in another set (``scene_set``, the held-out sources) an
    independent field (it was the same one: correlation 1.0)."""
    from hsicam.cameras import DDCASSICamera
    from hsicam.config import load_config
    from hsicam.engine.evaluate import HELDOUT_NOISE_SET, TestNoise, evaluate_method
    from hsicam.engine.methods import Method

    cfg = load_config("tiny", ["camera.kind=dd_cassi", "camera.sensor.sigma=0.05", "model.consistency.iterations=0"])
    cam = DDCASSICamera.from_config(cfg)
    scene = torch.rand(len(cam.bands), 24, 24, generator=torch.Generator().manual_seed(1))
    sensors = []

    def record(sensor):
        sensors.append(sensor.clone())
        return cam.A_adjoint(sensor)

    method = Method("probe", cam, record, lambda s: s)
    for scene_set in (None, HELDOUT_NOISE_SET):
        evaluate_method(method, [scene], ["scene_0000"], TestNoise(seeds=(3,)), keep_arrays=False, scene_set=scene_set)
    with torch.no_grad():
        clean = cam.A(scene[None])
        expect = cam(scene[None], sensor_generator=torch.Generator().manual_seed(zlib.crc32(b"3:scene_0000")))
    torch.testing.assert_close(sensors[0], expect, rtol=0, atol=0)
    e_val, e_held = ((s - clean).flatten() for s in sensors)
    assert float(e_held.std()) > 0.04  # noise was applied to the held-out capture too
    assert abs(float(torch.corrcoef(torch.stack([e_val, e_held]))[0, 1])) < 0.2


@pytest.mark.slow
def test_heldout_scenes_get_noise_independent_of_the_validation_scenes_of_the_same_name(env, tmp_path, monkeypatch):
    """`hsicam evaluate` scores the validation split and the held-out-sources scenes, both named scene_0000…:
    a validation scene and the held-out scene of the same name were captured with one noise field (correlation
    1.0 under Gaussian σ_s). The held-out scenes now get their own; the validation scenes keep the seed of
    their name alone (crc32 of "seed:name"), so documented noisy figures stay valid."""
    import hsicam.engine.methods as methods
    from hsicam.config import load_config
    from hsicam.engine.experiments import heldout_scenes, validation_scenes

    built, sensors = [], []
    real_build = methods.build_method

    def recording_build(*args, **kwargs):  # the real method; its reconstruction a cheap adjoint, recorded
        m = real_build(*args, **kwargs)
        built.append(m)

        def fn(sensor):
            sensors.append(sensor.clone())
            return m.camera.A_adjoint(sensor)
        return dataclasses.replace(m, reconstruct=fn)

    monkeypatch.setattr(methods, "build_method", recording_build)
    res = run_cli_in_process("evaluate", "--config", "tiny", "--method", "dd-cassi-gaptv", "--sensor-sigma", "0.05",
                             "--out", str(tmp_path / "ev"), env=env)
    assert res.returncode == 0, res.stderr
    cfg = load_config("tiny")
    (val, val_names), (held, held_names) = validation_scenes(cfg), heldout_scenes(cfg)
    assert len(sensors) == len(val_names) + len(held_names)
    val_sensors, held_sensors = dict(zip(val_names, sensors)), dict(zip(held_names, sensors[len(val_names):]))
    common = sorted(set(val_names) & set(held_names))
    assert common, (val_names, held_names)  # the two sets share scene names: the case at stake
    cam = built[0].camera
    cam.set_noise(**{**cam.noise_levels(), "sensor_sigma": 0.05})  # as evaluate applied --sensor-sigma
    with torch.no_grad():
        for i, name in enumerate(val_names):  # the validation seeds as documented: crc32("0:scene_name")
            expect = cam(val[i][None], sensor_generator=torch.Generator().manual_seed(zlib.crc32(f"0:{name}".encode())))
            torch.testing.assert_close(val_sensors[name], expect, rtol=0, atol=0)
        for name in common:
            e_val = (val_sensors[name] - cam.A(val[val_names.index(name)][None])).flatten()
            e_held = (held_sensors[name] - cam.A(held[held_names.index(name)][None])).flatten()
            corr = float(torch.corrcoef(torch.stack([e_val, e_held]))[0, 1])
            assert abs(corr) < 0.2, (name, corr)


def test_file_sha256_hashes_again_a_file_changed_in_place_with_its_mtime_set_back(tmp_path):
    """A byte flipped in place (same path, inode and size), the mtime set back to the ns (os.utime): the per-process
    cache handed out the old hash (keyed on path, inode, size, mtime); the change time moves on any write."""
    import hashlib
    import os

    from hsicam.io import file_sha256

    path = tmp_path / "w.safetensors"
    path.write_bytes(bytes(range(256)) * 16)
    first = file_sha256(path)
    st = path.stat()
    flip_byte_in_place(path, 100)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))
    after = path.stat()
    assert (after.st_ino, after.st_size, after.st_mtime_ns) == (st.st_ino, st.st_size, st.st_mtime_ns)  # the case
    assert hashlib.sha256(path.read_bytes()).hexdigest() != first
    assert file_sha256(path) == hashlib.sha256(path.read_bytes()).hexdigest()


def test_root_sync_does_not_copy_a_damaged_checkpoint_and_says_so(tmp_path, caplog):
    """The root weights missing, the kept checkpoint's weights with a flipped byte: sync_root copied the damaged
    file to the run root without a word (readers then refused both). It now leaves the root alone, with one warning."""
    import logging

    from hsicam.runs.checkpoint import MANIFEST, RECOPY_HINT, CheckpointManager
    from hsicam.spectral import Bands

    run = tmp_path / "run"
    net = torch.nn.Linear(2, 3)
    mgr = CheckpointManager(run)
    mgr.save(net, torch.optim.Adam(net.parameters()), {"global_step": 1, "best_psnr": None}, Bands.uniform(500, 600, 50))
    root, kept = run / "model.safetensors", run / "checkpoints" / "step-00000001" / "model.safetensors"
    sha = json.loads((run / MANIFEST).read_text())["weights"]["sha256"]
    assert root.read_bytes() == kept.read_bytes()  # an undamaged checkpoint is copied
    root.unlink()
    flip_byte_in_place(kept, kept.stat().st_size - 3)  # in the tensors' bytes
    hashes_read.clear()  # as a new process (a resume) would see it
    with caplog.at_level(logging.WARNING, logger="hsicam.runs.checkpoint"):
        assert mgr.sync_root() is False
        assert mgr.sync_root() is False  # the next save's sync (a resumed run: one per epoch) says it no more
    assert not root.exists()
    assert [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING] == [
        f"{kept} differs from the weights {run / MANIFEST} records (sha256 {sha[:12]}…): the checkpoint is damaged (a "
        f"copy cut short, a disk error, an edit), so {root} was not rewritten from it; {RECOPY_HINT}"]


def test_stage_kernel_px_on_a_cassi_camera_is_not_silently_ignored(tiny_config, caplog):
    """model.unrolled.stage_kernel_px cuts the DOE camera's PSF in the stages; a CASSI camera has no kernel, and the
    key (31 on the quick preset) went unapplied without a word. Not refused (runs trained so must still load) nor
    warned about (the quick preset's own dd-cassi-unrolled baseline carries it): one note naming the key, none when
    it is 0, and none on the DOE camera, whose kernel it cuts."""
    import logging

    from hsicam.cameras import build_camera
    from hsicam.models.unrolled import build_unrolled

    def built(cfg):
        camera = build_camera(cfg)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="hsicam.models.unrolled"):
            net = build_unrolled(cfg.model.unrolled, camera)
        return camera, net, [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]

    for kind in ("dd_cassi", "sd_cassi"):
        for px in (31, 0):
            camera, _, said = built(tiny_config(f"camera.kind={kind}", "model.kind=unrolled", "model.unrolled.init=backprojection",
                                                "model.consistency.iterations=0", f"model.unrolled.stage_kernel_px={px}"))
            assert said == ([] if px == 0 else [
                f"model.unrolled.stage_kernel_px=31 is not applied: it cuts the DOE camera's PSF in the stages, and "
                f"{type(camera).__name__} has no PSF kernel to cut (its stages use its exact operator)"]), kind
    camera, net, said = built(tiny_config("model.kind=unrolled", "model.unrolled.stage_kernel_px=3"))
    assert said == [] and camera.margin > 2 and net.op_reach == (2, 2)  # the DOE camera's kernel cut to 3 px


@pytest.mark.parametrize("show", [None, True])
def test_an_empty_job_says_0_of_0_once(show, caplog, monkeypatch):
    """Progress(0): nothing was said (and an update read "1/0 points"); now one line saying there is nothing to do,
    on a terminal too (no bare tqdm counter); nothing with show=False; a negative total is refused."""
    import logging
    import sys

    from hsicam.progress import Progress, progress

    monkeypatch.setattr(sys.stderr, "isatty", lambda: False)  # the CLI's lines (show=None), as in a log file
    with caplog.at_level(logging.INFO, logger="hsicam.progress"):
        with Progress(0, "tolerance", "point", show=show) as bar:
            bar.update()  # (a caller that miscounts: no "1/0")
        assert list(progress([], 0, "synthetic train set", "scene", show=show)) == []
        with Progress(0, "quiet", show=False):
            pass
    assert [r.getMessage() for r in caplog.records] == ["tolerance: 0/0 points, nothing to do",
                                                        "synthetic train set: 0/0 scenes, nothing to do"]
    with pytest.raises(ValueError, match=r"^total must be >= 0 \(the number of items\), got -1$"):
        Progress(-1, "x")
