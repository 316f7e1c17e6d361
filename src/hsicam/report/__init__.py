"""Figures and reports. Plotting uses matplotlib's non-interactive Agg backend."""
