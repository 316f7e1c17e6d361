"""The CFA phase of a capture whose place on the sensor is unknown (``reconstruct --cfa-offset auto``).

A crop or a region-of-interest readout starts at some sensor pixel (Y, X); each pixel's colour
filter follows from it, and only (Y mod m, X mod m) matters for a CFA of period m. When it was not
recorded, it can be read back from the capture itself: for each of the m² candidates the network
reconstructs a window of the capture as if it started there, the camera images that estimate
again, and the candidate whose estimate explains the capture best (smallest relative residual
‖A x̂ − y‖² / ‖y‖² away from the window's border) is taken. At a wrong phase the network sees
every pixel through another filter than its own: the spectra it infers are not natural ones, and
their image through the real filters misses the capture's mosaic pattern.

Measured on 8 held-out-sources scenes cropped at random phases (`pretrained:standard`, 4×4 CFA; and
the quick demo camera): 8 of 8 right on noise-free 128–256 px windows, 8 of 8 with Gaussian
sensor noise σ = 0.01 and 0.02 of full scale (the right phase's residual 1.03–10× below the next
candidate's, the small ratios on dark scenes where noise dominates both); 7 of 8 at σ = 0.05, the
wrong one flagged as ambiguous (:attr:`CfaOffsetEstimate.ambiguous`). A featureless capture (a
uniform grey) is explained about equally by every phase: flagged too.

Session 67, 16 scenes (8 held-out-sources, 8 of the training distribution), aligned and cropped at random
places: `pretrained:standard` on 128 px windows was right on 32 of 32 noise-free, and every wrong estimate under
noise (σ = 0.02 and 0.05: 8 of 32 each) was flagged ambiguous. The quick demo camera (`make demo`'s) confuses
some phases: wrong and not flagged on 4 of 32 noise-free captures at 128 and at 256 px (one held-out scene's
phase 2,1 explains it within 17 % of its own 0,0), 2 of 32 at σ = 0.02. Its `auto` can therefore be wrong
without a warning; a calibrated offset is the safe choice.
"""

from __future__ import annotations

import dataclasses
import logging
import time

import torch

from hsicam.errors import InputError

log = logging.getLogger(__name__)

#: Side (px) of the capture's central window that the candidates are scored on.
DEFAULT_WINDOW_PX = 256
#: Side (px) of the window of the check of a capture reconstructed without ``--cfa-offset`` (taken to start where
#: the sensor does): smaller than :data:`DEFAULT_WINDOW_PX` since every such reconstruction pays it (about 0.6 s on
#: this 2-core CPU for the shipped camera, against 1.7 s at 256 px).
CHECK_WINDOW_PX = 128
#: The most seconds the check (not ``auto``, which was asked for) may take, projected from its first candidate's
#: time × the m² candidates; beyond it the check is skipped, and said so. The shipped camera's takes about 0.6 s; a
#: `paper`-preset run's (81 phases of its RDN on a window widened to 222 px by its 141 px PSFs) took 165 s of a
#: 172 s reconstruction of a 256² capture here (session 69), for a check the user had not asked for.
CHECK_TIME_BUDGET_S = 15.0


class EstimateTooSlow(InputError):
    """:func:`estimate_cfa_offset` stopped after its first candidate: scoring them all would take longer than its
    ``time_budget_s`` (``projected_s``: the projection)."""

    def __init__(self, message: str, projected_s: float) -> None:
        super().__init__(message)
        self.projected_s = projected_s


@dataclasses.dataclass(frozen=True)
class CfaOffsetEstimate:
    """What :func:`estimate_cfa_offset` found.

    ``offset``: (Y, X), each in [0, period): the sensor row and column, modulo the CFA period, of the
    capture's first pixel (what ``reconstruct --cfa-offset Y,X`` takes). ``residuals``: the relative
    residual ‖A x̂ − y‖² / ‖y‖² of every candidate, keyed ``"Y,X"``. ``window``: (row, column,
    height, width) of the capture's window they were scored on; ``margin_px``: border left out
    of the score on each side (the camera's light from beyond the window)."""

    offset: tuple[int, int]
    residuals: dict[str, float]
    window: tuple[int, int, int, int]
    margin_px: int
    #: :func:`cfa_phase_ratio` of the scored pixels (at least :data:`NARROW_BAND_PHASE_RATIO`: a capture below it is
    #: refused before any phase is scored, :class:`NarrowBandCapture`).
    phase_ratio: float = 1.0

    @property
    def runner_up(self) -> tuple[str, float]:
        """The second-best candidate ``"Y,X"`` and its residual."""
        key = sorted(self.residuals, key=self.residuals.get)[1]
        return key, self.residuals[key]

    @property
    def contrast(self) -> float:
        """(median − best) / best of the residuals: how much worse a typical wrong phase explains the
        capture than the chosen one (0: no better than a typical candidate)."""
        r = sorted(self.residuals.values())
        return (r[len(r) // 2] - r[0]) / r[0] if r[0] > 0 else float("inf")

    @property
    def ambiguous(self) -> bool:
        """True when the candidates explain the capture about equally well: the median residual is
        within :data:`MIN_CONTRAST` of the best, or within :data:`MIN_RESIDUAL_GAP` of it (every
        phase explains a featureless capture, e.g. a uniform grey, to a fraction of a percent)."""
        r = sorted(self.residuals.values())
        return self.contrast < MIN_CONTRAST or r[len(r) // 2] - r[0] < MIN_RESIDUAL_GAP

    @property
    def close_runner_up(self) -> bool:
        """True when the second-best phase explains the capture within :data:`MIN_RUNNER_UP_RATIO` of the best:
        the choice may be wrong even when not :attr:`ambiguous` (two phases apart from the rest)."""
        r = sorted(self.residuals.values())
        return r[1] < MIN_RUNNER_UP_RATIO * r[0]

    @property
    def rules_out_origin(self) -> bool:
        """True when the capture is clearly not at the CFA phase (0, 0), the sensor's first pixel: another phase
        explains it best, by a residual at least :data:`MIN_ORIGIN_RATIO` times smaller than (0, 0)'s, and the
        estimate is neither :attr:`ambiguous` nor :attr:`small`. What ``reconstruct`` warns of when no
        ``--cfa-offset`` was given."""
        best = self.residuals[f"{self.offset[0]},{self.offset[1]}"]
        return (self.offset != (0, 0) and not self.ambiguous and not self.small
                and self.residuals["0,0"] >= MIN_ORIGIN_RATIO * best)

    @property
    def scored_px(self) -> tuple[int, int]:
        """(height, width) of the part of the window the residuals were scored on (the window less its margins)."""
        return self.window[2] - 2 * self.margin_px, self.window[3] - 2 * self.margin_px

    @property
    def small(self) -> bool:
        """True when the scored part is narrower than :data:`MIN_SCORED_PX` (a small capture): the phase may be
        wrong without being :attr:`ambiguous`."""
        return min(self.scored_px) < MIN_SCORED_PX

    def as_dict(self) -> dict:
        return {"offset": list(self.offset), "residuals": dict(self.residuals), "window": list(self.window),
                "margin_px": self.margin_px, "contrast": self.contrast, "ambiguous": self.ambiguous,
                "close_runner_up": self.close_runner_up, "small": self.small, "phase_ratio": self.phase_ratio}


#: :attr:`CfaOffsetEstimate.ambiguous` below this contrast. On the 8 held-out-sources scenes the right
#: phase's contrast was 0.19–4.9 under sensor noise σ = 0.02 of full scale; at σ = 0.05 it fell to
#: 0.03–1.2, and the one wrong estimate (scene_0005) had 0.03.
MIN_CONTRAST = 0.1
#: ... or below this gap between the median and the best relative residual (a uniform capture: ~5e-6).
MIN_RESIDUAL_GAP = 1e-4
#: :attr:`CfaOffsetEstimate.close_runner_up` below this ratio of the second-best residual to the best. Measured
#: (session 67, 256 px windows, the 16 scenes aligned and cropped of :data:`MIN_ORIGIN_RATIO`): every estimate that
#: was wrong and not ambiguous had its runner-up within 1.17× (8 of 128, noise-free and at σ = 0.02, both cameras;
#: 1.02-1.17×), while right ones had theirs at 1.56× or more noise-free through `pretrained:standard` and 1.16× or
#: more through the quick demo camera; at 1.2× 14 of the 100 right, unambiguous estimates are flagged too (12 of
#: them at σ = 0.02, 12 through the demo camera): a warning to check the spectra, not an error.
MIN_RUNNER_UP_RATIO = 1.2
#: :attr:`CfaOffsetEstimate.rules_out_origin` needs (0, 0)'s residual at least this many times the best one. Measured
#: (session 67) on 128 px windows of 16 scenes (8 held-out-sources, 8 training-distribution), aligned and cropped at
#: random places, sensor noise σ = 0, 0.02 and 0.05 of full scale (the scenes peak at about 0.25): `pretrained:standard`
#: never named another phase unambiguously for an aligned capture, but the quick demo camera did for 6 of 50 (one
#: scene's phase 2,1 explains it nearly as well as 0,0, noise-free too; also at 256 px), at (0, 0)'s residual up to
#: 1.42× the best. At 2× none of the 100 aligned captures is ruled out, and the crops are: noise-free 13 of 14
#: (standard) and 9 of 15 (demo camera); at σ = 0.02 5 of 16 and 1 of 16 (at 1.5×: 13/14, 13/15, 8/16, 4/16).
#: The same 96 estimates through the `standard` camera retrained in session 68: 1 of 50 aligned captures ruled out
#: (a dark scene lit by narrow-band LEDs and display primaries, noise-free: its phase 0,2 explains it 6.6× better
#: than 0,0, and `auto` picks 0,2 there without a close runner-up), crops noise-free 12 of 14, σ = 0.02 6 of 16,
#: σ = 0.05 1 of 16.
MIN_ORIGIN_RATIO = 2.0
#: :attr:`CfaOffsetEstimate.small` below this scored side (px). Noise-free crops of held-out-sources scenes
#: through `pretrained:standard` (session 59): every phase right when 66 px were scored (96 px windows), two of
#: four wrong when 34 px were (64 px windows), by a residual only 7 % above the winner's and a contrast of 1.9,
#: so not flagged as ambiguous.
MIN_SCORED_PX = 64
#: :class:`NarrowBandCapture` below this :func:`cfa_phase_ratio`. Measured (session 74, the quick demo camera, central
#: 128 px, Gaussian sensor noise σ = 0, 0.001, 0.005 and 0.02 of full scale, clipped at 0): monochromatic fields,
#: textured scenes under 20-40 nm LEDs and an RGB-LED white 0 at every σ (band-pass filters that pass none of the
#: light: their phases' medians are the clipped noise's, 0); the 16 validation and held-out-sources scenes 0.010 to
#: 0.42 up to σ = 0.005 (a diagonal grating the least), at σ = 0.02 two of them 0 (the darkest scene, under noise ten
#: times its light, and a dim held-out one: their phase cannot be read either); a flat grey 0.98.
NARROW_BAND_PHASE_RATIO = 1e-3


class NarrowBandCapture(InputError):
    """:func:`estimate_cfa_offset` refused a capture whose :func:`cfa_phase_ratio` (``phase_ratio``) is below
    :data:`NARROW_BAND_PHASE_RATIO`: some filters see (almost) none of its light. Such spectra (a monochromator, a
    laser, one LED) are far from any the network learned, which then explains the capture worse at its true phase
    than at others: every phase score is meaningless (session 74's hunt: 9 of 11 aligned monochromatic fields were
    "clearly" at another phase, and --cfa-offset auto read 660 nm light as 420 nm); so are those of a capture whose
    noise drowns its darker filters' light. Raised before any phase is scored."""

    def __init__(self, message: str, phase_ratio: float) -> None:
        super().__init__(message)
        self.phase_ratio = phase_ratio


def cfa_phase_ratio(window: torch.Tensor, period: int) -> float:
    """The darkest CFA phase's median relative to the brightest phase's, over the lit CFA cells of ``window`` (H, W):
    the period × period cells whose brightest pixel reaches a tenth of the 99th percentile of the cells' brightest
    (a spot on black is judged on the spot, not on the black, whose every phase's median is 0). Medians, not means: a
    phase that sees no light holds the sensor's noise, whose mean clipped at 0 is ~0.4 σ but whose median is 0 (with
    means, 0.1 % noise hid a 660 nm LED: session 74's review). In [0, 1]; 0 when no phase's median in the lit cells
    is above 0. Phase (i, j) is the pixels (i + k·period, j + l·period) of the window."""
    h, w = (window.shape[-2] // period) * period, (window.shape[-1] // period) * period
    cells = (window[:h, :w].double().reshape(h // period, period, w // period, period).permute(0, 2, 1, 3)
             .reshape(-1, period * period))  # (cells, phases)
    brightest = cells.amax(dim=1)
    lit = cells[brightest > max(0.1 * float(torch.quantile(brightest, 0.99)), 0.0)]
    if not len(lit):
        return 1.0  # (a black window: estimate_cfa_offset refuses it before)
    meds = lit.median(dim=0).values
    top = float(meds.max())
    return max(float(meds.min()), 0.0) / top + 0.0 if top > 0 else 0.0  # (+ 0.0: never -0.0 from a rounded capture)


@torch.no_grad()
def estimate_cfa_offset(system, sensor: torch.Tensor, window_px: int = DEFAULT_WINDOW_PX,
                        min_scored_px: int = 0, time_budget_s: float | None = None,
                        progress: bool | None = False, phases=None, operators=None) -> CfaOffsetEstimate:
    """The CFA phase (Y, X) of the capture ``sensor`` (1, 1, H, W), values in [0, 1], for the trained
    :class:`~hsicam.models.system.CameraSystem` ``system`` (a camera with a CFA of period m > 1).

    Scores the m² candidates on the central ``window_px`` × ``window_px`` window (the whole capture
    when smaller): the network alone reconstructs it at each candidate phase, and the camera that
    explains captures (``system.step_camera``, e.g. measured PSFs, else ``system.camera``; PSFs cut
    to ``model.consistency.psf_energy``) images it again; the window is widened (within the capture) so that at
    least ``min_scored_px`` a side are scored inside the PSF's reach. Costs m² network passes on the window
    (the 4×4 CFA: 16; about 2.5 s for 256 px on one CPU core, `pretrained:standard`; a `paper`-preset run's 9×9 CFA:
    81 passes of its RDN). ``time_budget_s``: :class:`EstimateTooSlow` after the first candidate when its time × m²
    exceeds it (None: no limit). ``progress``: count the candidates (:class:`hsicam.progress.Progress`). ``phases``:
    the (Y, X) candidates to score (default all m²; e.g. only (0, 0) where the phase is known: the orientation check,
    :mod:`hsicam.engine.orientation`). ``operators``: :func:`scoring_operators` of ``system`` when already built (a
    second of PSFs for the shipped camera: the orientations score the same camera 8 times). InputError when the camera has no CFA, or the capture is too small or black."""
    from hsicam.progress import Progress

    period = int(getattr(system.camera, "code_period", 1))
    if period <= 1:
        raise InputError("the camera has no colour filter array: there is no CFA offset to estimate")
    if sensor.dim() != 4 or tuple(sensor.shape[:2]) != (1, 1):
        raise InputError(f"sensor image must be (1, 1, H, W), got {tuple(sensor.shape)}")
    was_training = system.training
    system.eval()
    try:
        op, step = scoring_operators(system) if operators is None else operators
        margin = int(getattr(step, "kernel_px", 1)) // 2 + period
        h, w = sensor.shape[-2:]
        need = 2 * margin + 4 * period
        if min(h, w) < need:
            raise InputError(f"the capture is {h}×{w} px: estimating its CFA offset needs at least {need}×{need} px "
                             f"(the camera's PSF reach of {margin} px on each side, plus 4 CFA periods); give the "
                             "offset with --cfa-offset Y,X")
        side = max(window_px, need, 2 * margin + int(min_scored_px))
        wh, ww = min(h, side), min(w, side)
        wy, wx = (h - wh) // 2, (w - ww) // 2
        y = sensor[..., wy : wy + wh, wx : wx + ww].float()
        inner = (..., slice(margin, wh - margin), slice(margin, ww - margin))
        if not torch.isfinite(y).all():  # the command line refuses such captures first; the library says it too
            raise InputError("the capture holds NaN or infinite values where its CFA offset would be estimated (its "
                             "central window): replace them (e.g. hot or dead pixels) or give the offset with "
                             "--cfa-offset Y,X")
        norm = float(y[inner].square().sum())
        if not norm > 0:
            raise InputError("the capture is black where its CFA offset would be estimated (its central window): "
                             "give the offset with --cfa-offset Y,X")
        ratio = cfa_phase_ratio(y[inner][0, 0], period)
        if ratio < NARROW_BAND_PHASE_RATIO:
            raise NarrowBandCapture(
                f"its CFA phase cannot be read from it: its darkest CFA phase's median is {ratio:.2g} of the "
                f"brightest's (below {NARROW_BAND_PHASE_RATIO:g}: filters that see almost none of its light), a "
                "narrow-band capture (a monochromator, a laser, one LED: spectra the network never learned, which "
                "it explains badly at every phase) or one whose noise drowns its darker filters' light", ratio)
        residuals = {}
        start = time.perf_counter()
        todo = [(cy, cx) for cy in range(period) for cx in range(period)] if phases is None else \
            [(int(cy) % period, int(cx) % period) for cy, cx in phases]
        with Progress(len(todo), "CFA offset", "phase", show=progress) as bar:
            for cy, cx in todo:
                origin = (cy + wy, cx + wx)  # the window's first pixel on the sensor, for this candidate
                # (a capture's clipped pixels lie on the map at its real phase, which is what is sought here)
                x = system.network(y, origin, operator=op, read_clipped=False)
                residuals[f"{cy},{cx}"] = float((step.A(x, origin) - y)[inner].square().sum()) / norm
                bar.update(1)
                if time_budget_s is not None and len(residuals) == 1:
                    projected = (time.perf_counter() - start) * len(todo)
                    if projected > time_budget_s:
                        raise EstimateTooSlow(
                            f"scoring the {len(todo)} CFA phases would take about {projected:.0f} s "
                            f"({projected / len(todo):.1f} s each, on a {wh}×{ww} px window)", projected)
    finally:
        system.train(was_training)
    best = min(residuals, key=residuals.get)
    oy, ox = (int(v) for v in best.split(","))
    return CfaOffsetEstimate((oy, ox), residuals, (wy, wx, wh, ww), margin, phase_ratio=ratio)


#: Side (px) of the window :func:`phase_blind` reconstructs twice.
PHASE_BLIND_WINDOW_PX = 64


def phase_blind(system, shape: tuple[int, int] = (PHASE_BLIND_WINDOW_PX, PHASE_BLIND_WINDOW_PX),
                offset: tuple[int, int] = (1, 1)) -> bool:
    """Whether ``system``'s reconstruction takes no CFA phase: a random sensor image (seeded, uniform in [0, 1], of
    ``shape`` up to :data:`PHASE_BLIND_WINDOW_PX` a side) reconstructs bit for bit alike at ``offset`` and at (0, 0).
    A property of the run, not of a capture (a dark or flat window reconstructs alike at every phase whatever the
    network: session 75's review). So is a network that reads the sensor image alone (the paper's RDN,
    ``model.rdn.demosaic_input: false``) with no consistency steps: shift-equivariant, it reconstructs a crop as the
    whole capture away from the borders, and ``--cfa-offset`` changes nothing (session 75's hunt)."""
    h, w = (min(int(v), PHASE_BLIND_WINDOW_PX) for v in shape)
    y = torch.rand(1, 1, h, w, generator=torch.Generator().manual_seed(0))
    y = y.to(next((t.device for t in system.parameters()), torch.device("cpu")))
    was_training = system.training
    system.eval()
    try:
        with torch.no_grad():
            return bool(torch.equal(system.reconstruct(y, (0, 0)), system.reconstruct(y, tuple(offset))))
    except InputError:  # what stops it (a missing linear step) stops the reconstruction itself, which says it
        return False
    finally:
        system.train(was_training)


def scoring_operators(system) -> tuple:
    """(the network's operator, the camera that re-images its estimate) that :func:`estimate_cfa_offset` scores with:
    the nominal snapshots of ``system.camera`` and of ``system.step_camera`` (else the camera), PSFs cut to
    ``model.consistency.psf_energy``."""
    from hsicam.models.consistency import cut_psf

    explain = system.step_camera if system.step_camera is not None else system.camera
    return _nominal(system.camera), cut_psf(_nominal(explain), system.consistency.psf_energy)


def _nominal(camera):
    """The camera's nominal operator snapshot (the camera itself when it has none)."""
    snap = getattr(camera, "snapshot", None)
    return snap(nominal=True) if callable(snap) else camera
