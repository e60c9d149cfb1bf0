"""Calibration charts: random texture (focus), ChArUco (geometry) and slanted edges (MTF), as images and printable files."""
