"""Dynamic radiance fields (thesis Ch. 5): DeRF and the K-Planes-style baseline."""
