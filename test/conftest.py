"""Shared fixtures: deterministic seeds, the shared data folder (tests that need it skip without it), a short synthetic
sequence as observations."""
import os
from pathlib import Path

import numpy as np
import pytest
import torch

if not torch.cuda.is_available():  # Triton kernels run through its interpreter (read when Triton is imported)
    os.environ.setdefault("TRITON_INTERPRET", "1")

from gausem_bench.data import SHARED_DATA, VARIABLE
from gausem_core.data import SYNTHETIC_CLASSES, SyntheticDataset
from gausem_core.geometry import invert_pose
from gausem_core.slam.observation import Observation


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)
    np.random.seed(0)


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder {SHARED_DATA} is absent (set {VARIABLE})")
    return SHARED_DATA


@pytest.fixture(scope="session")
def ade20k_model() -> Path:
    """The shared ADE20K segmentation model (tests that need it skip without it)."""
    from gausem_core.semantics.ade20k import MODEL_FILE, MODELS_VARIABLE, shared_models
    model = shared_models() / MODEL_FILE
    if not model.is_file():
        pytest.skip(f"the shared ADE20K model {model} is absent (set {MODELS_VARIABLE})")
    return model


@pytest.fixture(scope="module")
def sequence(request):
    """Every ``SEQUENCE_STRIDE``-th frame (the requesting module's constant) of the default synthetic sequence at
    80x60: its observations and world poses (the first frame's is the identity)."""
    data = SyntheticDataset("default", resolution=(80, 60), stride=request.module.SEQUENCE_STRIDE)
    frames = [data[i] for i in range(len(data))]
    first = torch.tensor(frames[0].gt_pose)
    observations = [Observation.from_arrays(f.rgb, f.depth, f.labels, f.camera, SYNTHETIC_CLASSES.palette,
                                             f.timestamp) for f in frames]
    return observations, [(invert_pose(first) @ torch.tensor(f.gt_pose)).float() for f in frames]
