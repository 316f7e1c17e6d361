"""The training tasks :func:`hsicam.engine.loop.fit` runs: joint camera + network training
(:class:`SystemTask`; fine-tuning to measured PSFs is the same task with the optics frozen) and
the Choi et al. spectral prior (:class:`PriorTask`)."""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Any, Callable

import torch
import torch.nn.functional as F
import yaml

from hsicam.config import ChoiConfig, Config, TrainConfig, absolute_paths, dump_yaml
from hsicam.data.pipeline import build_datasets, dataset_root
from hsicam.engine.loop import Task, draw_uniform, step_generator
from hsicam.engine.provenance import data_record, generator_change_warning, synthetic_set_record
from hsicam.errors import ConfigError
from hsicam.io import atomic_open, write_json
from hsicam.metrics import psnr_per_band, sam_degrees, ssim
from hsicam.models import CameraSystem
from hsicam.models.demosaic import box_mean
from hsicam.models.priors import SpectralAutoencoder, build_prior
from hsicam.models.registry import check_network_memory
from hsicam.runs.camera_files import camera_files_record

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class GroupRate:
    """How the train section sets a camera parameter group's learning rate: ``key`` (for messages),
    ``rate(train) -> lr`` in the parameters' own units, and ``shown(lr)`` in the key's units."""

    key: str
    rate: Callable[[TrainConfig], float]
    shown: Callable[[float], str]


# The learning rate of each camera parameter group, from the train section (units in the key names).
CAMERA_GROUP_LR = {
    "doe": GroupRate("train.doe_lr_nm", lambda t: t.doe_lr_nm * 1e-9, lambda lr: f"{lr * 1e9:g} nm"),  # metres
    "cfa": GroupRate("train.cfa_lr", lambda t: t.cfa_lr, lambda lr: f"{lr:g}"),
}


def draw_noise(t: TrainConfig, generator: torch.Generator) -> dict[str, float]:
    """The noise levels of one training step, drawn uniformly in the ``train`` ranges.

    Both levels are always drawn (in this order), whatever the camera, so a step's random
    numbers do not depend on the camera kind; each camera uses the levels it has.
    """
    return {"sigma_height_nm": draw_uniform(t.sigma_height_nm, generator),
            "sensor_sigma": draw_uniform(t.sensor_sigma, generator)}


def system_loss(recon: torch.Tensor, truth: torch.Tensor, t: TrainConfig, period: int = 1) -> torch.Tensor:
    """L1 (paper eq. 10), plus ``t.relative_l1`` × the L1 relative to the local brightness of the
    truth, box₉(mean over bands) + ``t.relative_eps``, plus ``t.ssim_loss`` × (1 − SSIM) and
    ``t.sam_loss`` × :func:`spectral_angle_loss`, plus ``t.spectral_grad_loss`` ×
    :func:`spectral_gradient_loss`; (B, C, H, W) pairs → scalar."""
    loss = F.l1_loss(recon, truth)
    if t.relative_l1 > 0:
        local = box_mean(truth.mean(dim=1, keepdim=True), 9) + t.relative_eps
        loss = loss + t.relative_l1 * ((recon - truth).abs() / local).mean()
    if t.ssim_loss > 0:
        loss = loss + t.ssim_loss * (1.0 - ssim(recon, truth, dtype=recon.dtype).mean())
    if t.sam_loss > 0:
        loss = loss + t.sam_loss * spectral_angle_loss(recon, truth, t.relative_eps)
    if t.spectral_grad_loss > 0:
        loss = loss + t.spectral_grad_loss * spectral_gradient_loss(recon, truth)
    if t.phase_loss > 0 and period > 1:
        loss = loss + t.phase_loss * phase_trace_loss(recon - truth, period)
    return loss


def phase_trace_loss(error: torch.Tensor, period: int) -> torch.Tensor:
    """Mean |ē_p − ē| (B, C, H, W) → scalar: ē_p the error averaged over the pixels of phase p = (i mod
    m, j mod m) of the window (the top-left m·⌊H/m⌋ × m·⌊W/m⌋ px), ē its mean over the m² phases: the
    error's m-periodic part, the trace of the CFA period; 0 for an error that does not depend on phase."""
    m = int(period)
    b, c, h, w = error.shape
    hm, wm = h // m * m, w // m * m
    if hm == 0 or wm == 0:
        return error.sum() * 0.0
    per_phase = error[..., :hm, :wm].reshape(b, c, hm // m, m, wm // m, m).mean(dim=(2, 4))  # (B, C, m, m)
    return (per_phase - per_phase.mean(dim=(-2, -1), keepdim=True)).abs().mean()


def spectral_gradient_loss(recon: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Mean |Δx̂ − Δx| over pixels and the C − 1 band steps, Δx = x[:, 1:] − x[:, :-1] (B, C, H, W)
    → scalar: L1 on the spectrum's shape, blind to a level offset common to all bands; 0 for one band."""
    if recon.shape[1] < 2:
        return recon.sum() * 0.0
    return F.l1_loss(recon.diff(dim=1), truth.diff(dim=1))


SAM_LOSS_FLOOR = 1e-3  # spectral_angle_loss: the estimate's norm floor, relative to its batch's typical level


def spectral_angle_loss(recon: torch.Tensor, truth: torch.Tensor, min_brightness: float) -> torch.Tensor:
    """Mean spectral angle (radians) over the pixels whose truth has a mean over bands above
    ``min_brightness`` (dark pixels fix no spectrum, and acos has no gradient at 1); 0 if none.

    The angle's gradient has the size 1/|x̂|: an estimate of (near) zero at one bright pixel gave 1e11 there,
    1e18 at 1e-20 of its truth, inf below, and under ``train.grad_clip`` set the whole step's direction. So
    the estimate's norm has a floor: with u = x̂ / (peak(x) · s), s the batch's typical level of estimate
    against truth (the median over the kept pixels of peak(x̂)/peak(x), which the dark pixels' large ratios do
    not raise; a constant for autograd; 1 where it is 0), |u| under δ = SAM_LOSS_FLOOR counts as
    r = (|u|² + δ²)/(2δ) ≥ δ/2 (the same value and slope at δ). The angle is exact where |u| ≥ δ, and its gradient
    in u has the size 1/r (r = |u| above δ) ≤ 2/δ: ≤ 2/(δ · peak(x) · s · K) per pixel of x̂, K kept pixels.
    Dividing the spectra by positive factors leaves the angle as it is and keeps it free of the data's and of
    the estimate's overall scale (float32 from 1e-15 to 1e15)."""
    keep = truth.mean(dim=1) > min_brightness  # (B, H, W)
    if not bool(keep.any()):
        return recon.sum() * 0.0
    peak = truth.abs().amax(dim=1)  # (B, H, W); kept: >= the band mean > min_brightness > 0
    peak = torch.where(keep, peak, torch.ones_like(peak))[:, None]  # (the others are dropped below)
    with torch.no_grad():
        level = (recon.abs().amax(dim=1, keepdim=True) / peak)[:, 0][keep].median()
        level = torch.where(level > 0, level, torch.ones_like(level))
    # |y|² in [1, C] and |u|² about as much for a typical kept pixel; the dropped pixels' u is set to 0 (the
    # estimate of a dark truth over the batch's level could overflow, and an inf there poisons the gradient)
    u, y = torch.where(keep[:, None], recon / (peak * level), 0.0), truth / peak
    u2, dot, y2 = (u * u).sum(dim=1)[keep], (u * y).sum(dim=1)[keep], (y * y).sum(dim=1)[keep]
    d = SAM_LOSS_FLOOR
    norm_u = torch.where(u2 >= d * d, u2.clamp_min(d * d).sqrt(), (u2 + d * d) / (2 * d))
    cos = dot / (norm_u * y2.sqrt())
    return torch.acos(cos.clamp(-1.0 + 1e-6, 1.0 - 1e-6)).mean()


def apply_noise(camera, levels: dict[str, float]) -> None:
    """Set the levels of ``levels`` that ``camera`` has (others do not apply to it)."""
    known = camera.noise_levels()
    camera.set_noise(**{k: v for k, v in levels.items() if k in known})


#: The seed of the validation's noise draws in training (:func:`validate_system`): one for every run, whatever its
#: ``train.seed``, so runs of different seeds are scored on the same draws (paired). 0: the draws of ``train.seed: 0``,
#: the seed every run validated under before (session 60), so their metrics.jsonl stay comparable.
VALIDATION_NOISE_SEED = 0


@torch.no_grad()
def validate_system(model: CameraSystem, loader, device: torch.device,
                    seed: int = VALIDATION_NOISE_SEED) -> dict[str, float]:
    """Mean PSNR (per band, peak 1), SSIM and SAM (°) over the validation patches.

    Reconstructions are clipped to [0, 1] before scoring; noise is the camera's current noise,
    drawn from the fixed ``seed`` (training: :data:`VALIDATION_NOISE_SEED`, not ``train.seed``).
    """
    g = step_generator(seed, 0, 0, device)
    sums = {"psnr": 0.0, "ssim": 0.0, "sam": 0.0}
    n = n_sam = 0
    for scene in loader:
        scene = scene.to(device)
        recon, _ = model(scene, g)
        recon, truth = recon.float().clamp(0, 1), model.target(scene)
        sums["psnr"] += psnr_per_band(recon, truth).sum().item()
        sums["ssim"] += ssim(recon, truth).sum().item()
        sam = sam_degrees(recon, truth)  # NaN for a patch whose truth is black everywhere: it has no angle
        sums["sam"] += sam.nan_to_num(0.0).sum().item()
        n_sam += int((~sam.isnan()).sum())
        n += scene.shape[0]
    out = {k: v / max(n, 1) for k, v in sums.items()}
    out["sam"] = sums["sam"] / n_sam if n_sam else float("nan")
    return out


class _ConfigDataTask(Task):
    """A task trained on the scenes of its config's ``data`` section (``self.cfg.data``, on ``self.bands``): the
    synthetic set generated (or a folder listed) once before the ranks read it, recorded in ``RUN/data.json``, and a
    resume warned when the generator version changed since the run began."""

    cfg: Config

    def prepare_data(self) -> None:
        dataset_root(self.cfg.data, self.bands)

    def data_record(self) -> dict[str, Any] | None:
        return data_record(self.cfg.data, self.bands)

    def synthetic_set(self) -> dict[str, Any] | None:
        return synthetic_set_record(self.cfg.data, self.bands)

    def resume_warning(self, run_dir: Path) -> str | None:
        return generator_change_warning(run_dir, self.cfg.data, "goes on")


class SystemTask(_ConfigDataTask):
    """Camera + network trained end to end: each step simulates sensor images of ground-truth
    patches through the *current* optics, reconstructs them, loss L1 (paper eq. 10).

    Optimizer groups: ``net`` (``train.lr``) and the camera's declared groups (DOE camera:
    ``doe`` at ``train.doe_lr_nm``, ``cfa`` at ``train.cfa_lr``), minus ``train.freeze``.
    Noise: ``train.sigma_height_nm`` / ``train.sensor_sigma`` ranges drawn per step; validation
    uses the camera's configured noise.

    ``train.optics_steps`` = N: from step N on, the camera's groups get no gradient and every batch
    is imaged through ``camera.fixed_measure()`` (no autograd through the optics; the DOE camera's
    PSFs computed once per run or resume), so only the network learns, at network-only step cost.
    """

    def __init__(self, cfg: Config, model: CameraSystem, extra_freeze: tuple[str, ...] = ()) -> None:
        self.cfg, self.model = absolute_paths(cfg), model  # config.yaml names the data and camera files from anywhere
        self.bands = model.bands
        self.eval_noise = model.camera.noise_levels()
        self.freeze = set(cfg.train.freeze) | set(extra_freeze)
        self.find_unused_parameters = cfg.train.optics_steps is not None
        self._fixed_measure = None  # camera.fixed_measure() once the optics are fixed
        known = {"net", *model.camera.param_groups()}
        unknown = sorted(set(cfg.train.freeze) - known)  # e.g. `doe` on a CASSI camera: nothing to freeze
        if unknown:
            # a group the camera kind has but this config switched off: say so (it read "unknown group doe for the
            # doe camera")
            off = [g for g in unknown if g in ("doe", "cfa") and model.camera.kind == "doe"
                   and not getattr(getattr(cfg.camera, g, None), "enabled", True)]
            why = "".join(f"; camera.{g}.enabled is false, so there is no {g.upper()} to freeze" for g in off)
            raise ConfigError(f"train.freeze: unknown parameter group(s) {', '.join(unknown)} for the "
                              f"{model.camera.kind} camera; it has {', '.join(sorted(known))}{why}")
        self._check_something_trains()
        self._check_camera_rates()
        if "net" not in self.freeze:  # the network was built for its weights; its training needs 4× that
            check_network_memory(cfg, model.camera, training=True)

    def _check_camera_rates(self) -> None:
        """ConfigError, before any work, for a camera group trained at a rate as large as the span its
        parameters take (:meth:`~hsicam.cameras.base.Camera.param_group_spans`): Adam moves every
        parameter by about its rate per step, so each step would throw it across that span (e.g.
        ``train.doe_lr_nm=1e30`` trained on without an error, its heights noise)."""
        t, spans = self.cfg.train, self.model.camera.param_group_spans()
        for name in self.model.camera.param_groups():
            if name in self.freeze or name not in spans or name not in CAMERA_GROUP_LR:
                continue
            g, (span, what) = CAMERA_GROUP_LR[name], spans[name]
            lr = g.rate(t)
            if lr >= span:
                raise ConfigError(f"{g.key}={g.shown(lr)}: Adam moves each parameter by about that much per step, no "
                                  f"less than {what}; use a rate well below {g.shown(span)} (default "
                                  f"{g.shown(g.rate(TrainConfig()))}), or freeze the group (train.freeze=[{name}])")

    def _check_something_trains(self) -> None:
        """ConfigError, before any work, when ``train.freeze`` leaves no group to train, or freezes the
        network while ``train.optics_steps`` leaves only the network to train after that step."""
        t = self.cfg.train
        groups = {"net": list(self.model.net.parameters()), **self.model.camera.param_groups()}
        trained = sorted(n for n, params in groups.items() if n not in self.freeze and len(list(params)) > 0)
        frozen = f"train.freeze=[{', '.join(sorted(self.cfg.train.freeze))}]"
        if not trained:
            raise ConfigError(f"{frozen} leaves nothing to train (this {self.model.camera.kind} camera's groups with "
                              f"parameters: {', '.join(sorted(n for n, p in groups.items() if len(list(p)) > 0))})")
        if t.optics_steps is not None and "net" in self.freeze:
            raise ConfigError(f"{frozen} with train.optics_steps={t.optics_steps}: after step {t.optics_steps} only the "
                              "network trains, and it is frozen; drop one of the two")
        if len(self.model.camera.bands) == 1:  # terms over the band axis: nothing to compare across one band
            idle = [f"{k}={v:g}" for k, v in (("train.spectral_grad_loss", t.spectral_grad_loss),
                                              ("train.sam_loss", t.sam_loss),
                                              ("data.augment_relight", self.cfg.data.augment_relight)) if v]
            if idle:
                log.warning("%s does nothing with one band (a spectrum of one band has no shape: no band-to-band "
                            "difference, angle or relighting)", ", ".join(idle))
        optics = [n for n, params in self.model.camera.param_groups().items() if len(list(params)) > 0]
        if t.optics_steps is not None and not optics:  # (frozen optics still gain: their PSFs are fixed from step N)
            log.warning("train.optics_steps=%d does nothing: this %s camera has no optics parameters (the network alone "
                        "trains, from the first step as after it)", t.optics_steps, self.model.camera.kind)

    def module(self) -> CameraSystem:
        return self.model

    def param_groups(self) -> list[dict[str, Any]]:
        t = self.cfg.train
        named = {"net": (list(self.model.net.parameters()), t.lr)}
        for name, params in self.model.camera.param_groups().items():
            if name not in CAMERA_GROUP_LR:
                raise ConfigError(f"camera parameter group {name!r} has no learning rate in the train section")
            named[name] = (params, CAMERA_GROUP_LR[name].rate(t))
        groups = []
        for name, (params, lr) in named.items():
            if name in self.freeze:
                for p in params:
                    p.requires_grad_(False)
            else:
                groups.append({"params": params, "lr": lr, "name": name})
        return groups

    def write_run_files(self, run_dir: Path) -> None:
        with atomic_open(run_dir / "config.yaml", encoding="utf-8") as fh:
            fh.write(dump_yaml(self.cfg))

    def camera_record(self) -> dict[str, Any] | None:
        return camera_files_record(self.cfg)

    def on_device(self, device: torch.device) -> None:
        t = self.cfg.train
        if t.bf16:
            self.model.autocast_dtype = torch.bfloat16
        if t.channels_last:
            self.model.net.to(memory_format=torch.channels_last)
        if t.compile:
            self.model.net.compile()  # in place: state-dict keys stay those of the plain module

    def datasets(self):
        return build_datasets(self.cfg.data, self.bands, self.model.camera.margin,
                              code_period=getattr(self.model.camera, "code_period", 1), stream=self.cfg.train.seed)

    def on_step_start(self, step: int, generator: torch.Generator) -> None:
        apply_noise(self.model.camera, draw_noise(self.cfg.train, generator))
        n = self.cfg.train.optics_steps
        if n is None or step < n:
            self._fixed_measure = None
        elif self._fixed_measure is None:  # the optics have had their last update
            self._fixed_measure = self.model.camera.fixed_measure()

    def training_step(self, trainable, scene: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        recon, _ = trainable(scene, generator, measure=self._fixed_measure)
        return system_loss(recon.float(), self.model.target(scene), self.cfg.train,
                           getattr(self.model.camera, "code_period", 1))

    def noisy_validation(self) -> bool:
        return any(v > 0 for v in self.eval_noise.values())

    def validate(self, loader, device: torch.device) -> dict[str, float]:
        self.model.camera.set_noise(**self.eval_noise)
        return validate_system(self.model, loader, device, VALIDATION_NOISE_SEED)

    def on_fit_end(self, run_dir: Path, summary: dict[str, Any]) -> dict[str, Any]:
        self.model.camera.set_noise(**self.eval_noise)
        return summary


class PriorTask(_ConfigDataTask):
    """The Choi et al. spectral prior: a denoising autoencoder on training-split patches of
    ``cfg.data`` (bands ``cfg.bands``); inputs corrupted by Gaussian noise of σ uniform in
    [0, ``train_noise``] per patch, loss MSE. Writes ``prior.safetensors`` and, last,
    ``summary.json`` (the run is finished)."""

    weights_file = "prior.safetensors"
    what = "prior training"
    batch_size_key = "baselines.choi.batch_size"
    seed_key = "baselines.choi.seed"

    def __init__(self, cfg: Config, settings: ChoiConfig) -> None:
        self.cfg, self.settings = absolute_paths(cfg), settings  # config.yaml names the data from anywhere
        self.bands = cfg.bands.to_bands()
        self.model = build_prior(settings, len(self.bands), training=True)  # refused when it cannot train

    def loop_config(self) -> TrainConfig:
        """The loop settings: ``train_steps`` steps of cosine-decayed Adam, validation at the end."""
        s = self.settings
        return TrainConfig(epochs=s.train_steps, batch_size=s.batch_size, lr=s.lr, lr_schedule="cosine",
                           grad_clip=None, eval_every_epochs=s.train_steps, checkpoint_every_steps=500,
                           log_every_steps=50, seed=s.seed, device=self.cfg.train.device,
                           max_minutes=self.cfg.train.max_minutes)

    def module(self) -> SpectralAutoencoder:
        return self.model

    def param_groups(self) -> list[dict[str, Any]]:
        return [{"params": list(self.model.parameters()), "lr": self.settings.lr, "name": "prior"}]

    def write_run_files(self, run_dir: Path) -> None:
        with atomic_open(run_dir / "config.yaml", encoding="utf-8") as fh:
            fh.write(dump_yaml(self.cfg))
        with atomic_open(run_dir / "prior.yaml", encoding="utf-8") as fh:
            fh.write(yaml.safe_dump(dataclasses.asdict(self.settings), sort_keys=False))

    def datasets(self):
        """The published prior's training data: clean patches, never relit (``data.augment_relight`` is
        a setting of the camera's own training; :data:`hsicam.engine.prior.PRIOR_UNREAD_DATA_KEYS`). The
        training patches' stream is the prior's own ``baselines.choi.seed`` (0: ``data.split_seed``'s alone)."""
        return build_datasets(dataclasses.replace(self.cfg.data, augment_relight=0.0), self.bands, 0,
                              stream=self.settings.seed)

    def training_step(self, trainable, clean: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        b = clean.shape[0]
        sig = torch.rand((b, 1, 1, 1), generator=generator, device=generator.device) * self.settings.train_noise
        noise = torch.randn(clean.shape, generator=generator, device=generator.device)
        noisy = clean + sig.to(clean.device) * noise.to(clean.device)
        return F.mse_loss(trainable(noisy), clean)

    def validate(self, loader, device: torch.device) -> dict[str, float]:
        se, n = 0.0, 0
        with torch.no_grad():  # (the loop validates under no_grad too; a direct call builds no graph)
            for clean in loader:
                clean = clean.to(device)
                se += float((self.model(clean) - clean).square().sum())
                n += clean.numel()
        return {"psnr": -10 * math.log10(max(se / max(n, 1), 1e-30))}

    def weights_metadata(self) -> dict[str, str]:
        return {"kind": "choi-spectral-prior"}

    def on_fit_end(self, run_dir: Path, summary: dict[str, Any]) -> dict[str, Any]:
        out = {k: v for k, v in summary.items() if not k.startswith("val_")}
        if "val_psnr" in summary:
            out["val_psnr_autoencoder"] = summary["val_psnr"]
        write_json(run_dir / "summary.json", out)
        return out
