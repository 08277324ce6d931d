"""``tools.field_vectors_check`` on the field demo of the programmed fields (``tools.programmed_field``)."""
from __future__ import annotations

import json

import pytest

from engine.fields import gl as glfield
from engine.fields.dynamic import COHERENCE
from tools.field_vectors_check import check, main
from tools.programmed_field import write_export

MVEC = "EPE moving: mvec's flow from the vectors {}"


@pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")
def test_the_check_tells_steady_motion_from_motion_that_turns(tmp_path):
    from demos.upsample import run_field_demo

    figures = {}
    for name, zigzag in (("steady", False), ("zigzag", True)):
        export = write_export(tmp_path / name / "export", zigzag=zigzag)
        run_field_demo(export, tmp_path / name / "demo", k=2, frames=10, width=64, height=48, methods=("reproject",),
                       progress=False, backend="cpu")
        figures[name] = check(tmp_path / name / "demo", 2)
    steady, zigzag = figures["steady"], figures["zigzag"]
    assert steady["pairs"] == zigzag["pairs"] == 4 and steady["moving share of the frame"] > 0.05
    # the steady translation: mvec's flow from the field's vectors is well ahead of no motion, and the
    # coherence check drops none of it
    assert steady[MVEC.format("as is")] < 0.5 * steady["EPE moving: zero motion (reproject)"]
    assert steady[MVEC.format("as is")] == steady[MVEC.format(f"coherence {COHERENCE}")]
    # the zig-zag one: the coherence check drops the motion that turned, and with it the flow's error
    assert zigzag[MVEC.format(f"coherence {COHERENCE}")] < zigzag[MVEC.format("as is")]
    out = tmp_path / "check.json"
    assert main([str(tmp_path / "steady" / "demo"), "--json", str(out)]) == 0
    assert json.loads(out.read_text())[MVEC.format("as is")] == steady[MVEC.format("as is")]
    assert main([str(tmp_path)]) == 2  # not a demo's folder: one line, exit 2
