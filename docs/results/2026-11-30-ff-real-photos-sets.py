"""Forward-facing real-photo sets from the Beer capture (docs/results/2026-11-30-ff-real-photos.md).

The Beer walk (``../shared/data/llff_beer``, 71 photos) turns around its object, but three stretches of it face
one way. Each stretch becomes an LLFF folder of its own (the photos linked, their rows of ``poses_bounds.npy``
copied), which ``interleave train field`` classifies by its own cameras (``llff_scene_type``).

    PYTHONPATH=. python docs/results/2026-11-30-ff-real-photos-sets.py ../shared/data/llff_beer OUT_DIR

writes OUT_DIR/ffA (photos 0-5), ffB (9-13) and ffC (56-62) and prints each set's scene type, the largest angle
of an optical axis from the mean axis, and the camera centres' extent (scene units).
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from models.fields.data.views import llff_scene_type, load_llff, optical_axis_spread

#: Set name -> the capture's photo numbers (its stretches that face one way).
SETS = {"ffA": range(0, 6), "ffB": range(9, 14), "ffC": range(56, 63)}


def write_set(src: Path, out: Path, photos: range) -> None:
    """An LLFF folder at ``out`` holding ``photos`` of ``src`` (links to its images, its pose rows)."""
    (out / "images").mkdir(parents=True, exist_ok=True)
    rows = np.load(src / "poses_bounds.npy")
    for i in photos:
        link = out / "images" / f"{i:04d}.jpg"
        if not link.exists():
            link.symlink_to((src / "images" / f"{i:04d}.jpg").resolve())
    np.save(out / "poses_bounds.npy", rows[list(photos)])


def main(argv: list[str]) -> int:
    src, out = Path(argv[0]), Path(argv[1])
    for name, photos in SETS.items():
        write_set(src, out / name, photos)
        views = load_llff(out / name, downscale=8)
        spread = optical_axis_spread(views.cameras)
        extent = np.ptp(np.stack([c.position for c in views.cameras]), axis=0)
        print(f"{name}: photos {photos.start}-{photos.stop - 1}, {llff_scene_type(views.cameras)}, "
              f"axes within {spread:.1f} deg, centres' extent {np.round(extent, 2).tolist()}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
