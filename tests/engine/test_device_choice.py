"""Which device a training runs on and what ``train.bf16`` does there (Apple's ``mps`` simulated, as in
test_portability.py). ``train.bf16`` on ``mps`` went to ``torch.autocast("mps", bfloat16)`` unchecked: torch 2.4 has
no autocast on MPS (RuntimeError at the first step, after the data and the run folder were made), torch 2.5 only
float16 (a warning, "Disabling autocast", and a float32 training whose config says bf16). Now one ConfigError before
any work where this torch cannot; ``train.device: auto`` never picks ``mps`` (docs/training.md, "Devices")."""

from __future__ import annotations

import warnings

import pytest
import torch
import torch.amp.autocast_mode as autocast_mode

from hsicam.devices import autocast_problem
from hsicam.engine.loop import resolve_device
from hsicam.errors import ConfigError

TORCH_24 = "User specified an unsupported autocast device_type 'mps'"  # torch's own words (autocast_mode.py)


def _torch_without_mps_autocast(monkeypatch):
    """torch 2.4: no autocast on MPS (its autocast asks is_autocast_available, which said False for mps)."""
    real = autocast_mode.is_autocast_available
    monkeypatch.setattr(autocast_mode, "is_autocast_available", lambda d: d != "mps" and real(d))


def _a_mac(monkeypatch):
    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


def test_no_autocast_problem_on_the_cpu_where_the_network_is_not_autocast(monkeypatch):
    _torch_without_mps_autocast(monkeypatch)
    assert autocast_problem("cpu", torch.bfloat16) is None


def test_a_torch_without_autocast_on_mps_is_a_problem_in_its_own_words(monkeypatch):
    _torch_without_mps_autocast(monkeypatch)
    assert autocast_problem(torch.device("mps"), torch.bfloat16) == TORCH_24


def test_a_torch_that_disables_autocast_in_bfloat16_is_a_problem_in_its_own_words(monkeypatch):
    """torch 2.5: MPS autocast in float16 only; bfloat16 warned and left autocast off."""
    said = ("In MPS autocast, but the target dtype is not supported. Disabling autocast.\n"
            "MPS Autocast only supports dtype of torch.float16 currently.")

    class Autocast25:
        def __init__(self, device_type, dtype=None):
            warnings.warn(said)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

    monkeypatch.setattr(torch, "autocast", Autocast25)
    assert autocast_problem("mps", torch.bfloat16) == " ".join(said.split())


@pytest.mark.skipif(tuple(int(v) for v in torch.__version__.split(".")[:2]) < (2, 6),
                    reason="bfloat16 autocast on MPS: torch 2.6 or newer")
def test_this_torch_can_autocast_mps_in_bfloat16():
    assert autocast_problem("mps", torch.bfloat16) is None


def test_auto_never_picks_mps(monkeypatch):
    _a_mac(monkeypatch)
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("mps") == torch.device("mps")


def test_train_bf16_on_mps_where_torch_cannot_is_refused_before_any_work(monkeypatch, tmp_path, cache_env):
    from hsicam.config import load_config
    from hsicam.engine.train import train

    _a_mac(monkeypatch)
    _torch_without_mps_autocast(monkeypatch)
    run = tmp_path / "run"
    cfg = load_config("tiny", ["train.device=mps", "train.bf16=true", "train.epochs=1"])
    with pytest.raises(ConfigError) as err:
        train(cfg, run, progress=False)
    assert str(err.value) == (f"train.bf16 on mps: torch {torch.__version__} cannot autocast the network there in "
                              f"bfloat16 ({TORCH_24}); set train.bf16=false to train in float32")
    assert not run.exists() and not list(cache_env.iterdir())  # no run folder, no scene generated


# --------------------------------------------------------------------------------------------
# devices.py
# --------------------------------------------------------------------------------------------
def test_dist_env_reads_rank_world_and_local_rank(monkeypatch):
    from hsicam.devices import dist_env

    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    assert dist_env() == (0, 1, 0)
    monkeypatch.setenv("RANK", "5")
    monkeypatch.setenv("WORLD_SIZE", "8")
    monkeypatch.setenv("LOCAL_RANK", "1")
    assert dist_env() == (5, 8, 1)


def test_a_cuda_index_beyond_the_machines_devices_is_named(monkeypatch):
    import torch

    from hsicam.devices import device_problem

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert device_problem("cuda:1") is None and device_problem("cuda") is None
    assert device_problem("cuda:2") == "this machine has 2 CUDA device(s), cuda:0 to cuda:1"


def test_mps_without_an_mps_device_is_refused(monkeypatch):
    import torch

    from hsicam.devices import device_problem

    monkeypatch.setattr(torch.backends.mps, "is_available", lambda: False)
    assert device_problem("mps") == "no MPS device is available here; use cpu"
    assert device_problem("cpu") is None
    assert device_problem("meta") == "hsicam runs on cpu, cuda or mps"
    assert device_problem("banana") == "unknown device; use cpu, cuda, cuda:N or mps"
