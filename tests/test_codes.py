import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from codedvideo.codes import bump_starts, check_code, make_code, window_coverage
from codedvideo.errors import InputError


@settings(max_examples=40, deadline=None)
@given(
    h=st.integers(7, 40),
    w=st.integers(7, 40),
    frames=st.integers(1, 36),
    bump=st.integers(1, 10),
    seed=st.integers(0, 2**31),
    tiled=st.booleans(),
)
def test_every_window_covers_every_subframe(h, w, frames, bump, seed, tiled):
    bump = min(bump, frames)
    if 49 * bump < frames:
        return
    mask = make_code("hitomi-tiled" if tiled else "hitomi", (h, w), frames=frames, bump=bump, rng=seed)
    assert mask.shape == (frames, h, w)
    assert (window_coverage(mask) > 0).all()
    rep = check_code(mask)
    assert rep.binary and rep.single_bump and rep.fixed_bump and rep.window_coverage
    assert rep.bump_length == bump
    assert rep.never_open_pixels == 0


def test_paper_settings_n36_all_bumps():
    for bump in range(1, 11):
        mask = make_code("hitomi", (64, 64), frames=36, bump=bump, rng=bump)
        assert (window_coverage(mask) > 0).all(), bump
        assert (mask.sum(0) == bump).all()


def test_impossible_coverage_is_a_clear_error():
    with pytest.raises(InputError, match="coverage impossible"):
        make_code("hitomi", (16, 16), frames=64, bump=1)


def test_seeded_and_random():
    a = make_code("hitomi", (32, 32), frames=8, bump=2, rng=5)
    b = make_code("hitomi", (32, 32), frames=8, bump=2, rng=5)
    c = make_code("hitomi", (32, 32), frames=8, bump=2, rng=6)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    # the sliding code is not periodic: most pixels differ from the pixel 7 columns on
    s = bump_starts((32, 32), frames=8, bump=2, rng=5)
    assert (s[:, 7:] != s[:, :-7]).mean() > 0.5
    t = bump_starts((32, 32), frames=8, bump=2, rng=5, tiled=True)
    assert (t[:, 7:] == t[:, :-7]).all()


def test_check_code_flags_violations():
    rng = np.random.default_rng(0)
    bern = make_code("bernoulli", (20, 20), frames=8, rng=rng)
    rep = check_code(bern)
    assert rep.binary and not rep.single_bump
    two_bumps = np.zeros((6, 8, 8), np.uint8)
    two_bumps[[0, 3]] = 1
    assert not check_code(two_bumps).single_bump
    holes = make_code("hitomi", (14, 14), frames=8, bump=2)
    holes[:, 3, 3] = 0
    assert check_code(holes).never_open_pixels == 1
    assert not check_code(holes * 2).binary
