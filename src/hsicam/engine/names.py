"""The names of the method and experiment registries, without torch: the command line checks
``evaluate --method``, ``experiment NAME`` and ``--scale`` and writes their help from here, so
``hsicam evaluate --help`` and a usage error do not wait for torch and the methods.

The home of :data:`METHOD_ALIASES`, :data:`EXPERIMENTS` and :data:`SCALES`
(:mod:`hsicam.engine.methods` and :mod:`hsicam.engine.experiments` import them from here). The
registered methods live in :mod:`hsicam.engine.methods`' registry (:func:`register_method`);
:data:`METHOD_NAMES` is a copy of its names for the command line, and tests/cli/test_cli_names.py
holds it equal to ``(*method_names(), *METHOD_ALIASES)``, order included: register a method, add
its name here.
"""

from __future__ import annotations

#: Old method names that still work → the registered name (results carry the registered one).
METHOD_ALIASES: dict[str, str] = {"doe-rdn": "doe-learned"}

#: The names ``evaluate --method`` takes: the registered methods in registration order (ours
#: first, then the baselines), then the old names of :data:`METHOD_ALIASES`.
METHOD_NAMES: tuple[str, ...] = (
    "doe-learned", "doe-box-demosaic", "doe-linear-demosaic", "doe-tent-demosaic",
    "dd-cassi-gaptv", "dd-cassi-desci", "dd-cassi-choi", "dd-cassi-rdn", "dd-cassi-unrolled",
    "sd-cassi-rdn", "sd-cassi-unrolled",
    *METHOD_ALIASES,
)

#: The paper's experiments (:func:`hsicam.engine.experiments.run_experiment`).
EXPERIMENTS: tuple[str, ...] = ("compare", "ablation", "noise", "cfa-period")

#: Their scales: the preset of that name plus each experiment's overrides.
SCALES: tuple[str, ...] = ("tiny", "quick", "paper")
