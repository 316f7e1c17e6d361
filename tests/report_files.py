"""The result files `hsicam report` reads, as the commands write them (a results.json of `hsicam evaluate`, an
experiment.json of `hsicam experiment noise`), and a finished folder holding one: used by
report/test_report_fields.py (which damages their fields) and report/test_report_rare_paths.py."""

from __future__ import annotations

import json
from pathlib import Path

from hsicam.io import mark_complete

MEAN = {"psnr": 30.0, "ssim": 0.9, "sam": 5.0}
CONVENTIONS = {"psnr": "per band, peak 1"}


def evaluation(**changes) -> dict:
    """A results.json of the shape `hsicam evaluate` writes, with ``changes``."""
    data = {"method": "doe-learned", "scenes": [{"name": "a", **MEAN}], "mean": MEAN, "conventions": CONVENTIONS,
            "bands_nm": [500.0, 550.0, 600.0]}
    return {**data, **changes}


def experiment(*, drop: str | None = None, **changes) -> dict:
    """An experiment.json of the shape `hsicam experiment noise` writes, with ``changes`` and without ``drop``."""
    point = {"sigma_height_nm": 0.0, "sensor_sigma": 0.0, "psnr": 30.0, "ssim": 0.9}
    data = {"experiment": "noise", "scale": "tiny", "seeds": [0], "scenes": ["a"],
            "rows": [{"method": "doe-learned", **MEAN}], "conventions": CONVENTIONS,
            "noise_grid": {"sigma_height_nm": [0.0], "sensor_sigma": [0.0], "results": {"doe-learned": [point]}}}
    data = {**data, **changes}
    data.pop(drop, None)
    return data


def folder_with(tmp_path: Path, name: str, data: dict) -> Path:
    """``tmp_path/ev`` holding ``name`` (``data`` as JSON) and the completion marker its command writes last."""
    d = tmp_path / "ev"
    d.mkdir(parents=True)
    (d / name).write_text(json.dumps(data))
    mark_complete(d, {"command": "test"})
    return d
