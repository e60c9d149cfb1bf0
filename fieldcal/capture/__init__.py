"""Capture: acquisition plans (inspectable streams of moves and exposures) and the one runner that executes them."""
