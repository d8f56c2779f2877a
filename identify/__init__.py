"""Identifiability of (d, h, E) from different measurements (issue 7; work in progress)."""
