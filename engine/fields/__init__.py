"""Exported radiance fields rendered without torch: assets, numpy references, moderngl renderers."""
