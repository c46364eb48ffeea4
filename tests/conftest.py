import numpy as np
import pytest


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


def random_dictionary(rng, n_features, atoms):
    D = rng.normal(size=(n_features, atoms)).astype(np.float32)
    return D / np.linalg.norm(D, axis=0)
