"""Shared pytest configuration: CPU-first, deterministic; `gpu` tests skip cleanly without CUDA."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("AVATARCTL_DIST_TIMEOUT", "60")  # multi-rank tests: a lost rank ends a collective in 60 s


def pytest_collection_modifyitems(config, items):
    try:
        import torch

        has_cuda = torch.cuda.is_available()
    except Exception:  # pragma: no cover - torch missing is an install error reported elsewhere
        has_cuda = False
    skip_gpu = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords and not has_cuda:
            item.add_marker(skip_gpu)


@pytest.fixture(autouse=True)
def _seed_everything():
    import random

    import numpy as np
    import torch

    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)
    yield


@pytest.fixture(scope="session")
def toy_fitted_project(tmp_path_factory):
    """A toy-sphere project after ingest and 10 micro fit steps (seconds, no anny), shared by the export and viewer
    tests (they add outputs beside the fit, never change it)."""
    from fixtures.toy_fitted import make_toy_fitted

    return make_toy_fitted(tmp_path_factory.mktemp("toy_fitted"), iters=10)


@pytest.fixture(scope="session")
def toy_gaussian_project(tmp_path_factory):
    """The toy project fitted for a few steps with the Gaussian local fields (viewer and player tests)."""
    from fixtures.toy_fitted import make_toy_fitted_gaussians

    return make_toy_fitted_gaussians(tmp_path_factory.mktemp("toy_gaussians"))


@pytest.fixture(scope="session")
def random_smplx(tmp_path_factory):
    """(model file, `SmplBody`) of a random SMPL-X model (`fixtures.smpl`, seed 4; never a licensed file), shared by
    the dataset-layout tests (DNA-Rendering, 4D-DRESS)."""
    from fixtures.smpl import write_random_smpl_npz

    from avatarctl.body.smpl import SmplBody

    path = write_random_smpl_npz(tmp_path_factory.mktemp("smplx") / "SMPLX_NEUTRAL.npz", "smplx", seed=4)
    return path, SmplBody.from_file(path, kind="smplx")
