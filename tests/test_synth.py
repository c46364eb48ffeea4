import numpy as np
import pytest

from codedvideo import synth
from codedvideo.errors import InputError


def _rng(seed=0):
    return np.random.default_rng(seed)


def _check_clip(v, shape):
    assert v.shape == shape
    assert v.dtype == np.float32
    assert np.isfinite(v).all()
    assert v.min() >= 0.0 and v.max() <= 255.0


# ----------------------------------------------------------------------------- photographs
def test_photographs_are_shipped_and_split():
    assert not set(synth.TRAIN_PHOTOS) & set(synth.TEST_PHOTOS)
    assert set(synth.TRAIN_PHOTOS) | set(synth.TEST_PHOTOS) == set(synth.PHOTO_FILES)
    for name in synth.PHOTO_FILES:
        assert synth.photo_path(name).is_file()
    cam = synth.photo("camera")
    assert cam.shape == (512, 512) and cam.dtype == np.float32 and cam.max() <= 255
    cam[0, 0] = -1  # a copy: the cache is untouched
    assert synth.photo("camera")[0, 0] >= 0
    with pytest.raises(InputError, match="nosuch"):
        synth.photo_path("nosuch")


def test_colour_photos_become_the_grey_of_rgb2gray():
    import skimage.io
    from skimage.color import rgb2gray

    ref = rgb2gray(skimage.io.imread(synth.photo_path("chelsea"))) * 255
    np.testing.assert_allclose(synth.photo("chelsea"), ref, atol=1e-3)


# ----------------------------------------------------------------------------- motions
@pytest.mark.parametrize("motion", synth.MOTIONS)
def test_every_motion_gives_frames_in_range(motion):
    kw = dict(frames=5, size=(24, 32), rng=_rng())
    args = {
        "translate": dict(velocity=(0.4, -1.3)),
        "rotate": dict(omega_deg_per_frame=3.0),
        "zoom": dict(rate_per_frame=-0.04),
        "occlude": dict(velocity=(1.0, 0.5), blob=0.1),
        "deform": dict(amplitude=2.0),
    }[motion]
    photos = ("camera", "coins") if motion == "occlude" else ("camera",)
    v = getattr(synth, motion)(*photos, **kw, **args)
    _check_clip(v, (5, 24, 32))
    assert np.abs(np.diff(v, axis=0)).max() > 1.0  # it moves


def test_translation_moves_the_content_by_the_velocity():
    v = synth.translate("camera", frames=4, size=(40, 48), velocity=(0.0, 1.0), rng=_rng(3))
    for t in range(3):  # frame t+1 shifted back by 1 px is frame t
        np.testing.assert_allclose(v[t + 1][:, 1:], v[t][:, :-1], atol=1e-3)
    assert not np.allclose(v[1], v[0], atol=1.0)
    down = synth.translate("camera", frames=3, size=(40, 48), velocity=(-2.0, 0.0), rng=_rng(4))
    np.testing.assert_allclose(down[1][:-2], down[0][2:], atol=1e-3)
    half = synth.translate("camera", frames=3, size=(40, 48), velocity=(0.0, 0.5), rng=_rng(5))
    np.testing.assert_allclose(half[2][:, 1:], half[0][:, :-1], atol=1e-3)  # subpixel steps add up
    assert np.abs(half[1] - half[0]).mean() > 0.5


def test_rotation_and_zoom_are_exact_on_the_pixel_grid():
    r = synth.rotate("camera", frames=2, size=(33, 33), omega_deg_per_frame=90.0, rng=_rng(1))
    np.testing.assert_allclose(r[1], np.rot90(r[0], k=1), atol=1e-2)
    z = synth.zoom("camera", frames=2, size=(33, 33), rate_per_frame=1.0, rng=_rng(2))
    # magnified 2x about the centre (16, 16): z1[16 + 2a] == z0[16 + a]
    np.testing.assert_allclose(z[1][::2, ::2], z[0][8:25, 8:25], atol=1e-2)


def test_occluder_moves_rigidly_over_a_static_background():
    bg = np.zeros((80, 80), np.float32)
    fg = np.full((80, 80), 200.0, np.float32)
    v = synth.occlude(bg, fg, frames=4, size=(64, 64), velocity=(0.5, 1.5), radius=10.0,
                      start=(30.0, 20.0), source_centre=(40.0, 40.0))
    _check_clip(v, (4, 64, 64))
    yy, xx = np.mgrid[:64, :64]
    for t in range(4):
        w = v[t] / 200.0
        area = w.sum()
        assert area == pytest.approx(np.pi * 10**2, rel=0.02)
        assert (yy * w).sum() / area == pytest.approx(30.0 + 0.5 * t, abs=1e-2)
        assert (xx * w).sum() / area == pytest.approx(20.0 + 1.5 * t, abs=1e-2)
    assert (v[:, :, 50:] == 0).all()  # far from the path the background never changes


def test_deformation_is_smooth_and_travels():
    still = synth.deform("camera", frames=3, size=(32, 32), amplitude=0.0, rng=_rng())
    np.testing.assert_array_equal(still[0], still[2])
    v = synth.deform("camera", frames=3, size=(32, 32), amplitude=2.0, phase_per_frame=0.5, rng=_rng())
    _check_clip(v, (3, 32, 32))
    assert np.abs(v[1] - v[0]).mean() > 0.5


def test_bad_arguments_are_input_errors():
    with pytest.raises(InputError, match="frames"):
        synth.translate("camera", frames=0, size=(16, 16), velocity=(0, 1))
    with pytest.raises(InputError, match="size"):
        synth.translate("camera", frames=2, size=(16,), velocity=(0, 1))
    with pytest.raises(InputError, match="rate_per_frame"):
        synth.zoom("camera", frames=2, size=(16, 16), rate_per_frame=-1.0)
    with pytest.raises(InputError, match="rng"):
        synth.rotate("camera", frames=2, size=(16, 16), omega_deg_per_frame=1, rng=0)
    with pytest.raises(InputError, match="nosuch"):
        synth.make_scene("nosuch", frames=2, size=(16, 16))
    with pytest.raises(InputError, match="motion"):
        synth.make_scene({"motion": "spin", "photo": "camera"}, frames=2, size=(16, 16))


# ----------------------------------------------------------------------------- scenes
def test_scenes_are_seeded():
    a = synth.make_scene("camera-translate", frames=3, size=(32, 32), seed=0)
    b = synth.make_scene("camera-translate", frames=3, size=(32, 32), seed=0)
    c = synth.make_scene("camera-translate", frames=3, size=(32, 32), seed=1)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    spec = {"motion": "occlude", "photo": "moon", "foreground": "cell", "velocity": [0.5, 1.0]}
    d = synth.make_scene(spec, frames=3, size=(32, 32), seed=2)
    np.testing.assert_array_equal(d, synth.make_scene(spec, frames=3, size=(32, 32), seed=2))
    _check_clip(d, (3, 32, 32))


def test_default_scene_moves_and_static70_is_mostly_still():
    d = synth.make_scene("default", frames=6, size=(64, 64), seed=0)
    _check_clip(d, (6, 64, 64))
    np.testing.assert_array_equal(d, synth.make_scene("default", frames=6, size=(64, 64), seed=7))
    assert (np.ptp(d, axis=0) > 0.1).mean() > 0.9  # drift: nearly every pixel changes
    assert np.abs(np.diff(d, axis=0)).mean() > 1.0
    s = synth.make_scene("default-static70", frames=6, size=(64, 64), seed=0)
    _check_clip(s, (6, 64, 64))
    still = np.ptp(s, axis=0) == 0
    assert 0.65 <= still.mean() <= 0.75
    assert (s.std(axis=0) < 1e-3).mean() >= 0.65
    assert np.abs(np.diff(s, axis=0)).max() > 5.0  # the box does move


def test_held_out_scenes_use_test_photos_only():
    scenes = synth.test_scenes(frames=3, size=(32, 32), seed=0)
    assert set(scenes) == set(synth.TEST_SCENES)
    assert {n.rsplit("-", 1)[1] for n in scenes} == set(synth.MOTIONS)
    for name, v in scenes.items():
        _check_clip(v, (3, 32, 32))
        assert set(synth.scene_photos(name)) <= set(synth.TEST_PHOTOS)
        assert np.abs(np.diff(v, axis=0)).mean() > 0.01, name
    assert set(synth.scene_photos("default")) <= set(synth.TEST_PHOTOS)


# ----------------------------------------------------------------------------- training set
def test_training_videos_use_train_photos_only(monkeypatch):
    loaded = []
    real = synth._photo_cached
    monkeypatch.setattr(synth, "_photo_cached", lambda name: loaded.append(name) or real(name))
    clips = synth.training_videos(frames=4, count=20, size=(16, 16), seed=5)
    assert len(clips) == 20 and len(clips.meta) == 20
    for c in clips:
        _check_clip(c, (4, 16, 16))
    assert loaded and set(loaded) <= set(synth.TRAIN_PHOTOS)
    assert clips.photos and clips.photos <= set(synth.TRAIN_PHOTOS)
    assert not clips.photos & set(synth.TEST_PHOTOS)
    for m in clips.meta:
        assert m["motion"] in synth.MOTIONS
        assert synth.SPEED_RANGE[0] <= m["speed"] <= synth.SPEED_RANGE[1]
        if "velocity" in m:
            assert np.hypot(*m["velocity"]) == pytest.approx(m["speed"])


def test_training_videos_are_seeded_and_may_be_longer():
    a = synth.training_videos(frames=4, count=3, size=(16, 16), seed=5)
    b = synth.training_videos(frames=4, count=3, size=(16, 16), seed=5)
    c = synth.training_videos(frames=4, count=3, size=(16, 16), seed=6)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    assert any(not np.array_equal(x, y) for x, y in zip(a, c))
    long = synth.training_videos(frames=4, count=2, size=(16, 16), seed=5, length=10)
    assert all(c.shape == (10, 16, 16) for c in long)
    with pytest.raises(InputError, match="length"):
        synth.training_videos(frames=4, count=1, seed=0, length=3)
