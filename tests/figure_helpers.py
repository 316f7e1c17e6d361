"""Reading back what a saved matplotlib figure shows: where its text was drawn."""

from __future__ import annotations


def drawn_extent(fig, axis):
    """Window extent (a Bbox, px) of an axis's visible tick labels and its label, the figure drawn again as it was
    saved (a figure closed by :func:`hsicam.io.save_figure` no longer has a canvas that renders)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.transforms import Bbox

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    parts = [t.get_window_extent(renderer) for t in axis.get_ticklabels() if t.get_visible() and t.get_text()]
    if axis.label.get_text():
        parts.append(axis.label.get_window_extent(renderer))
    return Bbox.union(parts)
