"""Environments: the double-lane-change vehicle (eq. 53) and its Gymnasium face."""
