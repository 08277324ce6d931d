"""Which views a run trains and is scored on: scene folders detected, loaded and split into train and test
views (static scenes: NeRF-synthetic, LLFF, rgbd-rig; dynamic scenes: rgbd-rig videos, D-NeRF), and the split
a run recorded in its ``data.json`` loaded again.

The record that :func:`select_views` / :func:`select_dynamic_views` return is what ``interleave train
field|dynamic`` writes to ``data.json``; :func:`load_run_views` / :func:`load_dynamic_run_views` rebuild the
same views from it (``interleave eval``, the demo, the exporters' parity view).
"""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Any, Optional

import numpy as np

from engine.core.errors import InputError
from engine.io.llff import choose_image_folder
from models.fields.data.timed import TimedViews, load_dnerf, load_rig_video, split_by_camera
from models.fields.data.views import Views, load_llff, load_nerf_synthetic, load_rig, split_indices

__all__ = ["DATASETS", "detect_dataset", "select_views", "load_run_views", "DYNAMIC_DATASETS", "DYNAMIC_TEST_SPLITS",
           "detect_dynamic_dataset", "select_dynamic_views", "load_dynamic_run_views", "read_data_record"]


def read_data_record(run_dir: str | Path, made_by: str) -> dict[str, Any]:
    """The ``data.json`` record of a run directory; InputError naming the file when it is missing."""
    file = Path(run_dir) / "data.json"
    if not file.is_file():
        raise InputError(f"file does not exist: the run was not made by '{made_by}' (or the folder is not a run "
                         "directory)", file=file)
    return json.loads(file.read_text())


# ----------------------------------------------------------------------------------------------------
# Static scenes


DATASETS = ("nerf-synthetic", "llff", "rig")


def detect_dataset(path: str | Path) -> str:
    """The layout of a scene folder: ``nerf-synthetic`` (transforms_train.json), ``llff``
    (poses_bounds.npy) or ``rig`` (rig.json)."""
    root = Path(path)
    for marker, kind in (("transforms_train.json", "nerf-synthetic"), ("poses_bounds.npy", "llff"),
                         ("rig.json", "rig")):
        if (root / marker).is_file():
            return kind
    if not root.exists():
        raise InputError("folder does not exist", file=root)
    raise InputError("is not a scene folder: expected transforms_train.json (NeRF-synthetic), poses_bounds.npy "
                     "(LLFF) or rig.json (rgbd-rig)", file=root)


def _positions(pool: Views, spec: list, name: str) -> list[int]:
    """View positions in ``pool`` for a list of positions and/or names (a name matches a view's name or
    its file stem)."""
    stems = [Path(n).stem if n else "" for n in pool.names]
    out = []
    for item in spec:
        if isinstance(item, int):
            if not 0 <= item < len(pool):
                raise InputError(f"position {item} out of range: {len(pool)} views were loaded", field=name)
            out.append(item)
        elif item in pool.names or item in stems:
            out.append(pool.names.index(item) if item in pool.names else stems.index(item))
        else:
            raise InputError(f"no view named {item!r} (views: {', '.join(stems[:8])}{'...' if len(stems) > 8 else ''})",
                             field=name)
    if len(set(out)) != len(out):
        raise InputError(f"names a view twice: {spec}", field=name)
    return out


def select_views(dataset: str, scene: str | Path, downscale: int, *, views: Optional[int] = None,
                 train_views: Optional[list] = None, test_views: Optional[list] = None,
                 max_test_views: int = 0) -> tuple[Views, Views, dict[str, Any]]:
    """Load a scene and split it into (train, test) views; the third item records the choice (``data.json``).

    NeRF-synthetic: train views come from the train split, test views from the test split (all present
    frames unless ``test_views``). LLFF and rigs: one pool; the default split is ``split_indices`` (every
    8th frame held out, train views spread over the rest), or the rig's own train/test cameras when
    ``views`` is not given. ``train_views`` / ``test_views`` are positions among the *loaded* frames
    (listed frames whose files are missing are skipped) or view names (``r_20``, ``cam3``).

    ``downscale`` is relative to the dataset's full-size images; 0 (auto) keeps the dataset's own images, and
    for LLFF picks the coarsest ``images_N`` folder shipped (``models.fields.data.views.load_llff``). The
    record holds the resolution reached (``downscale``) and, for LLFF, the folder read (``image_folder``).
    """
    if dataset not in DATASETS:
        raise InputError(f"must be one of {DATASETS}, got {dataset!r}", field="dataset")
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 0:
        raise InputError(f"must be an integer >= 0 (0: auto), got {downscale!r}", field="downscale")
    auto = downscale == 0
    downscale = 1 if auto and dataset != "llff" else int(downscale)
    if dataset == "nerf-synthetic":
        pool = load_nerf_synthetic(scene, "train", downscale=downscale)
        test_pool = load_nerf_synthetic(scene, "test", downscale=downscale)
        train_idx = (_positions(pool, train_views, "train_views") if train_views is not None
                     else split_indices(len(pool), views=views, test_every=0)[0])
        test_idx = (_positions(test_pool, test_views, "test_views") if test_views is not None
                    else list(range(len(test_pool))))
    else:
        pool = (load_llff(scene, downscale=None if auto else downscale) if dataset == "llff"
                else load_rig(scene).downscaled(downscale))
        test_pool = pool
        tr = _positions(pool, train_views, "train_views") if train_views is not None else None
        te = _positions(pool, test_views, "test_views") if test_views is not None else None
        if dataset == "rig" and pool.default_split is not None and views is None and tr is None and te is None:
            train_idx, test_idx = (list(x) for x in pool.default_split)
        else:
            if tr is not None and te is None:
                te = split_indices(len(pool))[1]
                te = [i for i in te if i not in tr]
            train_idx, test_idx = split_indices(len(pool), views=None if tr is not None else views,
                                                train_views=tr, test_views=te)
    if max_test_views:
        test_idx = test_idx[:max_test_views]
    if not train_idx:
        raise InputError("no train views selected", field="train_views")
    if not test_idx:
        raise InputError("no test views selected", field="test_views")
    train, test = pool.subset(train_idx), test_pool.subset(test_idx)
    record = {"dataset": dataset, "scene": str(Path(scene).resolve()), "downscale": int(train.downscale),
              "train_views": [int(i) for i in train_idx], "test_views": [int(i) for i in test_idx],
              "train_names": list(train.names), "test_names": list(test.names)}
    if dataset == "llff":
        record["image_folder"] = choose_image_folder(scene, record["downscale"])[0].name
    return train, test, record


def load_run_views(run_dir: str | Path) -> tuple[Views, Views]:
    """The (train, test) views a run was trained and is evaluated on, from its ``data.json``."""
    rec = read_data_record(run_dir, "interleave train field")
    train, test, _ = select_views(rec["dataset"], rec["scene"], rec["downscale"], train_views=rec["train_views"],
                                  test_views=rec["test_views"])
    return train, test


# ----------------------------------------------------------------------------------------------------
# Dynamic scenes


DYNAMIC_DATASETS = ("rig", "dnerf")
#: the D-NeRF splits a dynamic run can hold out (a rig holds out cameras: 'test' only)
DYNAMIC_TEST_SPLITS = ("test", "val")


def detect_dynamic_dataset(path: str | Path) -> str:
    """``rig`` (rig.json) or ``dnerf`` (transforms_train.json whose frames carry a time)."""
    root = Path(path)
    if (root / "rig.json").is_file():
        return "rig"
    meta = root / "transforms_train.json"
    if meta.is_file():
        try:
            frames = json.loads(meta.read_text()).get("frames", [])
        except json.JSONDecodeError:
            frames = []
        if frames and all("time" in f for f in frames):
            return "dnerf"
        raise InputError("is a static NeRF-synthetic scene (its frames have no 'time'): use 'interleave train "
                         "field'", file=meta)
    if not root.exists():
        raise InputError("folder does not exist", file=root)
    raise InputError("is not a dynamic scene folder: expected rig.json (rgbd-rig video) or a D-NeRF "
                     "transforms_train.json", file=root)


def _camera_names(pool: TimedViews, spec, name: str) -> list[str]:
    out = []
    for item in spec:
        if isinstance(item, int):
            if not 0 <= item < len(pool.camera_names):
                raise InputError(f"camera position {item} out of range for {len(pool.camera_names)} cameras",
                                 field=name)
            out.append(pool.camera_names[item])
        elif item in pool.camera_names:
            out.append(item)
        else:
            raise InputError(f"no camera named {item!r} (cameras: {', '.join(pool.camera_names)})", field=name)
    if len(set(out)) != len(out):
        raise InputError(f"names a camera twice: {spec}", field=name)
    return out


def select_dynamic_views(dataset: str, scene: str | Path, downscale: int, *, cameras: Optional[int] = None,
                         train_cameras: Optional[list] = None, test_cameras: Optional[list] = None,
                         frames: Optional[list[int]] = None, test_every: int = 1, max_test_views: int = 0,
                         test_split: str = "test") -> tuple[TimedViews, TimedViews, dict[str, Any]]:
    """Load a dynamic scene and split it into (train, test) views; the third item is ``data.json``'s record.

    rgbd-rig: every frame (or ``frames``) of the train cameras trains, the test cameras' frames are held out;
    the default split is the rig's, ``cameras`` picks that many train cameras spread over the non-test ones,
    ``train_cameras`` / ``test_cameras`` name them (names or positions). D-NeRF: the train split trains, the
    ``test_split``'s frames ('test' or 'val') whose times lie in the trained range are held out (the others
    are dropped with a warning: the field cannot extrapolate in time). ``test_every`` keeps every k-th test
    view, ``max_test_views`` at most that many.
    """
    if dataset not in DYNAMIC_DATASETS:
        raise InputError(f"must be one of {DYNAMIC_DATASETS}, got {dataset!r}", field="dataset")
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 0:
        raise InputError(f"must be an integer >= 0 (0: auto, the dataset's images), got {downscale!r}",
                         field="downscale")
    downscale = int(downscale) or 1
    if isinstance(test_every, bool) or not isinstance(test_every, int) or test_every < 1:
        raise InputError(f"must be a positive integer, got {test_every!r}", field="test_every")
    if test_split not in DYNAMIC_TEST_SPLITS:
        raise InputError(f"must be one of {DYNAMIC_TEST_SPLITS}, got {test_split!r}", field="test_split")
    if dataset == "rig" and test_split != "test":
        raise InputError("an rgbd-rig holds out cameras, not a split: test_split must be 'test'", field="test_split")
    dropped: list[str] = []
    if dataset == "rig":
        pool = load_rig_video(scene, downscale=downscale, frames=frames)
        split = pool.default_split or ([], [])
        rig_train = [pool.camera_names[c] for c in np.unique(pool.camera_ids[split[0]])] if split[0] else []
        rig_test = [pool.camera_names[c] for c in np.unique(pool.camera_ids[split[1]])] if split[1] else []
        test_names = _camera_names(pool, test_cameras, "test_cameras") if test_cameras is not None else rig_test
        if train_cameras is not None:
            train_names = _camera_names(pool, train_cameras, "train_cameras")
        else:
            rest = [n for n in pool.camera_names if n not in test_names]
            if cameras is None:
                train_names = [n for n in rig_train if n not in test_names] or rest
            else:
                if isinstance(cameras, bool) or not isinstance(cameras, int) or not 1 <= cameras <= len(rest):
                    raise InputError(f"must be an integer in 1..{len(rest)} (cameras left after the test cameras), "
                                     f"got {cameras!r}", field="cameras")
                positions = np.floor(np.linspace(0, len(rest) - 1, cameras) + 0.5).astype(int)
                train_names = [rest[p] for p in positions]
        train, test = split_by_camera(pool, train_names, test_names)
        record_cams = {"train_cameras": train_names, "test_cameras": test_names}
    else:
        if cameras is not None or train_cameras is not None or test_cameras is not None:
            raise InputError("D-NeRF is monocular: it takes no camera choice", field="cameras")
        train = load_dnerf(scene, "train", downscale=downscale)
        test = load_dnerf(scene, test_split, downscale=downscale, bounds=train.bounds)
        lo, hi = train.time_range
        inside = [i for i in range(len(test)) if lo <= test.times[i] <= hi]
        dropped = [test.names[i] for i in range(len(test)) if i not in inside]
        if dropped:
            warnings.warn(f"{len(dropped)} test view(s) lie outside the trained time range [{lo:.4g}, {hi:.4g}] and "
                          f"are not evaluated: {', '.join(dropped)}", stacklevel=2)
        test = test.subset(inside)
        record_cams = {"train_cameras": [], "test_cameras": []}
    keep = list(range(0, len(test), test_every))
    if max_test_views:
        keep = keep[:max_test_views]
    test = test.subset(keep)
    if len(test) == 0:
        raise InputError("no test view selected", field="test_cameras")
    record = {"dataset": dataset, "scene": str(Path(scene).resolve()), "downscale": int(downscale), **record_cams,
              "frames": None if frames is None else [int(f) for f in frames], "test_every": int(test_every),
              "max_test_views": int(max_test_views), "test_split": test_split, "train_views": len(train),
              "test_names": list(test.names), "dropped_test_views": dropped}
    return train, test, record


def load_dynamic_run_views(run_dir: str | Path, split: Optional[str] = None) -> tuple[TimedViews, TimedViews]:
    """The (train, test) views a dynamic run was trained and is evaluated on, from its ``data.json``; ``split``
    ('test' or 'val', D-NeRF) replaces the held-out split the run recorded."""
    rec = read_data_record(run_dir, "interleave train dynamic")
    with warnings.catch_warnings():  # the warnings were given when the run was made
        warnings.simplefilter("ignore")
        is_rig = rec["dataset"] == "rig"
        train, test, _ = select_dynamic_views(
            rec["dataset"], rec["scene"], rec["downscale"], train_cameras=rec["train_cameras"] if is_rig else None,
            test_cameras=rec["test_cameras"] if is_rig else None, frames=rec.get("frames"),
            test_every=rec.get("test_every", 1), max_test_views=rec.get("max_test_views", 0),
            test_split=split or rec.get("test_split", "test"))
    return train, test
