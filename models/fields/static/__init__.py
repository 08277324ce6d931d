"""The static radiance field and model (thesis Ch. 3-4)."""
