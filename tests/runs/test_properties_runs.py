"""Property-based tests (hypothesis) of the linear consistency step's file (``linear_step.safetensors``): any band
count, CFA period and filter width, any dtype or memory layout written. The reference is the file read back in its
real format and the filters written. Moved from engine/test_properties_pipeline.py."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from hsicam.errors import InputError
from hsicam.runs.linear_step import linear_step_info, load_linear_step, save_linear_step, stale_reason
from property_settings import PIPELINE_PROPS, one_torch_thread

pytestmark = one_torch_thread


# ------------------------------------------------------------------------------------------------
# linear_step.safetensors: round trip
# ------------------------------------------------------------------------------------------------
@PIPELINE_PROPS
@given(m=st.integers(1, 4), c=st.integers(1, 9), k=st.sampled_from([1, 3, 7]),
       layout=st.sampled_from(["float64", "float32", "transposed", "channels_last"]),
       window=st.sampled_from([1, 3, 7, 9]), seed=st.integers(0, 99))
def test_linear_step_file_round_trip(tmp_path_factory, m, c, k, layout, window, seed):
    """Any dtype or memory layout in, the float32 filters out (bit for bit), the metadata back with the stored
    width; another band count, period or filter width is named."""
    d = tmp_path_factory.mktemp("ls")
    g = torch.Generator().manual_seed(seed)
    ref = torch.randn(m * m, c, k, k, generator=g, dtype=torch.float64) * 10.0 ** float(seed % 7 - 3)
    weight = {"float64": ref, "float32": ref.float(),
              "transposed": ref.transpose(-1, -2).contiguous().transpose(-1, -2),
              "channels_last": ref.contiguous(memory_format=torch.channels_last)}[layout]
    weights = d / "model.safetensors"
    weights.write_bytes(bytes([seed]))
    from hsicam.io import file_sha256

    info = {"window_px": k, "training_scenes": np.int64(seed), "ridge": np.float32(1e-6),
            "weights_sha256": file_sha256(weights)}
    save_linear_step(d / "ls.safetensors", weight, info)
    back = load_linear_step(d / "ls.safetensors", c, m)
    assert back.dtype == torch.float32 and torch.equal(back, ref.float())
    meta = linear_step_info(d / "ls.safetensors")
    assert meta["filter_px"] == k and meta["training_scenes"] == seed and meta["weights_sha256"] == file_sha256(weights)
    assert stale_reason(d / "ls.safetensors", weights, k) is None
    assert (stale_reason(d / "ls.safetensors", weights, window) is None) == (window == k)
    with pytest.raises(InputError, match=f"do not fit a camera of {c + 1} bands"):
        load_linear_step(d / "ls.safetensors", c + 1, m)
    weights.write_bytes(bytes([seed + 1]))
    assert "other weights" in stale_reason(d / "ls.safetensors", weights, k)
