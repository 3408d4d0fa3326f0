"""Algorithms: exact policy iteration (Algorithm 1), AGPI actor-critic (Algorithm 2), baselines."""
