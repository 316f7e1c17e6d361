"""Hypothesis settings shared by the property-based test files of several folders, and the mark that runs a
test on one torch thread (the ``one_torch_thread`` fixture of conftest.py).

- ``PIPELINE_PROPS`` / ``PIPELINE_FEW``: the least-squares linear map, the linear step and its file, the
  fabrication exports (engine/, models/, runs/, export/): 40 and 15 examples, function-scoped fixtures and slow
  inputs allowed.
- ``OUTPUT_PROPS``: the result and preview writers (report/, data/): 30 examples, the same health checks off.
- ``TRAINING_PROPS`` / ``TRAINING_FEW``: the training side's pure functions and the data it reads (loss terms,
  schedule, patch sampler, relighting, generator, memory arithmetic: engine/, data/): 30 and 10 examples,
  function-scoped fixtures and slow inputs allowed.
- ``CORE_PROP`` / ``CORE_FEW``: the core pure functions (bands, sensor, colour, metrics, demosaic, TV, cubes:
  optics/, models/, report/, data/): 30 and 15 examples, every health check on; with ``seeds`` and
  ``random_grid`` (a random increasing wavelength grid).

Moved here from engine/test_properties_pipeline.py, engine/test_properties_training.py,
optics/test_properties_spectral_sensor_metrics.py and report/test_properties_report.py when their tests went to the floors of the code they test, so that each file
imports them without importing another test file."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

one_torch_thread = pytest.mark.usefixtures("one_torch_thread")

PIPELINE_PROPS = settings(max_examples=40, deadline=None, derandomize=True, database=None,
                          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
PIPELINE_FEW = settings(PIPELINE_PROPS, max_examples=15)

OUTPUT_PROPS = settings(derandomize=True, database=None, deadline=None, max_examples=30,
                        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

TRAINING_PROPS = settings(max_examples=30, deadline=None, derandomize=True, database=None,
                          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
TRAINING_FEW = settings(TRAINING_PROPS, max_examples=10)

CORE_PROP = settings(max_examples=30, deadline=None, derandomize=True, database=None)
CORE_FEW = settings(max_examples=15, deadline=None, derandomize=True, database=None)

seeds = st.integers(0, 2**31 - 1)


def random_grid(seed: int, n: int, start: float, mean_step: float) -> np.ndarray:
    """n strictly ascending centres from ``start`` with steps in [0.2, 1.8] × ``mean_step`` (non-uniform)."""
    rng = np.random.default_rng(seed)
    return start + np.concatenate([[0.0], np.cumsum(mean_step * rng.uniform(0.2, 1.8, n - 1))])
