"""Static radiance fields trained from a few posed views on a CPU (thesis Ch. 3-4 groundwork).

Layers, as in nerfstudio: components (``encodings``: tri-planes, direction encodings, MLPs) -> field
(``field``: :class:`TriPlaneField`) -> model (``model``: scene contraction + sampling + rendering) ->
training (``losses``, ``train``). The sparse-input priors of thesis Ch. 3-4 are ``priors`` (config and
wiring), ``priors_depth``, ``priors_simple``, ``priors_vip``; ``ablation`` compares them. Data loaders and
the train/test split are in ``data``. The design note is ``docs/fields.md``.

>>> from models.fields import load_nerf_synthetic, FieldTrainConfig, train_field, evaluate_field  # doctest: +SKIP
>>> views = load_nerf_synthetic("lego", "train", downscale=8)                                   # doctest: +SKIP
>>> run = train_field(views.subset([0, 5, 10]), FieldTrainConfig(steps=500), "runs/lego3")       # doctest: +SKIP
>>> evaluate_field(run, load_nerf_synthetic("lego", "test", downscale=8))                        # doctest: +SKIP
"""
from models.fields.components.encodings import TriPlaneEncoding, plane_l1, plane_tv, sample_planes, sh_encoding
from models.fields.components.render import RayOutputs, composite, render_image, volume_weights
from models.fields.components.sampling import OccupancyGrid, camera_rays, ray_box_intersection, sample_intervals
from models.fields.data.views import (Views, box_from_cameras, check_views, load_llff, load_nerf_synthetic, load_rig,
                                      split_indices)
from models.fields.losses import LOSS_TERMS, LossInputs, LossTerm, RayBatch, register_loss_term
from models.fields.priors.config import PRIOR_NAMES, PriorsConfig, with_priors
from models.fields.static.field import FieldConfig, TriPlaneField
from models.fields.static.model import RenderConfig, SceneBox, StaticFieldModel
from models.fields.train_static import FieldTrainConfig, evaluate_field, load_model, train_field

__all__ = ["Views", "box_from_cameras", "check_views", "load_llff", "load_nerf_synthetic", "load_rig",
           "split_indices", "TriPlaneEncoding", "plane_l1", "plane_tv", "sample_planes", "sh_encoding",
           "FieldConfig", "TriPlaneField", "LOSS_TERMS", "LossInputs", "LossTerm", "RayBatch",
           "register_loss_term", "RenderConfig", "SceneBox", "StaticFieldModel", "RayOutputs", "composite",
           "render_image", "volume_weights", "OccupancyGrid", "camera_rays", "ray_box_intersection",
           "sample_intervals", "FieldTrainConfig", "evaluate_field", "load_model", "train_field", "PRIOR_NAMES",
           "PriorsConfig", "with_priors"]
