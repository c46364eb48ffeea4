"""One data-range rule: noise widens a range but never picks one, clipped pixels do not set it, and a stream's
warning says which captures hold the values above it.  Each case failed before the rule was made one."""
import warnings

import numpy as np
import pytest

from codedvideo.data.synth import make_scene
from codedvideo.model.codes import make_code
from codedvideo.model.physics import simulate
from codedvideo.model.units import capture_units

N, H, W = 8, 64, 64


def _units(codeds, mask, **options):
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        units = capture_units(codeds, lambda i: mask, **options)
    return units, [str(w.message) for w in said]


def _noisy(truth, mask, sigma, seed=0):
    return simulate(truth.astype(np.float32), mask, sigma=sigma, rng=seed).astype(np.float32)


@pytest.mark.parametrize("sigma", [10.0, 25.0])
def test_a_dark_8_bit_capture_with_read_noise_is_not_taken_for_unit_floats(sigma):
    truth = make_scene("default", frames=N, size=(H, W)).astype(np.float32)
    truth *= 37.0 / truth.max()  # a dark scene: its brightest pixel at 37 grey levels
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=0)
    units, _ = _units([_noisy(truth, mask, sigma)], mask, levels=dict(noise_sigma=sigma))
    assert units.value == 255.0, units


@pytest.mark.parametrize("sigma", [50.0, 80.0])
def test_heavy_read_noise_widens_the_8_bit_range_and_does_not_pick_another(sigma):
    truth = make_scene("default", frames=N, size=(H, W)).astype(np.float32)
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=0)
    units, _ = _units([_noisy(truth, mask, sigma)], mask, levels=dict(noise_sigma=sigma))
    assert units.value == 255.0, units


def test_a_unit_float_capture_with_its_own_noise_keeps_its_range():
    truth = make_scene("default", frames=N, size=(H, W)).astype(np.float32) / 255
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=0)
    units, _ = _units([_noisy(truth, mask, 0.03)], mask, levels=dict(noise_sigma=0.03))
    assert units.value == 1.0, units


def _overexposed():
    """An 8-bit scene whose highlights run to 1000 grey levels, through a Bernoulli code, read out by a sensor
    that clips the coded image at 510: the clipped pixels divided by an open count of 1 reach 510."""
    truth = make_scene("default", frames=N, size=(H, W)).astype(np.float32) * (240.0 / 255)
    truth[:, 8:24, 8:24] = 1000.0
    mask = make_code("bernoulli", (H, W), frames=N, p=0.5, rng=2)
    coded = np.minimum(simulate(truth, mask), 510.0).astype(np.float32)
    return coded, mask


def test_clipped_pixels_do_not_set_the_range_when_the_white_level_is_given():
    coded, mask = _overexposed()
    units, _ = _units([coded], mask, white_level=510.0)
    assert units.value == 255.0, units


def test_clipped_pixels_found_by_their_equal_values_do_not_set_the_range_and_are_said():
    coded, mask = _overexposed()
    units, said = _units([coded], mask)
    assert units.value == 255.0, units
    assert any("clipped by the sensor" in s and "--white-level 510" in s for s in said), said


def test_a_scene_of_one_flat_value_is_not_taken_for_clipping():
    mask = make_code("bernoulli", (H, W), frames=N, p=0.5, rng=2)
    coded = simulate(np.full((N, H, W), 0.5, np.float32), mask).astype(np.float32)  # coded = 0.5 x open count
    units, said = _units([coded], mask)
    assert units.value == 1.0 and not any("clipped" in s for s in said), (units, said)


def test_a_stream_warning_names_the_captures_above_the_range_not_the_whole_stream():
    truth = make_scene("default", frames=N, size=(H, W)).astype(np.float32) * (240.0 / 255)
    mask = make_code("hitomi", (H, W), frames=N, bump=2, rng=0)
    codeds = [simulate(truth, mask).astype(np.float32) for _ in range(5)]
    codeds[2] = codeds[2] * 8  # capture 3 blown out
    _, said = _units(codeds, mask, given=255.0)
    above = [s for s in said if "lie above the data range" in s]
    assert len(above) == 1, said
    assert "in 1 of 5 captures" in above[0] and "capture 3" in above[0], above
    share = float(above[0].split("%")[0].split()[-1])
    assert share < 25.0, above  # a fifth of the stream at most, not 100 %
