"""argparse ``type`` functions of the command line's options (``--device``, ``--seed``, ``--lr``,
``--seeds``, comma-separated lists: :func:`list_arg`, :func:`id_list_arg`; ``--run`` is :func:`hsicam.cli.run_folder`): a
bad value is a usage error naming the option (exit code 2, one line), never a traceback later in the
work. :func:`path_arg`: the ``~`` of every path argument (the parser adds it to them,
:data:`hsicam.cli.PATH_METAVARS`)."""

from __future__ import annotations

import argparse
import functools
import math
import os
from collections.abc import Sequence
from typing import Any, Callable

from hsicam.config import (LEVELS_RULE, MAX_SENSOR_SIGMA, MAX_SIGMA_HEIGHT_NM, MAX_TV_WEIGHT, MIN_TV_WEIGHT, SEED_MAX,
                           SEED_MIN, TOLERANCE_DRAW_STRIDE, empty_item_problem, levels_problem, seed_problem)
from hsicam.errors import InputError

#: The smallest ``--tile`` (px) of ``reconstruct`` and ``evaluate``.
MIN_TILE_PX = 16


class RegistryChoices(Sequence):
    """The ``choices`` of an option whose names a registry holds (``evaluate --method``, ``experiment NAME``),
    asked of ``names()`` only when argparse needs them: to check a value or to write the command's help. So the
    parser is built without importing the registry (torch and the methods behind it): ``hsicam --help`` and
    a usage error come back at once. Give the option a ``metavar`` (argparse lists choices without one while
    building) and ``%(choices)s`` in its help."""

    def __init__(self, names: Callable[[], Sequence[str]]) -> None:
        self._names = names

    @functools.cached_property
    def _list(self) -> tuple[str, ...]:
        return tuple(self._names())

    def __getitem__(self, index):
        return self._list[index]

    def __len__(self) -> int:
        return len(self._list)

    def __contains__(self, value: object) -> bool:
        return value in self._list


def _shown(text: str) -> str:
    return repr(text if len(text) <= 40 else text[:40] + "…")


def seed_arg(low: int = SEED_MIN, high: int = SEED_MAX) -> Callable[[str], int]:
    """argparse ``type`` of a ``--seed``: an integer in [``low``, ``high``] (default: the seeds every config key
    takes, [0, 2^32 - 1], where distinct seeds give distinct draws), checked by the config's one seed check
    (:func:`hsicam.config.seed_problem`)."""

    def seed(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"must be an integer, got {_shown(text)}") from None
        problem = seed_problem(value, low, high)
        if problem is not None:
            raise argparse.ArgumentTypeError(problem)
        return value

    return seed


def device_arg(spec: str) -> str:
    """argparse ``type`` of every ``--device``: a torch device this machine has (``cpu``, ``cuda``,
    ``cuda:N``, ``mps``), else a usage error saying what is available, never a traceback later. ``cpu``, which every
    machine has, is taken without asking torch: argparse checks the string default of every ``--device`` while it
    parses, also for ``--help`` or a usage error, which should not wait for torch to load."""
    if spec == "cpu":
        return spec
    from hsicam.devices import device_problem

    problem = device_problem(spec)
    if problem is not None:
        raise argparse.ArgumentTypeError(f"device {spec!r}: {problem}")
    return spec


def positive_number_arg(text: str) -> float:
    """argparse ``type`` of an option that must be a finite number > 0 (``--lr``): ``inf``, ``nan``,
    0 and negative values are usage errors."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {_shown(text)}")
    return value


def tv_weight_arg(text: str) -> float:
    """argparse ``type`` of ``reconstruct --tv-weight``: a number in the config's range of a non-zero
    ``model.consistency.tv_weight``, [:data:`~hsicam.config.MIN_TV_WEIGHT`, :data:`~hsicam.config.MAX_TV_WEIGHT`]."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not MIN_TV_WEIGHT <= value <= MAX_TV_WEIGHT:
        raise argparse.ArgumentTypeError(f"must be a number in [{MIN_TV_WEIGHT:g}, {MAX_TV_WEIGHT:g}], got {_shown(text)}")
    return value


def non_negative_number_arg(text: str) -> float:
    """argparse ``type`` of an option that must be a finite number >= 0 (a noise level: ``evaluate
    --sensor-sigma``, ``--sigma-height-nm``): ``inf``, ``nan`` and negative values are usage errors,
    before any data is read."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {_shown(text)}")
    return value


def sensor_sigma_arg(text: str) -> float:
    """argparse ``type`` of a Gaussian sensor-noise σ on the image scaled to full scale 1 (``evaluate
    --sensor-sigma``): a finite number in [0, 1], the range of ``camera.sensor.sigma`` (above the full scale the
    noise buries any signal)."""
    value = non_negative_number_arg(text)
    if value > MAX_SENSOR_SIGMA:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_SENSOR_SIGMA:g} (σ as a fraction of full scale, as "
                                         f"camera.sensor.sigma), got {_shown(text)}")
    return value


def sigma_height_arg(text: str) -> float:
    """argparse ``type`` of a DOE height noise σ_p in nm (``evaluate --sigma-height-nm``): a finite number in
    [0, :data:`hsicam.config.MAX_SIGMA_HEIGHT_NM`], the range of ``camera.doe.sigma_height_nm``."""
    value = non_negative_number_arg(text)
    if value > MAX_SIGMA_HEIGHT_NM:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_SIGMA_HEIGHT_NM:.0f} nm (1 mm, far beyond any DOE's "
                                         f"relief, as camera.doe.sigma_height_nm), got {_shown(text)}")
    return value


def count_arg(text: str) -> int:
    """argparse ``type`` of an option that counts something and needs at least one (``--seeds``):
    an integer >= 1; 0, negative and non-integer values are usage errors."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {_shown(text)}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def bounded_count_arg(most: int, each: str) -> Callable[[str], int]:
    """argparse ``type`` of a count of whole runs (:func:`count_arg`, at most ``most``; ``each``: what one of them
    costs, for the message): a count beyond any budget was accepted and ran for ever, or beyond the machine's
    integers ended in an OverflowError traceback of ``range``."""

    def bounded(text: str) -> int:
        value = count_arg(text)
        if value > most:
            raise argparse.ArgumentTypeError(f"must be at most {most} ({each}), got {_shown(text)}")
        return value

    return bounded


#: The most seeds ``--seeds`` takes (``evaluate``, ``experiment``), and fabricated DOEs ``tolerance --draws`` takes
#: per height-noise level.
MAX_SEEDS = 1000
MAX_DRAWS = TOLERANCE_DRAW_STRIDE  # a draw's seed is --seed·stride + draw (hsicam.engine.tolerance)
#: ``--seeds`` (the noise seeds 0 … N-1): each one is a whole evaluation under fresh test noise (``hsicam experiment``
#: trains its runs once).
seeds_arg = bounded_count_arg(MAX_SEEDS, "each seed is a whole run")
#: ``tolerance --draws``: each draw is a whole evaluation of the scenes.
draws_arg = bounded_count_arg(MAX_DRAWS, "each draw is a whole evaluation")


def list_items(text: str) -> list[str]:
    """The items of a comma-separated list option, stripped: none for an empty or blank value (each option says
    whether it needs one), else every item, and an empty item ("1,,2", "1,2,", ",") is a usage error naming it:
    dropping it ran a study of one value fewer than the user typed, without a word."""
    if not text.strip():
        return []
    problem = empty_item_problem(text)
    if problem:
        raise argparse.ArgumentTypeError(problem)
    return [v.strip() for v in text.split(",")]


def list_arg(convert: type, what: str, ok: Callable[[Any], bool] = lambda v: True, need: str = ""
             ) -> Callable[[str], tuple]:
    """argparse ``type`` of a comma-separated list of ``convert`` values (``what``: "numbers",
    "integers"), each of which must pass ``ok`` (``need`` says how): a usage error naming the option,
    before the run is loaded."""

    def parse(text: str) -> tuple:
        try:
            values = tuple(convert(v) for v in list_items(text))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected comma-separated {what}, got {text!r}") from None
        bad = [v for v in values if not ok(v)]
        if bad:
            raise argparse.ArgumentTypeError(f"every value must be {need}, got {bad[0]:g}")
        return values

    return parse


#: A list of finite numbers (``tolerance --shift-cells``, ``--sensor-distance-um``).
finite_numbers_arg = list_arg(float, "numbers", math.isfinite, "finite")
#: A list of DOE height noise levels σ_p (nm), each in [0, MAX_SIGMA_HEIGHT_NM] (``tolerance --sigma-height-nm``).
sigma_heights_arg = list_arg(float, "numbers", lambda v: math.isfinite(v) and 0 <= v <= MAX_SIGMA_HEIGHT_NM,
                             f"a finite number in [0, {MAX_SIGMA_HEIGHT_NM:.0f}] nm")
#: A list of DOE height level counts, each one ``export-optics`` exports (:func:`hsicam.config.levels_problem`: a power
#: of 2 in 2..2^16) (``tolerance --levels``; :func:`hsicam.engine.tolerance.check_levels` refused any other only once
#: the run was loaded).
levels_list_arg = list_arg(int, "integers", lambda v: levels_problem(v) is None,
                           f"{LEVELS_RULE} (height levels that export-optics exports)")


def levels_arg(text: str) -> int:
    """argparse ``type`` of ``export-optics --levels``: a level count it exports (:func:`hsicam.config.levels_problem`,
    the rule of ``tolerance --levels``), else a usage error before any work."""
    try:
        value: object = int(text)
    except ValueError:
        value = text
    problem = levels_problem(value)
    if problem is not None:
        raise argparse.ArgumentTypeError(problem)
    return value


def check_tile(tile: int | None) -> None:
    """``--tile`` of ``reconstruct`` and ``evaluate``, before any work: None (reconstruct_tiled's default) or at
    least :data:`MIN_TILE_PX`."""
    if tile is not None and tile < MIN_TILE_PX:
        raise InputError(f"--tile must be at least {MIN_TILE_PX} px")


def text_arg(text: str) -> str:
    """argparse ``type`` of an option that takes a name or a line of text (``data synth --holdout-sources``,
    ``pretrained pack --summary``, ``--preset``): an empty or blank value (``--preset "$PRESET"`` with the
    variable unset) is a usage error; taken as given it was the option's default (the config's held-out sources
    replaced by none, the preset guessed from the config) or an empty summary on the camera's card."""
    if not text.strip():
        raise argparse.ArgumentTypeError("the value is empty (an unset variable?)")
    return text


def id_list_arg(text: str) -> str:
    """argparse ``type`` of a comma-separated list of names (``data synth --holdout-sources``): not empty
    (:func:`text_arg`), and no empty item (:func:`list_items`); the names are checked where they are used."""
    list_items(text_arg(text))
    return text


def path_arg(convert: Callable[[str], Any] | None = None) -> Callable[[str], Any]:
    """argparse ``type`` of a path argument: a leading ``~`` expanded as a shell does
    (``os.path.expanduser``, also when it reached hsicam quoted, from a script or a Makefile), then
    ``convert`` (e.g. :func:`hsicam.cli.run_folder`), whose name argparse's errors keep. An empty path
    (``--dark "$DARK"`` with the variable unset) is a usage error: taken as given it was no option at all
    (``--dark``, ``--flat``, ``--psf-dir``, ``evaluate --data``, ``experiment --out``: exit 0 without it) or
    the current folder (``data show --out``, ``finetune --psf-dir``)."""

    def path(text: str) -> Any:
        if text == "":
            raise argparse.ArgumentTypeError("the path is empty (an unset variable?)")
        text = os.path.expanduser(text)
        return text if convert is None else convert(text)

    return path if convert is None else functools.update_wrapper(path, convert)
