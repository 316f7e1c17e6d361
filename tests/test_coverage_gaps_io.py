"""Lines of io / data formats / images / colour that the default suite never ran: user-facing errors and
edge cases, each checked against the text a user sees or an independent reference."""
from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from hsicam.errors import InputError


def _sensor_png(folder, value):
    folder.mkdir()
    img = (np.random.default_rng(0).random((16, 16)) * 60000).astype(np.uint16)
    Image.fromarray(img).save(folder / "sensor.png")
    (folder / "simulate.json").write_text(json.dumps({"sensor_png_scale": value}))
    return folder / "sensor.png"


@pytest.mark.parametrize("value", [0, -1, "nan", "inf"])
def test_simulate_json_with_a_non_positive_scale_is_named_not_blamed_on_scale(tmp_path, value):
    """A simulate.json whose sensor_png_scale is 0, negative, NaN or Inf: the error names that file, not
    `--scale`, which the user never passed (it read "scale (--scale) must be positive, got 0.0")."""
    from hsicam.data.images import read_capture

    png = _sensor_png(tmp_path / "sim", value)
    with pytest.raises(InputError) as exc:
        read_capture(png)
    msg = str(exc.value)
    assert msg.startswith(f"{tmp_path / 'sim' / 'simulate.json'}: its sensor_png_scale is ")
    assert msg.endswith("not a positive scale") and "--scale" not in msg
