"""Validation: the exact LQ case against python-control's DARE, and the paper reproduction."""
