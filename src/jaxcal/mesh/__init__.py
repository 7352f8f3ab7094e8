"""Mesh self-calibration: nodes ranging each other (closed form, grid-based Bayesian filter, batch)."""
