"""Posed (and time-stamped) views: dataset loaders and train/test splits."""
