"""Calibration: a trained run imaging with measured PSFs, and fine-tuning its network to them.

Fine-tuning (``hsicam finetune``)
---------------------------------
The trained network is adapted to the measured PSFs: the camera becomes a
:class:`~hsicam.cameras.measured.FixedPSFCamera` (the measured stack, the trained CFA, the
configured sensor noise), the DOE and the CFA are frozen, and only the network is trained with
the run's data, loss (L1) and schedule (the one training loop, :func:`hsicam.engine.loop.fit`). The new run
folder is a normal run (``config.yaml``, ``model.safetensors``, ``metrics.jsonl``) plus
``measured_psf.safetensors`` / ``measured_psf.json`` and ``finetune.json`` (validation PSNR
before and after).
"""


from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import torch

from hsicam.data.measured_psf import import_for_camera
from hsicam.engine.linear_step import refresh_linear_step
from hsicam.engine.loop import FitOptions, fit
from hsicam.engine.tasks import SystemTask
from hsicam.errors import InputError
from hsicam.io import write_json
from hsicam.runs.folder import MetricsLog, check_run_dir, load_run, with_measured_psf
from hsicam.runs.lock import RunLock, check_not_locked
from hsicam.runs.measured_psf import MEASURED_PSF_FILE, MeasuredPSF, load_measured_psf, save_measured_psf
from hsicam.runs.pretrained import resolve_run, run_label

log = logging.getLogger(__name__)


def run_psf_fingerprint(run_dir: str | Path) -> str | None:
    """Fingerprint of the measured PSFs a run was fine-tuned on (None for a simulated-optics run)."""
    p = Path(run_dir) / MEASURED_PSF_FILE
    if not p.is_file():
        return None
    return load_measured_psf(p).fingerprint


# ------------------------------------------------------------------------------------------------
# Fine-tuning the network with the optics frozen
# ------------------------------------------------------------------------------------------------
def check_finetune_resume(out_dir: Path) -> None:
    """InputError unless ``out_dir`` holds a fine-tuning to continue (its measured PSFs and a
    checkpoint). Reads only."""
    from hsicam.runs.checkpoint import CheckpointManager

    if not (out_dir / "config.yaml").is_file() or not (out_dir / MEASURED_PSF_FILE).is_file():
        why = "no such folder" if not out_dir.exists() else "not a fine-tuned run (no config.yaml and measured PSFs)"
        raise InputError(f"{out_dir}: nothing to resume ({why}); start the fine-tuning without --resume")
    if CheckpointManager(out_dir).state() is None:
        raise InputError(f"{out_dir}: a fine-tuned run without a checkpoint: nothing to resume; fine-tune again into a "
                         "new folder (without --resume)")


def continued_settings(out_dir: Path, run_dir: Path) -> list[str]:
    """The ``train.*`` and ``data.*`` overrides that turn the source run's config into the one the
    fine-tuning in ``out_dir`` was started with (its config.yaml): what a resume goes on with."""
    import dataclasses
    import json

    from hsicam.config import load_config

    started, source = load_config(out_dir / "config.yaml"), load_config(Path(run_dir) / "config.yaml")
    out = []
    for section in ("train", "data"):
        a, b = getattr(started, section), getattr(source, section)
        for f in dataclasses.fields(a):
            value = getattr(a, f.name)
            if value != getattr(b, f.name):
                plain = dataclasses.asdict(value) if dataclasses.is_dataclass(value) else value
                out.append(f"{section}.{f.name}={json.dumps(plain)}")
    return out


def _same_run(recorded: str, run_dir: Path) -> bool:
    """Whether ``recorded`` (a run's label: a folder, or ``pretrained:NAME``) names the run folder ``run_dir``."""
    try:
        return resolve_run(recorded).resolve() == Path(run_dir).resolve()
    except InputError:  # a shipped camera no longer installed, or a malformed name: not this run
        return False


def check_finetune_source(out_dir: Path, run_dir: Path) -> None:
    """InputError when the fine-tuning in ``out_dir`` was made from another run than ``run_dir`` (checked before the
    run and the PSFs are read: a wrong ``--run`` was blamed on the PSFs, which did not fit its bands). Reads only."""
    from hsicam.runs.folder import finetune_source

    source, _ = finetune_source(out_dir)
    if source is not None and not _same_run(source, run_dir):
        raise InputError(f"{out_dir}: was fine-tuned from {source}, not {run_label(run_dir)}; resume it with --run "
                         f"{source}")


def check_same_measured_psfs(out_dir: Path, psf_dir: str | Path, measured: MeasuredPSF) -> None:
    """InputError when the fine-tuning in ``out_dir`` was made from other measured PSFs than ``measured`` (imported
    from ``psf_dir``): continuing it would mix two calibrations (its source run: :func:`check_finetune_source`,
    checked before the PSFs are read). Reads only."""
    from hsicam.runs.folder import finetune_source
    from hsicam.runs.measured_psf import psf_difference

    _, made_from = finetune_source(out_dir)
    have = run_psf_fingerprint(out_dir)
    if have != measured.fingerprint:
        same = made_from is not None and Path(made_from).resolve() == Path(psf_dir).resolve()
        diff = psf_difference(load_measured_psf(Path(out_dir) / MEASURED_PSF_FILE), measured, psf_dir) if same else None
        why = diff[1] if diff is not None else "another --psf-pitch-um, or files changed since"
        what = (f"the PSFs of {psf_dir} as imported now differ from those it was fine-tuned on ({why})" if same else
                f"was fine-tuned on other measured PSFs{f' (those of {made_from})' if made_from else ''} than {psf_dir}")
        raise InputError(f"{out_dir}: {what} (fingerprint {str(have)[:12]} against {measured.fingerprint[:12]}); "
                         "resume it with the PSFs and pitch it started with, or fine-tune on these into a new folder "
                         "(without --resume)")


class FinetuneTask(SystemTask):
    """:class:`SystemTask` on a measured-PSF camera with the camera's groups frozen (network only);
    the new run folder also stores the measured PSFs it was tuned to."""

    what = "fine-tuning"

    def __init__(self, cfg, model, measured: MeasuredPSF, source_run: Path, psf_dir: str | Path = "") -> None:
        super().__init__(cfg, model, extra_freeze=tuple(model.camera.param_groups()))
        self.measured, self.source_run, self.psf_dir = measured, source_run, psf_dir

    def write_run_files(self, run_dir: Path) -> None:
        super().write_run_files(run_dir)
        save_measured_psf(run_dir / MEASURED_PSF_FILE, self.measured)
        write_json(run_dir / "measured_psf.json", self.measured.report)

    def weights_metadata(self) -> dict[str, str]:
        return {"finetuned_from": run_label(self.source_run), "psf_fingerprint": self.measured.fingerprint,
                "psf_dir": str(Path(self.psf_dir).resolve())}


def finetune(run_dir: str | Path, psf_dir: str | Path, out_dir: str | Path, *, overrides: tuple[str, ...] = (),
             pitch_um: float | None = None, progress: bool | None = None, resume: bool = False,
             stop_after_steps: int | None = None) -> dict[str, Any]:
    """Adapt the network of ``run_dir`` to the measured PSFs of ``psf_dir``; write run ``out_dir``.

    ``overrides`` are dotted config keys applied to the run's config (e.g. ``train.epochs=5``,
    ``train.lr=1e-4``); the optics keys must not change. ``resume``: continue the interrupted (or
    extend the finished) fine-tuning in ``out_dir``, made from the same run and the same measured
    PSFs (both checked first). Returns the summary written to ``finetune.json``: validation
    PSNR/SSIM/SAM with the measured PSFs before and after; a resume of a fine-tuning already finished at its
    epochs returns the loop's record (``already_finished``, ``step``, ``epoch``) and writes nothing.
    """
    run_dir, out_dir = resolve_run(run_dir), Path(out_dir)  # run_dir may be pretrained:NAME
    if out_dir.resolve() == run_dir.resolve():
        raise InputError("--out must be a new run folder, not the run being fine-tuned")
    check_not_locked(out_dir)  # another process trains there: refused before check_run_dir removes its temporaries
    with RunLock(out_dir) as lock:
        if resume and (out_dir / "config.yaml").is_file():
            lock.acquire()  # held from its first change to the last (re-entrant in fit)
        return _finetune(run_dir, psf_dir, out_dir, overrides, pitch_um, progress, resume, stop_after_steps)


#: The camera keys a fine-tuning's ``--set`` may change: the measured PSFs' kernel and the sensor's noise. The others
#: (and ``bands``) describe the optics the PSFs were measured through: a pixel pitch set here resampled the PSFs and
#: fine-tuned the network for a sensor the camera does not have, silently (``--psf-pitch-um`` is the PSFs' pitch).
FINETUNE_CAMERA_KEYS = ("camera.psf.kernel_px", "camera.sensor.noise", "camera.sensor.sigma",
                        "camera.sensor.full_well_e", "camera.sensor.read_noise_e", "camera.sensor.bit_depth")


def check_finetune_overrides(overrides) -> None:
    """InputError naming the first ``--set`` of a fine-tuning that changes the camera or its bands
    (other than :data:`FINETUNE_CAMERA_KEYS`)."""
    from hsicam.config import override_keys

    for key in sorted(override_keys(overrides)):
        if (key.split(".")[0] in ("camera", "bands") and key not in FINETUNE_CAMERA_KEYS
                and not any(k.startswith(key + ".") for k in FINETUNE_CAMERA_KEYS)):
            hint = " (the measured PSFs' own pitch is --psf-pitch-um)" if key == "camera.sensor.pixel_pitch_um" else ""
            raise InputError(f"--set {key}: fine-tuning keeps the camera it fine-tunes (its optics, sensor and bands); "
                             f"it may change {', '.join(FINETUNE_CAMERA_KEYS)}, train.* and the data{hint}")


def _finetune(run_dir: Path, psf_dir, out_dir: Path, overrides, pitch_um, progress, resume, stop_after_steps):
    # before any work, in fine-tuning's words
    check_finetune_overrides(overrides)
    if resume:
        check_finetune_resume(out_dir)
        check_finetune_source(out_dir, run_dir)
    else:
        again = (", or continue the fine-tuning there with --resume" if (out_dir / MEASURED_PSF_FILE).is_file() else "")
        check_run_dir(out_dir, False, f"fine-tuning writes a new run folder: choose another --out{again}")
    if resume:  # it goes on with the settings it was started with (--epochs, --lr, --set), then these
        overrides = (*continued_settings(out_dir, run_dir), *overrides)
    cfg, base = load_run(run_dir, "cpu", tuple(overrides), linear_step=False)  # the fine-tuned run fits its own
    measured = import_for_camera(psf_dir, base.camera, pitch_um=pitch_um)
    if resume:
        check_same_measured_psfs(out_dir, psf_dir, measured)
    torch.manual_seed(cfg.train.seed)
    task = FinetuneTask(cfg, with_measured_psf(base, measured), measured, run_dir, psf_dir)
    opts = FitOptions(cfg.train, cfg.data.num_workers, validate_at_start=True, progress=progress,
                      stop_after_steps=stop_after_steps)

    def then(summary: dict[str, Any]) -> dict[str, Any]:
        # under the run's lock: the linear consistency step's filters through the measured PSFs
        # (those of the source run were fitted through its simulated optics)
        changed = refresh_linear_step(out_dir, cfg.model.consistency, cfg.train.keep_weights)
        return {**summary, "changed": changed} if changed else summary  # (a finished one's resume says them)

    fitted = fit(task, opts, out_dir, resume, then=then)
    if "stopped_at_step" in fitted:  # an interruption simulated by a test: no summary yet
        return fitted
    if fitted.get("already_finished"):  # nothing trained: finetune.json stays the record of what was (its epochs)
        return fitted
    records = MetricsLog(Path(out_dir) / "metrics.jsonl").read()
    vals = [r for r in records if "val_psnr" in r and not r.get("final")]
    strip = lambda r: {k[4:]: v for k, v in r.items() if k.startswith("val_")}  # noqa: E731
    before = strip(vals[0]) if vals and vals[0]["step"] == 0 else {}
    last = strip(vals[-1]) if vals else {}
    best = max(vals, key=lambda r: r["val_psnr"]) if vals else None
    summary = {
        "source_run": run_label(run_dir),  # pretrained:NAME for a shipped camera, not its package folder
        "psf_dir": str(Path(psf_dir).resolve()),  # absolute: the folder named from any working folder
        "psf_fingerprint": measured.fingerprint,
        "frozen": ["camera.optics (DOE)", "camera.cfa"],
        "epochs": cfg.train.epochs,
        "steps": fitted["step"],
        "elapsed_s": fitted["elapsed_s"],
        "before": before,
        "after_last_epoch": last,
        "best_val_psnr": None if best is None else best["val_psnr"],
        "best_epoch": None if best is None else best["epoch"],
        "energy_in_kernel": measured.report["energy_in_kernel"],
    }
    write_json(out_dir / "finetune.json", summary)
    return summary
