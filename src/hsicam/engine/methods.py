"""Reconstruction methods, so evaluation treats the learned camera and the baselines alike.

A method owns a camera (the forward model that makes its measurement) and a reconstruction:

    y = method.camera(scene)            # simulated measurement (noise included)
    x̂ = method.reconstruct(y)           # cube aligned with method.camera's sensor area

Methods are registered by name (:func:`register_method`); :func:`build_method` looks them up
(and the old names in :data:`METHOD_ALIASES`).

    doe-learned      our learned camera (any network kind: rdn, mosaic, unrolled), from a run folder
                     (``doe-rdn``, its name when the RDN was its only network, still works)
    doe-box-demosaic the network-free per-band box demosaic through a run's optics (the reference)
    doe-tent-demosaic the same with the weighted-bilinear (tent) demosaic: a tent-skip network's start
    doe-linear-demosaic the best linear reconstruction through a run's optics: a filter per CFA phase and
                     band, least squares on the evaluation data's training split (the LMMSE demosaic)
    dd-cassi-gaptv   DD-CASSI + GAP-TV                 settings: baselines.gaptv
    dd-cassi-desci   DD-CASSI + DeSCI                  settings: baselines.desci (preset fast|full)
    dd-cassi-choi    DD-CASSI + Choi et al. ADMM       run: a spectral-prior folder (hsicam baseline train-prior);
                                                       ADMM settings: baselines.choi of the evaluation config when
                                                       set, else the folder's prior.yaml
    dd-cassi-rdn     DD-CASSI + the paper's RDN        run: `hsicam train --config dd_cassi_rdn` (or with
                                                       model.rdn.backprojection_input: the code-aware input)
    dd-cassi-unrolled DD-CASSI + the unrolled network  run: trained with camera.kind=dd_cassi, model.kind=unrolled
                                                       (GAP data steps with the CASSI operator + learned priors)

The DD-CASSI camera of the iterative methods is built from the evaluation config's band grid,
``camera.cassi`` and ``camera.sensor`` (whatever ``camera.kind`` says); the learned methods use
their run's own camera. CASSI has no blur, so the ground truth is the whole scene and every
reconstruction has the scene's size; where the evaluation config's camera is a DOE camera in
``valid`` mode (``--config quick``) the iterative methods are scored on that camera's sensor area
(:func:`compared_border_px`), and ``hsicam experiment compare`` scores every CASSI row there: one
table, the same pixels.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import torch

from hsicam.cameras import Camera, DDCASSICamera
from hsicam.config import load_config, override_keys
from hsicam.data.pipeline import scene_dataset, split_dataset
from hsicam.engine.prior import load_prior
from hsicam.errors import InputError
from hsicam.engine.linear_step import LINEAR_MAP_RIDGE, fit_linear_map
from hsicam.engine.names import METHOD_ALIASES  # old name → registered name (the CLI reads it torch-free)
from hsicam.models.demosaic import camera_demosaic, phase_linear
from hsicam.runs.folder import linear_step_problem, load_run
from hsicam.runs.pretrained import resolve_run
from hsicam.sensor import SensorNoise
from hsicam.solvers.choi import admm_prior
from hsicam.solvers.desci import desci, desci_settings
from hsicam.solvers.gaptv import gap_tv


@dataclass
class Method:
    """A named camera + reconstruction pair.

    Attributes:
        name: method name (a registered one, or a descriptive name for references).
        camera: forward model; ``camera.boundary`` decides the scene/sensor geometry.
        reconstruct: measurement (B, 1, H', W') → cube (B, C, H, W) on ``camera.bands``,
            aligned with ``target(scene)``.
        target: scene (B, C, H0, W0) → the ground truth the reconstruction is compared with.
        info: facts for result files (run folder, iterations, ...).
        model: the trained camera + network system of a learned method (None for the others).
        prepare: work before the first reconstruction (a fit), which
            :func:`~hsicam.engine.evaluate.evaluate_method` runs once the scenes are checked, outside
            the timed reconstructions (None: none).
        border_px: px left out of the score on every side of ``target(scene)`` and of the
            reconstruction (which still covers all of it): a CASSI method scored on the pixels a DOE
            camera scores, the scene less its kernel margin, where the two are compared
            (:func:`compared_border_px`). 0: all of ``target``.
    """

    name: str
    camera: Camera
    reconstruct: Callable[[torch.Tensor], torch.Tensor]
    target: Callable[[torch.Tensor], torch.Tensor]
    info: dict[str, Any] = field(default_factory=dict)
    model: Any = None
    prepare: Callable[[], Any] | None = None
    border_px: int = 0


Builder = Callable[[Any, "str | Path | None", "str | torch.device"], Method]
METHODS: dict[str, Builder] = {}


def register_method(name: str) -> Callable[[Builder], Builder]:
    """Decorator: register ``builder(cfg, run, device) -> Method`` under ``name``."""

    def deco(builder: Builder) -> Builder:
        METHODS[name] = builder
        return builder

    return deco


def build_method(name: str, cfg, run: str | Path | None = None, device: str | torch.device = "cpu") -> Method:
    """Method ``name``. ``cfg`` is the evaluation config (band grid, camera noise, data, baselines);
    ``run`` is a trained run folder for learned methods."""
    name = METHOD_ALIASES.get(name, name)
    if name not in METHODS:
        raise InputError(f"unknown method {name!r}; choose one of {', '.join(method_names())}")
    return METHODS[name](cfg, run, device)


def method_names() -> tuple[str, ...]:
    """The registered method names (ours first, then the baselines)."""
    return tuple(METHODS)


def baseline_names() -> tuple[str, ...]:
    """The CASSI baselines of Table 1."""
    return tuple(n for n in METHODS if n.startswith("dd-cassi-"))


def learned_method(name: str, model, run: str | Path, **info: Any) -> Method:
    """A :class:`Method` of a trained camera + network system."""
    return Method(name, model.camera, model.reconstructor(), model.target, {"run": str(run), **info}, model)


#: The network-free demosaic references by kernel (:func:`demosaic_reference`).
DEMOSAIC_REFERENCE_NAMES = {"box": "CFA box demosaic (no network)",
                            "tent": "CFA tent demosaic, weighted bilinear (no network)"}


def demosaic_reference(model, kernel: str = "box", window: int | None = None) -> Method:
    """The per-band demosaic of the sensor image through the model's optics
    (:func:`hsicam.models.demosaic.camera_demosaic`, ``kernel`` "box" or "tent", ``window`` px or
    None for the CFA's default), as a network-free method: what the network adds is its score
    minus this one. Needs a camera with a per-band sensor code (the CFA)."""
    if kernel not in DEMOSAIC_REFERENCE_NAMES:
        raise ValueError(f"demosaic kernel must be one of {', '.join(DEMOSAIC_REFERENCE_NAMES)}, got {kernel!r}")
    try:
        model.camera.sensor_code(1, 1)
    except NotImplementedError:
        raise ValueError(f"the demosaic reference needs a camera with a per-band sensor code, not "
                         f"{type(model.camera).__name__}") from None

    def reconstruct(sensor: torch.Tensor) -> torch.Tensor:
        return camera_demosaic(model.camera, sensor, kernel=kernel, window=window)

    return Method(DEMOSAIC_REFERENCE_NAMES[kernel], model.camera, reconstruct, model.target, {})


#: Name of the least-squares linear reference (:func:`linear_demosaic_reference`).
LINEAR_REFERENCE_NAME = "CFA linear demosaic, least squares on the training scenes (no network)"

#: Its neighbourhood (px): 11 px scored within 0.01 dB of 15 px on the demo's camera, 7 px 0.3 dB lower.
LINEAR_REFERENCE_WINDOW = 11


def linear_reference_window(camera, window: int = LINEAR_REFERENCE_WINDOW) -> int:
    """The side (px) of :func:`linear_demosaic_reference`'s fitted filters: ``window``, grown to the
    camera's CFA period (made odd) when that is wider (the flat-field fit sees every CFA phase)."""
    return max(window, getattr(camera, "code_period", 1) | 1)


def linear_demosaic_reference(model, train_scenes, window: int = LINEAR_REFERENCE_WINDOW,
                              ridge: float = LINEAR_MAP_RIDGE, weight: torch.Tensor | None = None) -> Method:
    """The best *linear* reconstruction through the model's optics: one ``window``×``window`` filter
    per CFA phase and band (:func:`hsicam.models.demosaic.phase_linear`), fitted by least squares on
    ``train_scenes`` (items (C, H, W), at least the camera's kernel) imaged noise-free through the
    camera (:func:`hsicam.engine.linear_step.fit_linear_map`, under the flat-field constraint: a
    uniform scene gives a uniform estimate; the window grows to the CFA period when that is wider).
    It undoes the optics' blur and the mosaic together as far as a linear map can, with what the
    training scenes teach about spectra and texture: what the network adds is its score minus this
    one. Needs a camera with a per-band
    sensor code (the CFA). ``weight``: filters already fitted that way on the same scenes (a run's
    linear consistency step, ``model.linear_step``), used instead of fitting them again."""
    if weight is None:
        weight = fit_linear_map(model, train_scenes, linear_reference_window(model.camera, window), ridge)
    window = int(weight.shape[-1])

    def reconstruct(sensor: torch.Tensor) -> torch.Tensor:
        return phase_linear(sensor, weight.to(sensor.device))

    return Method(LINEAR_REFERENCE_NAME, model.camera, reconstruct, model.target,
                  {"window_px": window, "ridge": ridge, "flat_field": True})


def _evaluation_settings(model, cfg, run) -> None:
    """What the evaluation's config (the run's own plus ``--set``) decides for a loaded run: the
    consistency step after the network (``model.consistency``; iterations=0 scores the network
    alone; a linear step whose filters in ``run`` do not fit it, e.g. another ``window_px``, is one
    :class:`InputError` naming the command that refits them) and the capture noise
    (``camera.sensor.*``, the DOE camera's ``camera.doe.sigma_height_nm``)."""
    problem = linear_step_problem(resolve_run(run), cfg.model.consistency)
    if problem:
        raise InputError(problem)
    missing = model.missing_linear_step(cfg.model.consistency)
    if missing:
        raise InputError(missing)  # before any scene is read, not at the first reconstruction
    model.consistency = cfg.model.consistency
    _evaluation_capture(model, cfg)


def _evaluation_capture(model, cfg) -> None:
    """How the evaluation config (the run's own plus ``--set``) captures scenes with a loaded run's
    camera: the scene boundary (``camera.boundary``, and the DOE camera's ``camera.padding``: a
    trained network reads any sensor image, so whole small scenes can be scored with ``same``) and
    the capture noise (``camera.sensor.*``, the DOE camera's ``camera.doe.sigma_height_nm``)."""
    model.camera.boundary = cfg.camera.boundary
    if hasattr(model.camera, "padding"):
        model.camera.padding = cfg.camera.padding
    model.camera.noise = SensorNoise.from_config(cfg.camera.sensor).to(next(model.parameters()).device)
    if "sigma_height_nm" in model.camera.noise_levels() and cfg.camera.kind == "doe":
        model.camera.set_noise(sigma_height_nm=cfg.camera.doe.sigma_height_nm)


def network_alone_reference(model) -> Method:
    """The system's network without its measurement-consistency step (``model.consistency``): what
    the step adds is the system's score minus this one."""
    alone = type(model)(model.camera, model.net)
    alone.autocast_dtype = model.autocast_dtype
    alone.eval()
    return Method("network alone (no consistency step)", model.camera, alone.reconstructor(), model.target, {})


def own_learned_method(run_cfg) -> str | None:
    """The registered method that scores a run of config ``run_cfg`` by its own network: ``doe-learned`` for a DOE
    camera, ``dd-cassi-{model.kind}`` / ``sd-cassi-{model.kind}`` for a learned CASSI one; None when none is
    registered (e.g. a CASSI run of the mosaic network, which the config refuses)."""
    kind = run_cfg.camera.kind
    own = "doe-learned" if kind == "doe" else f"{kind.replace('_', '-')}-{run_cfg.model.kind}"
    return own if own in METHODS else None


def _check_doe_run(name: str, run) -> None:
    """InputError when ``run`` was not trained with a DOE camera (a learned CASSI run), before its
    weights load: method ``name`` (doe-learned, a DOE demosaic reference) needs the DOE camera's
    optics and colour filter array; the refusal names the run's own method."""
    cfg_path = resolve_run(run) / "config.yaml"
    if not cfg_path.is_file():
        return  # load_run says what the folder lacks
    run_cfg = load_config(cfg_path)
    if run_cfg.camera.kind == "doe":
        return
    own = own_learned_method(run_cfg)
    use = f"--method {own}" if own is not None else "the learned method of its camera"
    raise InputError(f"{run}: method {name} evaluates a DOE camera; this run was trained with "
                     f"camera.kind={run_cfg.camera.kind} (model.kind={run_cfg.model.kind}): use {use}")


@register_method("doe-learned")
def _doe_method(cfg, run, device) -> Method:
    if run is None:
        raise InputError("method doe-learned needs --run RUN (a trained camera)")
    _check_doe_run("doe-learned", run)
    _, model = load_run(run, device)
    _evaluation_settings(model, cfg, run)
    return learned_method("doe-learned", model, run)


def network_skip(net):
    """The mosaic network whose demosaic skip starts ``net`` (``net`` itself, or the front end of an
    unrolled network with ``init: mosaic``), or None."""
    for candidate in (net, getattr(net, "front", None)):
        if candidate is not None and hasattr(candidate, "demosaic_kernel"):
            return candidate
    return None


def _demosaic_method(name: str, kernel: str, cfg, run, device) -> Method:
    """A network-free demosaic reference through a trained run's optics, scored on the same
    captures as the learned method (the evaluation config's boundary and noise)."""
    if run is None:
        raise InputError(f"method {name} needs --run RUN (the camera whose optics it images through)")
    _check_doe_run(name, run)
    _, model = load_run(run, device)
    _evaluation_capture(model, cfg)
    window = None
    skip = network_skip(model.net)
    if kernel == "tent" and skip is not None and skip.demosaic_kernel == "tent":
        window = skip.demosaic_window  # the network's own start
    return dataclasses.replace(demosaic_reference(model, kernel, window), info={"run": str(run)})


@register_method("doe-box-demosaic")
def _box_method(cfg, run, device) -> Method:
    """The network-free reference: the per-band box demosaic through a trained run's optics."""
    return _demosaic_method("doe-box-demosaic", "box", cfg, run, device)


@register_method("doe-linear-demosaic")
def _linear_method(cfg, run, device) -> Method:
    """The least-squares linear reconstruction through a trained run's optics, fitted on the
    training split of the evaluation config's data (:func:`linear_demosaic_reference`) through the
    run's own capture (its ``camera.boundary``, ``padding`` and noise-free optics, whatever the evaluation's).

    The fit is the method's ``prepare`` (also run by its first reconstruction): the training split
    (generated when synthetic, 2.5 GB for the standard camera) is made and imaged only once the scenes
    to score have passed evaluate's checks (:func:`hsicam.engine.evaluate.check_scenes`), so scenes too
    small to score are refused at once, and its time is not the first scene's reconstruction time;
    ``info["training_scenes"]`` is filled by the fit."""
    if run is None:
        raise InputError("method doe-linear-demosaic needs --run RUN (the camera whose optics it images through)")
    _check_doe_run("doe-linear-demosaic", run)
    _, model = load_run(run, device)
    cam = model.camera

    @functools.cache  # once: by prepare, or by the first reconstruction
    def fit() -> Method:
        bands = cfg.bands.to_bands()
        train, _ = split_dataset(cfg.data, bands)  # never empty: the split keeps at least one training scene
        _, own = load_run(run, device)  # the run's own capture, whatever the evaluation's
        weight = fit_linear_map(own, scene_dataset(cfg.data, train, bands), linear_reference_window(cam),
                                LINEAR_MAP_RIDGE)
        method.info["training_scenes"] = len(train)
        return linear_demosaic_reference(model, None, weight=weight)

    def reconstruct(sensor: torch.Tensor) -> torch.Tensor:
        return fit().reconstruct(sensor)

    _evaluation_capture(model, cfg)
    method = Method(LINEAR_REFERENCE_NAME, cam, reconstruct, model.target,
                    {"window_px": linear_reference_window(cam), "ridge": LINEAR_MAP_RIDGE, "flat_field": True,
                     "run": str(run)}, prepare=fit)
    return method


@register_method("doe-tent-demosaic")
def _tent_method(cfg, run, device) -> Method:
    """The weighted-bilinear (tent) demosaic through a trained run's optics: a tent-skip mosaic
    network's own start (its window), else the CFA's default tent."""
    return _demosaic_method("doe-tent-demosaic", "tent", cfg, run, device)


def dd_cassi_camera(cfg, device: torch.device | str = "cpu") -> DDCASSICamera:
    """The DD-CASSI camera of a config's bands, ``camera.cassi`` and ``camera.sensor``. The config's
    network settings are not this camera's: a DOE preset's linear consistency step (which the DD-CASSI
    camera cannot take, a config error) is switched off for it, so `--config quick` works."""
    model = dataclasses.replace(cfg.model, consistency=dataclasses.replace(cfg.model.consistency, iterations=0))
    cassi_cfg = dataclasses.replace(cfg, camera=dataclasses.replace(cfg.camera, kind="dd_cassi"), model=model)
    return DDCASSICamera.from_config(cassi_cfg).to(device)


def _identity(scene: torch.Tensor) -> torch.Tensor:
    return scene


def compared_border_px(cfg) -> int:
    """The border a CASSI method built from the evaluation config ``cfg`` leaves out of its score: when
    ``cfg``'s camera is a DOE camera in ``valid`` mode (``--config quick``, the comparison of Table 1), that
    camera's kernel margin // 2 px a side, so the CASSI rows are scored on the same pixels as the DOE camera's
    (its sensor area; they reconstruct the whole scene, whose border a DOE camera's sensor does not see); 0
    for a CASSI config or a ``same`` DOE config (the DOE camera then scores the whole scene too)."""
    if cfg.camera.kind != "doe" or cfg.camera.boundary != "valid":
        return 0
    from hsicam.cameras import build_camera

    return sensor_border_px(build_camera(cfg))


def sensor_border_px(camera) -> int:
    """The px a side by which ``camera``'s scored area falls short of the scene: margin // 2 in ``valid``
    mode (the centre crop of :meth:`hsicam.models.CameraSystem.target`), 0 in ``same`` mode."""
    return camera.margin // 2 if camera.boundary == "valid" else 0


def _cassi_method(name: str, cfg, cam, rec, info: dict) -> Method:
    """A DD-CASSI method of the evaluation config ``cfg``, scored on the area :func:`compared_border_px` says."""
    border = compared_border_px(cfg)
    return Method(name, cam, rec, _identity, {**info, **({"scored_border_px": border} if border else {})},
                  border_px=border)


def _camera_info(cam) -> dict:
    return {"camera": cam.kind, "convention": cam.convention, "shifts_px": list(cam.shifts),
            "aperture": cam.aperture.source or f"random seed {cam.aperture.seed}, density {cam.aperture.density}"}


@register_method("dd-cassi-gaptv")
def _gaptv_method(cfg, run, device) -> Method:
    s = cfg.baselines.gaptv
    cam = dd_cassi_camera(cfg, device)
    rec = functools.partial(gap_tv, cam, iterations=s.iterations, tv_weight=s.tv_weight,
                            tv_iterations=s.tv_iterations, accelerate=s.accelerate)
    return _cassi_method("dd-cassi-gaptv", cfg, cam, rec, {"solver": "gap-tv", **dataclasses.asdict(s), **_camera_info(cam)})


@register_method("dd-cassi-desci")
def _desci_method(cfg, run, device) -> Method:
    s = cfg.baselines.desci
    cam = dd_cassi_camera(cfg, device)
    # The GAP-TV start uses the GAP-TV baseline's weight (as Choi's does) unless baselines.desci sets its own.
    overrides = {"init_tv_weight": cfg.baselines.gaptv.tv_weight, **s.overrides()}
    ds = desci_settings(s.preset, **overrides)
    rec = functools.partial(desci, cam, settings=ds)
    return _cassi_method("dd-cassi-desci", cfg, cam, rec,
                         {"solver": "desci", "preset": s.preset, **dataclasses.asdict(ds), **_camera_info(cam)})


def _check_prior_keys(asked, trained, run, explicit: tuple[str, ...] = ()) -> None:
    """InputError when the evaluation's ``baselines.choi`` sets a key of the prior's architecture or
    training to a value the prior in ``run`` was not trained with (it was accepted, hashed and
    ignored). A key at its default is taken as not set (a config without the prior's section fills
    the others with defaults), unless it is in ``explicit`` (given by ``--set``:
    :func:`check_prior_overrides`)."""
    from hsicam.config import ChoiConfig
    from hsicam.engine.prior import PRIOR_TRAINING_KEYS

    default = ChoiConfig()
    differ = [f"baselines.choi.{k}={getattr(asked, k)!r} (the prior's: {getattr(trained, k)!r})"
              for k in PRIOR_TRAINING_KEYS if getattr(asked, k) != getattr(trained, k)
              and (k in explicit or getattr(asked, k) != getattr(default, k))]
    if differ:
        raise InputError(f"{run}: {', '.join(differ)}: the prior's architecture and training are fixed by `hsicam "
                         "baseline train-prior`; an evaluation sets only the ADMM keys (train another prior for these)")


def check_prior_overrides(run: str | Path, cfg, overrides) -> None:
    """:func:`_check_prior_keys` for ``hsicam evaluate --method dd-cassi-choi --run PRIOR``: the prior
    keys named in ``overrides`` (``baselines.choi.K=…``) are checked even when their value is the
    default."""
    from hsicam.engine.prior import PRIOR_TRAINING_KEYS, load_prior_settings

    named = override_keys(overrides)  # a section given as a mapping names its keys too
    explicit = tuple(k for k in PRIOR_TRAINING_KEYS if f"baselines.choi.{k}" in named)
    if explicit and cfg.baselines.choi is not None:
        _check_prior_keys(cfg.baselines.choi, load_prior_settings(run), run, explicit)


@register_method("dd-cassi-choi")
def _choi_method(cfg, run, device) -> Method:
    if run is None:
        raise InputError("method dd-cassi-choi needs --run PRIOR (a spectral prior from `hsicam baseline train-prior`)")
    cam = dd_cassi_camera(cfg, device)
    prior, trained = load_prior(run, cam.bands, device)
    admm = cfg.baselines.choi if cfg.baselines.choi is not None else trained
    _check_prior_keys(admm, trained, run)
    admm = dataclasses.replace(admm, features=trained.features, latent=trained.latent)
    init_tv = cfg.baselines.gaptv.tv_weight  # the start is the GAP-TV baseline's (its iterations: init_iterations)
    rec = functools.partial(admm_prior, cam, prior=prior, settings=admm, init_tv_weight=init_tv)
    return _cassi_method("dd-cassi-choi", cfg, cam, rec, {"solver": "choi-admm", "run": str(run), **dataclasses.asdict(admm),
                                                         "init_tv_weight": init_tv, **_camera_info(cam)})


def _learned_cassi(name: str, network: str, kind: str = "dd_cassi") -> Builder:
    """Builder of a learned CASSI method: a run trained with camera.kind=``kind`` and ``network``."""

    def build(cfg, run, device) -> Method:
        if run is None:
            raise InputError(f"method {name} needs --run RUN (trained with `hsicam train --set camera.kind={kind} "
                             f"--set model.kind={network}`)")
        cfg_path = resolve_run(run) / "config.yaml"
        if cfg_path.is_file():
            run_cfg = load_config(cfg_path)
            if run_cfg.camera.kind != kind:
                raise InputError(f"{run}: method {name} needs a run trained with camera.kind={kind}, "
                                 f"this one has camera.kind={run_cfg.camera.kind}")
            if run_cfg.model.kind != network:
                raise InputError(f"{run}: method {name} needs a run trained with model.kind={network}, "
                                 f"this one has model.kind={run_cfg.model.kind}")
        _, model = load_run(run, device)
        _evaluation_settings(model, cfg, run)
        return learned_method(name, model, run, **_camera_info(model.camera))

    return build


register_method("dd-cassi-rdn")(_learned_cassi("dd-cassi-rdn", "rdn"))
register_method("dd-cassi-unrolled")(_learned_cassi("dd-cassi-unrolled", "unrolled"))
# a trained SD-CASSI run scored by its own network (not a baseline of the comparison: baseline_names is DD-CASSI's)
register_method("sd-cassi-rdn")(_learned_cassi("sd-cassi-rdn", "rdn", "sd_cassi"))
register_method("sd-cassi-unrolled")(_learned_cassi("sd-cassi-unrolled", "unrolled", "sd_cassi"))
