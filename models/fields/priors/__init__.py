"""Sparse-input priors: sparse depth, Simple-RF, ViP visibility, sparse flow."""
