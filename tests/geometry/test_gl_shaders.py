"""The GL passes' sources, checked without a GL context."""
import re

from engine.geometry.backends.gl.context import SHADERS, shader_source


def test_shaders_test_nan_by_its_bits():
    """No pass relies on NaN comparing false or on isnan(): NVIDIA's compiler folds !(x > y) into x <= y
    (measured on an H200: a NaN pixel took the wrong branch), so NaN tests go through nan_bits/nonfinite_bits."""
    negated = re.compile(r"!\s*\([^()]*[<>]")
    for path in sorted(SHADERS.iterdir()):
        text = path.read_text()
        assert "isnan(" not in text, path.name
        assert not negated.search(text), (path.name, negated.search(text))
    assert "bool nan_bits(float x)" in shader_source("clear_words", {"CLEAR_BINDING": 31})
