"""Simulators: UWB channel models and mesh / trajectory scenarios."""
