"""DeSCI: GAP with weighted nuclear norm minimisation (WNNM) of grouped patches (Liu et al., TPAMI 2019).

Each iteration is an (accelerated) GAP projection onto {x : Φx = y} followed by a WNNM denoiser
at a decreasing noise level σ; the start is a GAP-TV estimate, as in the published code.

The WNNM denoiser (Gu et al., CVPR 2014), vectorised in torch:

1. reference patches p×p×C every ``step`` pixels (plus the last row/column);
2. block matching: the ``group`` most similar patches (ℓ2 over the whole spectral patch) within
   ±``search`` pixels, from box-filtered squared differences, one shift at a time for all
   references at once; distances use the cube's leading spectral principal components
   (``match_components``), which keeps ≥99 % of the energy of natural spectra at a fraction of the
   cost;
3. each group is a (p²C) × K matrix Y; after removing its mean patch, the singular values s_i come
   from the K × K Gram matrix (batched ``eigh``) and are shrunk with WNNM's closed form
   s'_i = (s_i − ε + √((s_i + ε)² − 4w)) / 2 where the discriminant is positive, else 0;
4. denoised patches are put back with ``index_add`` and averaged where they overlap.

Deviations from the published implementation (liuyang12/DeSCI; stated so results can be read
correctly): the spectral patch p×p×C is grouped and matched as one vector, whereas the published CASSI
code (``test_desci_cassi.m`` → ``gapwnnm_int_fwise.m``) matches and denoises each band on its own, as
2-D patches; the WNNM constant w = c·σ²(√d + √K)²/4 (d = p²C) is scaled with the
group's dimensions so that pure-noise singular values (≈ σ(√d + √K)) are removed for any patch
size and band count (WNNM's 2c√K·σ² assumes d ≈ K); and block matching runs every
``match_every`` iterations rather than every iteration. The published CASSI settings are patch 6,
reference step 2, K = 70 patches per group, search ±30 px, one σ = 12/255 and 60 GAP-WNNM iterations
after 40 of GAP-TV; ``fast`` keeps the patch size but takes step 4, K = 24, ±10 px and 24 iterations
over a falling σ (minutes per scene on a CPU), ``full`` comes closer (:data:`DESCI_PRESETS`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F

from hsicam.config import GAPTVConfig
from hsicam.devices import float64_device
from hsicam.errors import InputError
from hsicam.solvers.common import checked_gram_diagonal
from hsicam.solvers.gaptv import SolverInfo, gap_tv

log = logging.getLogger(__name__)


@dataclass
class DeSCISettings:
    """Settings of :func:`desci` (see :data:`DESCI_PRESETS` for ``fast`` and ``full``)."""

    patch: int = 6  # patch side p (px)
    step: int = 4  # reference patch stride (px)
    search: int = 10  # block-matching window ±search (px)
    group: int = 24  # K: patches per group
    sigmas: list[float] = field(default_factory=lambda: [0.15, 0.1, 0.07, 0.05])  # σ schedule, [0, 1] scale
    iterations: list[int] = field(default_factory=lambda: [6, 6, 6, 6])  # GAP iterations per σ
    c: float = 1.0  # WNNM constant
    match_every: int = 3  # redo block matching every n iterations
    match_components: int | None = 6  # spectral PCA components for block matching (None: all bands)
    init_iterations: int = 60  # GAP-TV iterations of the start
    init_tv_weight: float = GAPTVConfig.tv_weight
    accelerate: bool = True
    chunk: int = 512  # groups processed at once (memory)


DESCI_PRESETS: dict[str, dict] = {
    # minutes per 256×256×31 scene on a 2-core CPU
    "fast": {},
    # closer to the published setting (denser references, larger groups and windows, a longer σ schedule):
    # about 15-20× the time of "fast"
    "full": {"step": 2, "search": 12, "group": 40, "sigmas": [0.2, 0.15, 0.12, 0.1, 0.08, 0.07, 0.06, 0.05],
             "iterations": [8, 8, 8, 8, 8, 8, 8, 8], "match_every": 2, "match_components": 10,
             "init_iterations": 80},
}


def desci_settings(preset: str = "fast", **overrides) -> DeSCISettings:
    """Settings of a preset with ``overrides`` (None values are ignored)."""
    if preset not in DESCI_PRESETS:
        raise InputError(f"unknown DeSCI preset {preset!r}; choose one of {', '.join(DESCI_PRESETS)}")
    values = {**DESCI_PRESETS[preset], **{k: v for k, v in overrides.items() if v is not None}}
    s = DeSCISettings(**values)
    if len(s.sigmas) != len(s.iterations):
        raise InputError(f"DeSCI: {len(s.sigmas)} sigmas but {len(s.iterations)} iteration counts")
    if min(s.patch, s.step, s.group, s.match_every, s.chunk) < 1 or s.search < 0:
        raise InputError("DeSCI: patch, step, group, match_every and chunk must be >= 1, search >= 0")
    if s.step > s.patch:  # reference patches every `step` px cover every pixel only when step <= patch
        raise InputError(f"DeSCI: step {s.step} is larger than patch {s.patch}: the pixels between reference patches "
                         "would get no estimate (0); use baselines.desci.step <= baselines.desci.patch")
    return s


# --------------------------------------------------------------------------------------------
# Block matching
# --------------------------------------------------------------------------------------------
def reference_positions(size: int, patch: int, step: int) -> torch.Tensor:
    """Top-left coordinates 0, step, ..., plus size − patch (so every pixel is covered)."""
    last = size - patch
    pos = list(range(0, last + 1, step))
    if pos[-1] != last:
        pos.append(last)
    return torch.tensor(pos, dtype=torch.int64)


def spectral_features(x: torch.Tensor, components: int | None) -> torch.Tensor:
    """(C, H, W) cube → (C', H, W) projection on its leading spectral principal components."""
    c = x.shape[0]
    if components is None or components >= c:
        return x
    flat = x.reshape(c, -1).to(float64_device(x.device), torch.float64)  # the CPU for MPS, which has no float64
    cov = flat @ flat.T / flat.shape[1]
    _, vecs = torch.linalg.eigh(cov)
    basis = vecs[:, -components:].T.to(x.device, x.dtype)  # (C', C), orthonormal rows
    return (basis @ x.reshape(c, -1)).reshape(components, *x.shape[1:])


def block_matching(feat: torch.Tensor, patch: int, rows: torch.Tensor, cols: torch.Tensor, search: int,
                   group: int) -> torch.Tensor:
    """Flat top-left indices (R, K) of the K most similar patches of each reference.

    Args:
        feat: (C', H, W) features.
        rows, cols: reference top-left coordinates (the references are their outer product).
        search: ±window (px); group: K, capped by the fewest in-image candidates of any reference
            (images a few px wider than the patch have fewer than K).
    Returns:
        (len(rows)·len(cols), K) indices i·W + j (i ≤ H − patch, j ≤ W − patch) into the
        patch-position grid of the image; the first one is the reference itself.
    """
    c, h, w = feat.shape
    hp, wp = h - patch + 1, w - patch + 1
    dev = feat.device
    rows, cols = rows.to(dev), cols.to(dev)
    offs = range(-search, search + 1)
    n_off = len(offs) ** 2
    pad = F.pad(feat[None], (search, search, search, search), mode="constant", value=0.0)[0]
    dists = torch.empty(len(offs), len(offs), len(rows), len(cols), dtype=feat.dtype, device=dev)
    inf = torch.tensor(float("inf"), dtype=feat.dtype, device=dev)
    for a, dy in enumerate(offs):
        # all horizontal shifts of this row shift at once: (n, C', H, W)
        shifted = torch.stack([pad[:, search + dy : search + dy + h, search + dx : search + dx + w] for dx in offs])
        e = (shifted - feat[None]).square().sum(1, keepdim=True)  # (n, 1, H, W)
        box = F.avg_pool2d(e, patch, stride=1) * (patch * patch)  # (n, 1, hp, wp)
        d = box[:, 0][:, rows][:, :, cols]  # (n, R_r, R_c)
        valid_r = ((rows + dy) >= 0) & ((rows + dy) < hp)
        valid_c = (cols[None, :] + torch.tensor(list(offs), device=dev)[:, None] >= 0) & \
                  (cols[None, :] + torch.tensor(list(offs), device=dev)[:, None] < wp)  # (n, R_c)
        ok = valid_r[None, :, None] & valid_c[:, None, :]
        dists[a] = torch.where(ok, d, inf)
    dists = dists.reshape(n_off, -1).T  # (R, n_off)
    # A reference has a candidate at offset (0, 0) but may have fewer than K in the image: an
    # out-of-image (infinite) candidate's index would point past the image or wrap into the next row.
    k = min(group, int(torch.isfinite(dists).sum(1).min()))
    # The reference first, also when other candidates tie with it at distance 0 (flat regions, where
    # topk's order among ties is arbitrary): a reference left out of its group leaves its pixels
    # covered by no patch (estimate 0).
    dists[:, search * len(offs) + search] = -1.0
    best = torch.topk(dists, k, dim=1, largest=False).indices  # (R, K), by distance
    dy = best // len(offs) - search
    dx = best % len(offs) - search
    ry = rows[:, None].expand(len(rows), len(cols)).reshape(-1, 1)
    rx = cols[None, :].expand(len(rows), len(cols)).reshape(-1, 1)
    return (ry + dy) * w + (rx + dx)


# --------------------------------------------------------------------------------------------
# WNNM
# --------------------------------------------------------------------------------------------
def wnnm_shrink(s: torch.Tensor, weight: torch.Tensor | float, eps: float = 1e-8) -> torch.Tensor:
    """WNNM closed form: s' = (s − ε + √((s + ε)² − 4w)) / 2 where (s + ε)² > 4w, else 0."""
    disc = (s + eps) ** 2 - 4 * weight
    return torch.where(disc > 0, (s - eps + torch.sqrt(disc.clamp_min(0))) / 2, torch.zeros_like(s)).clamp_min(0)


def wnnm_groups(groups: torch.Tensor, sigma: float, c: float = 1.0) -> torch.Tensor:
    """Low-rank estimate of each group (G, d, K): mean removed, singular values WNNM-shrunk."""
    g, d, k = groups.shape
    mean = groups.mean(dim=2, keepdim=True)
    y = groups - mean
    gram = (y.transpose(1, 2) @ y).to(float64_device(y.device), torch.float64)  # (G, K, K); the CPU for MPS
    evals, vecs = torch.linalg.eigh(gram)
    s = evals.clamp_min(0).sqrt()
    weight = c * sigma**2 * (math.sqrt(d) + math.sqrt(k)) ** 2 / 4
    shrunk = wnnm_shrink(s, weight)
    ratio = torch.where(s > 1e-12, shrunk / s.clamp_min(1e-12), torch.zeros_like(s))
    proj = (vecs * ratio[:, None, :]) @ vecs.transpose(1, 2)  # V diag(s'/s) Vᵀ, (G, K, K)
    return y @ proj.to(groups.device, groups.dtype) + mean


def _patch_offsets(patch: int, w: int, device: torch.device) -> torch.Tensor:
    u = torch.arange(patch, device=device)
    return (u[:, None] * w + u[None, :]).reshape(-1)  # (p²,)


def wnnm_denoise(x: torch.Tensor, sigma: float, settings: DeSCISettings, matches: torch.Tensor | None = None
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """WNNM denoising of one cube (C, H, W) at noise level σ; returns (estimate, matches).

    ``matches`` (R, K) from a previous call are reused (no block matching) when given.
    """
    c, h, w = x.shape
    p = settings.patch
    if min(h, w) < p:
        raise InputError(f"DeSCI: the image ({h}×{w}) is smaller than the patch ({p} px)")
    rows = reference_positions(h, p, settings.step)
    cols = reference_positions(w, p, settings.step)
    if matches is None:
        feat = spectral_features(x, settings.match_components)
        matches = block_matching(feat, p, rows, cols, settings.search, settings.group)
    offs = _patch_offsets(p, w, x.device)
    flat = x.reshape(c, h * w)
    acc = torch.zeros_like(flat)
    cnt = torch.zeros(h * w, dtype=x.dtype, device=x.device)
    n_ref, k = matches.shape
    for a in range(0, n_ref, settings.chunk):
        m = matches[a : a + settings.chunk]  # (G, K)
        idx = (m[:, :, None] + offs[None, None, :]).reshape(-1)  # (G·K·p²,)
        g = m.shape[0]
        vals = flat[:, idx].reshape(c, g, k, p * p).permute(1, 0, 3, 2).reshape(g, c * p * p, k)
        est = wnnm_groups(vals, sigma, settings.c)
        est = est.reshape(g, c, p * p, k).permute(1, 0, 3, 2).reshape(c, -1)
        acc.index_add_(1, idx, est)
        cnt.index_add_(0, idx, torch.ones_like(idx, dtype=x.dtype))
    return (acc / cnt.clamp_min(1)).reshape(c, h, w), matches


# --------------------------------------------------------------------------------------------
# The solver
# --------------------------------------------------------------------------------------------
@torch.no_grad()
def desci(camera, y: torch.Tensor, settings: DeSCISettings | None = None, x0: torch.Tensor | None = None,
          return_info: bool = False):
    """DeSCI reconstruction of a measurement (B, 1, H, W') → cube (B, C, H, W) [, SolverInfo]."""
    phi = checked_gram_diagonal(camera, y, x0, "DeSCI")
    s = settings or DeSCISettings()
    t0 = time.perf_counter()
    info = SolverInfo()
    if x0 is None:
        x = gap_tv(camera, y, s.init_iterations, s.init_tv_weight, accelerate=s.accelerate)
    else:
        x = x0.clone()
    y_acc = y.clone()
    matches: list[torch.Tensor | None] = [None] * x.shape[0]
    it = 0
    for sigma, n in zip(s.sigmas, s.iterations):
        for _ in range(n):
            yb = camera.A(x)
            if s.accelerate:
                y_acc = y_acc + (y - yb)
                x = x + camera.A_adjoint((y_acc - yb) / phi)
            else:
                x = x + camera.A_adjoint((y - yb) / phi)
            redo = it % s.match_every == 0
            out = []
            for b in range(x.shape[0]):
                xb, mb = wnnm_denoise(x[b], sigma, s, None if redo else matches[b])
                matches[b] = mb
                out.append(xb)
            x = torch.stack(out)
            it += 1
            if return_info:
                info.residual.append(camera.relative_residual(x, y))
    info.iterations = it
    info.runtime_s = time.perf_counter() - t0
    info.extra = {"groups": int(matches[0].shape[0]) if matches and matches[0] is not None else 0}
    log.info("DeSCI: %d GAP-WNNM iterations in %.1f s", it, info.runtime_s)
    return (x, info) if return_info else x
