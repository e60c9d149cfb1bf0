"""Calibration reports: PNG plots of surfaces, bands and residuals, and one HTML page."""
