"""Quality on held-out real footage: the learned dictionary beats the 3D DCT and the trivial estimate."""
import json

import numpy as np
import pytest

from codedvideo.engine.config import PipelineConfig
from codedvideo.solvers.dictionaries import dct_dictionary
from codedvideo.model.metrics import evaluate
from codedvideo.data.scenes import load_video
from codedvideo.model.physics import static_estimate
from codedvideo.engine.simulation import simulate_capture
from codedvideo.model.codes import CodeSpec
from codedvideo.engine.training import train_dictionary
from codedvideo.engine.windows import Execution, reconstruct_volume
from codedvideo.solvers.region import OmpSettings
from codedvideo.formats.store import load_dictionary


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    """The default training recipe (synthetic motion of the training photographs), shortened."""
    cache = tmp_path_factory.mktemp("dict")
    cfg = PipelineConfig(frames=8, cache=str(cache))
    cfg = cfg.model_copy(update=dict(dictionary=cfg.dictionary.model_copy(
        update=dict(atoms=256, samples=6000, iterations=5, clips=36))))
    path, meta = train_dictionary(cfg, progress=False)
    assert meta["training_set"] == ["synth:train"]
    return load_dictionary(path)[0]


@pytest.mark.slow
@pytest.mark.parametrize("code,bump", [("hitomi", 2), ("bernoulli", 2)])
def test_learned_beats_dct_and_trivial_on_held_out_real_footage(learned, code, bump, tmp_path):
    video = load_video("footage:bikes-b", frames=8, size=(64, 64))
    cap = simulate_capture(video, code=CodeSpec(code, bump=bump), sigma=0.0, seed=0)
    s = OmpSettings(max_atoms=8, tol_rms=2.0)
    got = {}
    for name, D in (("learned", learned), ("dct", dct_dictionary(8))):
        vol, _ = reconstruct_volume(cap["coded"], cap["mask"], D, settings=s,
                                    run=Execution(tile=32, cache=tmp_path / name, progress=False))
        got[name] = evaluate(vol, video, data_range=255.0)["psnr"]
    trivial = evaluate(static_estimate(cap["coded"], cap["mask"]), video, data_range=255.0)["psnr"]
    assert got["learned"] > got["dct"] + 0.3, json.dumps(got)
    assert got["learned"] > trivial + 3.0, (got, trivial)
    assert np.isfinite(list(got.values())).all()
