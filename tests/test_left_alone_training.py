"""Training-loop items earlier sessions left alone (session 60): the learning-rate schedule where the
warm-up ends, the spectral-angle term's gradient at a zero estimate, the patch stream's seed."""

from __future__ import annotations

import math

import pytest

from hsicam.config import TrainConfig
from hsicam.engine.loop import lr_factor


# ------------------------------------------------------------------------------------------------
# 1. warm-up then cosine: continuous where the warm-up ends
# ------------------------------------------------------------------------------------------------
def _warmup_cosine(s: int, w: int, total: int) -> float:
    """Linear warm-up (s + 1)/W, then a cosine over the remaining T − W steps (the usual "linear warm-up then
    cosine decay", e.g. transformers' get_cosine_schedule_with_warmup, with the warm-up reaching 1 at its last step)."""
    if s < w:
        return (s + 1) / w
    return 0.5 * (1 + math.cos(math.pi * min((s - w) / max(total - w, 1), 1.0)))


@pytest.mark.parametrize("w, total", [(0, 1), (0, 10), (1, 10), (4, 100), (20, 640), (50, 100), (9, 10), (99, 100)])
def test_cosine_after_warm_up_runs_over_the_remaining_steps_without_a_drop(w, total):
    t = TrainConfig(lr_schedule="cosine", warmup_steps=w)
    run = [lr_factor(t, s, total, 10) for s in range(total + 1)]
    for s, f in enumerate(run):
        assert f == pytest.approx(_warmup_cosine(s, w, total), rel=1e-12, abs=1e-15), f"step {s}"
    # continuity where the warm-up ends: its last step and the first cosine step both run at the full rate
    if w:
        assert run[w - 1] == pytest.approx(1.0, abs=1e-15)
    assert run[w] == pytest.approx(1.0, abs=1e-15)
    # the cosine reaches its floor 0 at T, and decays monotonically to it; the warm-up never overshoots 1
    assert run[total] == pytest.approx(0.0, abs=1e-12) or w >= total
    assert all(b <= a + 1e-15 for a, b in zip(run[w:], run[w + 1:]))
    assert all(0 < f <= 1 for f in run[:total])
    # a resumed run at step k gets the uninterrupted run's factor: the schedule is a function of the step
    assert [lr_factor(t, s, total, 10) for s in reversed(range(total + 1))] == run[::-1]
