from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).parent
DATA = HERE / "data"
sys.path.insert(0, str(HERE))  # tests import the `scenes` helper


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


@pytest.fixture
def bmx_las() -> Path:
    return DATA / "autzen-bmx-2010.las"


@pytest.fixture
def autzen_laz() -> Path:
    from tiereg.demo import sample_lidar

    return sample_lidar()
