"""Shared fixtures."""
import pytest


@pytest.fixture(scope="module")
def one_torch_thread():
    """Run a module's torch code on one thread: on the shared 2-core machines, contending threads cost more."""
    import torch

    old = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(old)


@pytest.fixture(scope="session", autouse=True)
def sift_cache(tmp_path_factory):
    """The per-view SIFT cache of the priors (``models.fields.priors.depth.feature_cache_dir``) in a folder of
    this test session, not the user's ``~/.cache``."""
    import os

    from models.fields.priors.depth import CACHE_ENV

    folder = tmp_path_factory.mktemp("sift-cache")
    old = os.environ.get(CACHE_ENV)
    os.environ[CACHE_ENV] = str(folder)
    yield folder
    if old is None:
        os.environ.pop(CACHE_ENV, None)
    else:
        os.environ[CACHE_ENV] = old


@pytest.fixture(params=["one range", "three threads"])
def point_split(request, monkeypatch):
    """Run the per-point kernels (``engine.geometry.kernels.split_points``) in one range, or split into ranges of
    at least 40 points on 3 threads: a test that asserts exact results with this fixture holds the split to the
    same bits."""
    from engine.geometry import kernels

    if request.param == "three threads":
        monkeypatch.setattr(kernels, "MIN_POINTS_PER_THREAD", 40)
        monkeypatch.setenv(kernels.THREADS_ENV, "3")
    return request.param
