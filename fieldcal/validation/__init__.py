"""Validation: the whole pipeline against a simulated lens whose truth is known (``fieldcal validate``)."""
