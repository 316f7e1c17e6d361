"""Found by following docs/data.md, hardware.md, optics.md, networks.md and architecture.md literally (walk2)."""
from __future__ import annotations

import logging


def test_cfa_offset_auto_says_the_part_it_scored_on_not_the_window(caplog, monkeypatch):
    """``reconstruct --cfa-offset auto`` on a 64 px capture of the tiny camera logged "scored on the central 64×64 px"
    and, for a small capture, warned in the next line that it "was scored on only 38×38 px": the residuals are scored on
    the window less the PSF's reach on each side (docs/hardware.md), so the first line must name that part too."""
    from hsicam.cli.reconstruct import estimated_cfa_offset
    from hsicam.engine import cfa_offset
    from hsicam.engine.cfa_offset import CfaOffsetEstimate

    window, margin = (0, 0, 96, 80), 13
    residuals = {f"{y},{x}": 0.003 for y in range(3) for x in range(3)}
    residuals.update({"1,2": 0.001, "0,0": 0.002})
    est = CfaOffsetEstimate((1, 2), residuals, window, margin)
    monkeypatch.setattr(cfa_offset, "estimate_cfa_offset", lambda model, sensor, **kw: est)
    with caplog.at_level(logging.INFO):
        assert estimated_cfa_offset(None, None)[0] == (1, 2)
    [line] = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    scored_h, scored_w = window[2] - 2 * margin, window[3] - 2 * margin  # 70 × 54
    assert line.endswith(f"scored on the central {scored_h}×{scored_w} px)"), line


def test_cfa_offset_auto_on_a_small_ambiguous_capture_warns_of_both(caplog, monkeypatch):
    """docs/hardware.md: a small capture "is warned about too"; an ambiguous one that was also small got only the
    ambiguity warning (``elif``). Both now, each naming its own reason."""
    from hsicam.cli.reconstruct import estimated_cfa_offset
    from hsicam.engine import cfa_offset
    from hsicam.engine.cfa_offset import MIN_SCORED_PX, CfaOffsetEstimate

    window, margin = (0, 0, 64, 64), 13  # scored on 38 × 38 px, under MIN_SCORED_PX
    residuals = {f"{y},{x}": 0.003 for y in range(3) for x in range(3)}  # every phase explains it as well: ambiguous
    est = CfaOffsetEstimate((0, 0), residuals, window, margin)
    assert est.ambiguous and est.small and max(est.scored_px) < MIN_SCORED_PX
    monkeypatch.setattr(cfa_offset, "estimate_cfa_offset", lambda model, sensor, **kw: est)
    with caplog.at_level(logging.INFO):
        estimated_cfa_offset(None, None)
    warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warned) == 2, warned
    assert "is barely better than the other phases" in warned[0]
    assert f"was scored on only {window[2] - 2 * margin}×{window[3] - 2 * margin} px" in warned[1]
