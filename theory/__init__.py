"""Empirical checks of the paper's theorems (1-4) on any model, value and policy."""
