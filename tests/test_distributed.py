"""The same graph on a real dask.distributed scheduler with two workers on loopback."""
import numpy as np
import pytest

from codedvideo.codes import make_code
from codedvideo.dictionaries import dct_dictionary
from codedvideo.physics import simulate
from codedvideo.pipeline import reconstruct_volume
from codedvideo.reconstruct import OmpSettings
from codedvideo.synth import make_scene


@pytest.fixture(scope="module")
def cluster():
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as c:
        yield c


def test_distributed_equals_local(cluster, tmp_path):
    video = make_scene("default", frames=4, size=(40, 52))
    mask = make_code("hitomi", video.shape[1:], frames=4, bump=2, rng=1)
    coded = simulate(video, mask)
    D = dct_dictionary(4)
    s = OmpSettings(max_atoms=6, tol_rms=0.5)
    local, _ = reconstruct_volume(coded, mask, D, settings=s, tile=16, cache=tmp_path / "a", progress=False)
    remote, info = reconstruct_volume(coded, mask, D, settings=s, tile=16, cache=tmp_path / "b", progress=False,
                                      scheduler=cluster.scheduler_address)
    assert info["tiles_computed"] == info["tiles"] == 12
    np.testing.assert_allclose(remote, local, rtol=1e-5, atol=1e-3)
