"""The orientation of a capture against the sensor's readout (``reconstruct --orientation``).

A capture stored mirrored or rotated (a sensor whose readout is flipped, a camera program that mirrors the live
view, a TIFF saved rotated) puts every pixel under another colour filter than the one the camera model gives it: the
CFA phases cannot fix it, the tile is another one. The 8 transforms of the square (the dihedral group) name how the
capture as stored relates to the sensor's readout, row 0 at the top, column 0 at the left:

=================  ===================================================================
``as-read``        the readout itself
``flip-lr``        mirrored left-right: stored[r, c] = readout[r, W-1-c]
``flip-ud``        mirrored top-bottom: stored[r, c] = readout[H-1-r, c]
``rot90``          turned 90° counter-clockwise (``np.rot90(readout)``)
``rot180``         turned 180°
``rot270``         turned 90° clockwise (``np.rot90(readout, 3)``)
``transpose``      mirrored about the main diagonal: stored[r, c] = readout[c, r]
``antitranspose``  mirrored about the other diagonal: stored[r, c] = readout[H-1-c, W-1-r]
=================  ===================================================================

:func:`to_sensor` undoes the transform (the reconstruction runs on the sensor's readout), :func:`to_capture` applies
it (the cube is given back in the capture's frame, pixel for pixel over the file as stored).
:func:`estimate_orientation` scores the 8 orientations (× the CFA phases) as :mod:`hsicam.engine.cfa_offset` scores
phases.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np

from hsicam.errors import InputError

if TYPE_CHECKING:  # (not imported at run time: the command line's parser names ORIENTATIONS without torch)
    import torch

#: The orientations a capture may be stored in, relative to the sensor's readout (module docstring).
ORIENTATIONS = ("as-read", "flip-lr", "flip-ud", "rot90", "rot180", "rot270", "transpose", "antitranspose")
#: The check (no ``--orientation``) warns when another orientation at phase (0, 0) explains the capture at least this
#: many times better than the capture as read at its best phase; :attr:`OrientationEstimate.close_runner_up` below it.
#: Measured (session 75; docs/hardware.md, "Orientation"): the quick demo camera's 16 validation and held-out scenes
#: (256², σ = 0.02): no aligned capture warned about at 1.2, 1.5 or 2×; misoriented ones 30, 12 and 0 of 105 (noise-free,
#: 2 scenes: 6 of 14 at each); `pretrained:standard` on a procedural capture: 5 of 7 at 1.5×, the aligned one quiet.
MIN_ORIENTATION_RATIO = 1.5


def known_orientation(name: str) -> str:
    """``name`` when it is one of :data:`ORIENTATIONS`, else one InputError naming them."""
    if name not in ORIENTATIONS:
        raise InputError(f"unknown orientation {name!r}: use one of {', '.join(ORIENTATIONS)}")
    return name


def _flip(a, axis: int):
    return np.flip(a, axis) if isinstance(a, np.ndarray) else a.flip(axis)  # (else a torch tensor)


def _rot90(a, k: int):
    return np.rot90(a, k, axes=(-2, -1)) if isinstance(a, np.ndarray) else a.rot90(k, (-2, -1))


def _transpose(a):
    return np.swapaxes(a, -2, -1) if isinstance(a, np.ndarray) else a.transpose(-2, -1)


#: stored = _TO_CAPTURE[name](readout), on the last two axes.
_TO_CAPTURE = {"as-read": lambda a: a, "flip-lr": lambda a: _flip(a, -1), "flip-ud": lambda a: _flip(a, -2),
               "rot90": lambda a: _rot90(a, 1), "rot180": lambda a: _rot90(a, 2), "rot270": lambda a: _rot90(a, 3),
               "transpose": _transpose, "antitranspose": lambda a: _rot90(_transpose(a), 2)}


def to_capture(image, name: str):
    """The sensor-frame ``image`` (a tensor or an array, the last two axes rows and columns) as the capture stored in
    orientation ``name`` holds it (a view for an array, a tensor as torch gives it)."""
    return _TO_CAPTURE[known_orientation(name)](image)


def to_sensor(image, name: str):
    """The capture ``image`` stored in orientation ``name`` brought back to the sensor's readout (the inverse of
    :func:`to_capture`: rot90 and rot270 undo each other, the others undo themselves)."""
    return to_capture(image, {"rot90": "rot270", "rot270": "rot90"}.get(known_orientation(name), name))


@dataclasses.dataclass(frozen=True)
class OrientationEstimate:
    """What :func:`estimate_orientation` found. ``orientation``: the one whose best CFA phase explains the capture best
    (smallest relative residual); ``estimates``: each orientation's
    :class:`~hsicam.engine.cfa_offset.CfaOffsetEstimate` of the capture brought back by :func:`to_sensor` (its phases,
    scored as ``--cfa-offset auto`` scores them)."""

    orientation: str
    estimates: dict

    @property
    def residuals(self) -> dict[str, float]:
        """Each orientation's best residual over the phases scored."""
        return {name: min(est.residuals.values()) for name, est in self.estimates.items()}

    @property
    def runner_up(self) -> tuple[str, float]:
        """The second-best orientation and its residual."""
        r = self.residuals
        name = sorted(r, key=r.get)[1]
        return name, r[name]

    @property
    def close_runner_up(self) -> bool:
        """True when another orientation explains the capture within :data:`MIN_ORIENTATION_RATIO` of the chosen one:
        the choice is not clear (measured: wrong orientations often come that close; module constants)."""
        return self.runner_up[1] < MIN_ORIENTATION_RATIO * self.residuals[self.orientation]

    def as_dict(self) -> dict:
        est = self.estimates[self.orientation]
        return {"orientation": self.orientation, "residuals": self.residuals,
                "phases": {name: list(e.offset) for name, e in self.estimates.items()},
                "close_runner_up": self.close_runner_up, "window": list(est.window), "margin_px": est.margin_px}


def estimate_orientation(system, sensor: torch.Tensor, window_px: int | None = None, phases=None,
                         progress: bool | None = False) -> OrientationEstimate:
    """The orientation of the capture ``sensor`` (1, 1, H, W) for the trained camera ``system`` (one with a CFA):
    each of the 8 :data:`ORIENTATIONS` is undone (:func:`to_sensor`) and scored by
    :func:`~hsicam.engine.cfa_offset.estimate_cfa_offset` (its ``phases``: default all m², 8 × m² network passes on
    the central ``window_px`` window, default :data:`~hsicam.engine.cfa_offset.DEFAULT_WINDOW_PX`); the orientation
    with the smallest residual at its best phase wins. ``progress``: count the orientations. InputError as
    ``estimate_cfa_offset`` (no CFA, a capture too small, black or narrow-band)."""
    from hsicam.engine.cfa_offset import DEFAULT_WINDOW_PX, estimate_cfa_offset, scoring_operators
    from hsicam.progress import Progress

    window_px = DEFAULT_WINDOW_PX if window_px is None else window_px
    estimates, operators = {}, scoring_operators(system)
    with Progress(len(ORIENTATIONS), "orientation", "orientation", show=progress) as bar:
        for name in ORIENTATIONS:
            estimates[name] = estimate_cfa_offset(system, to_sensor(sensor, name).contiguous(), window_px,
                                                  phases=phases, operators=operators)
            bar.update(1)
    best = min(estimates, key=lambda n: min(estimates[n].residuals.values()))
    return OrientationEstimate(best, estimates)


def check_orientation_at_origin(system, sensor: torch.Tensor, as_read, window_px: int) -> dict | None:
    """The cheap orientation check of a capture reconstructed without ``--orientation``, after the CFA check
    ``as_read`` (its :class:`~hsicam.engine.cfa_offset.CfaOffsetEstimate`): when its best phase is not (0, 0) (where
    a capture that is not a crop, read in its right orientation, is best: 1 of 16 aligned captures of the demo
    camera's scenes was not, noise-free, 5 of 16 at σ = 0.02; 13 of 14 and 94 of 105 misoriented ones), the 7 other
    orientations are scored at phase (0, 0) (7 network passes on the same window; none otherwise). Returns
    ``{"orientation": NAME, "residual": r, "as_read_best": r0, "residuals": {...}}`` with NAME the other orientation
    explaining the capture best, or None when nothing was scored. The caller warns when
    ``residual * MIN_ORIENTATION_RATIO <= as_read_best``."""
    from hsicam.engine.cfa_offset import estimate_cfa_offset, scoring_operators

    if tuple(as_read.offset) == (0, 0):
        return None
    scores, operators = {}, scoring_operators(system)
    for name in ORIENTATIONS[1:]:
        est = estimate_cfa_offset(system, to_sensor(sensor, name).contiguous(), window_px,
                                  min_scored_px=min(as_read.scored_px), phases=[(0, 0)], operators=operators)
        scores[name] = est.residuals["0,0"]
    best = min(scores, key=scores.get)
    return {"orientation": best, "residual": scores[best], "as_read_best": min(as_read.residuals.values()),
            "residuals": scores}
