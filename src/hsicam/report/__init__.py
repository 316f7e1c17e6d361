"""Figures and reports, drawn on `matplotlib.figure.Figure` objects saved to files: no pyplot, and the user's matplotlib
backend is left as it is."""
