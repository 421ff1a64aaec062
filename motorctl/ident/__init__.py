"""Identification from logged runs: nominal IDIM-LS fit, residual analysis, effect search."""
