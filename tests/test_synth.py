import numpy as np

from codedvideo.data import synth


def test_scenes_are_seeded_in_range_and_moving():
    a = synth.make_scene("default", frames=6, size=(48, 64))
    b = synth.make_scene("default", frames=6, size=(48, 64))
    assert a.shape == (6, 48, 64) and a.dtype == np.float32
    assert 0 <= a.min() and a.max() <= 255
    np.testing.assert_array_equal(a, b)
    assert np.abs(np.diff(a, axis=0)).mean() > 0.5


def test_translation_moves_at_the_requested_speed():
    img = synth.photo("camera")
    v = synth.translate(img, frames=3, size=(40, 40), velocity=(0.0, 1.0))
    # frame t+1 at x equals frame t at x+1 (interior)
    np.testing.assert_allclose(v[1][:, :-1], v[0][:, 1:], atol=1e-2)
    assert not np.allclose(v[1], v[0])


def test_static70_scene_has_a_still_region():
    s = synth.make_scene("default-static70", frames=8, size=(64, 64))
    still = (s.std(0) < 1e-3).mean()
    assert 0.65 <= still <= 0.75


def test_training_clips_use_train_photos_only_and_are_seeded(monkeypatch):
    used = []
    real = synth.photo
    monkeypatch.setattr(synth, "photo", lambda name: used.append(name) or real(name))
    clips = synth.training_videos(frames=4, count=12, size=(24, 24), seed=5)
    assert len(clips) == 12 and all(c.shape == (4, 24, 24) for c in clips)
    assert used and set(used) <= set(synth.TRAIN_PHOTOS)
    again = synth.training_videos(frames=4, count=3, size=(24, 24), seed=5)
    for x, y in zip(clips[:3], again):
        np.testing.assert_array_equal(x, y)
