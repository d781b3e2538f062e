"""Parametric hand models the dataset adapters convert from (MANO)."""
