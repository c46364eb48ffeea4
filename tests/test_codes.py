import json

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from codedvideo.model.codes import bump_starts, check_code, make_code, window_coverage
from codedvideo.model.errors import InputError


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


# ----------------------------------------------------------------------------- every scheme
from typing import get_args  # noqa: E402

from codedvideo.model.codes import CODE_NAMES, grid_code, row_starts, thinout_code  # noqa: E402
from codedvideo.formats.volumes import load_code_file  # noqa: E402

BUILT = [n for n in CODE_NAMES if n != "file"]
RANDOM = ("hitomi", "hitomi-tiled", "rowwise", "flutter", "bernoulli", "shifting")

#: (single_bump, fixed_bump, bump_length, window_coverage) at N = 8, L = 2 on 30 x 33
EXPECTED = {
    "hitomi": (True, True, 2, True),
    "hitomi-tiled": (True, True, 2, True),
    "rowwise": (True, True, 2, True),
    "thinout": (True, True, 1, False),  # 7 rows cannot cover N = 8
    "grid": (True, True, 1, True),  # n = 3
    "global": (True, True, 8, True),
}


@pytest.mark.parametrize("name", BUILT)
def test_every_code_is_binary_uint8_and_seeded(name):
    a = make_code(name, (30, 33), frames=8, bump=2, p=0.4, rng=11)
    assert a.shape == (8, 30, 33) and a.dtype == np.uint8 and a.flags.c_contiguous
    assert np.isin(a, (0, 1)).all()
    assert np.array_equal(a, make_code(name, (30, 33), frames=8, bump=2, p=0.4, rng=11))
    gen = make_code(name, (30, 33), frames=8, bump=2, p=0.4, rng=np.random.default_rng(11))
    assert np.array_equal(a, gen)  # a seed and a generator built from it agree
    other = make_code(name, (30, 33), frames=16, bump=2, p=0.4, rng=12)[:8]
    b = make_code(name, (30, 33), frames=16, bump=2, p=0.4, rng=11)[:8]
    if name in RANDOM:
        assert not np.array_equal(b, other), "a different seed must give a different code"
    else:
        assert np.array_equal(b, other), "deterministic codes ignore the seed"


@pytest.mark.parametrize("name", BUILT)
def test_check_code_reports_the_documented_constraints(name):
    mask = make_code(name, (30, 33), frames=8, bump=2, rng=3)
    rep = check_code(mask)
    assert rep.binary and rep.frames == 8 and rep.patch == 7
    assert rep.window_coverage == (rep.uncovered_windows == 0)
    assert 0 < rep.open_fraction <= 1
    if name in EXPECTED:
        assert (rep.single_bump, rep.fixed_bump, rep.bump_length, rep.window_coverage) == EXPECTED[name]
        assert rep.never_open_pixels == 0
    else:  # flutter, bernoulli, shifting: several bumps per pixel
        assert not rep.single_bump and not rep.fixed_bump and rep.bump_length is None
    if name == "flutter":
        assert not rep.window_coverage and rep.uncovered_windows == (30 - 6) * (33 - 6)
    d = rep.as_dict()
    assert {"binary", "single_bump", "fixed_bump", "window_coverage", "never_open_pixels"} <= set(d)


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 40), w=st.integers(1, 12), frames=st.integers(1, 30), bump=st.integers(1, 10),
       seed=st.integers(0, 2**31))
def test_rowwise_one_bump_per_row_and_seven_rows_cover(h, w, frames, bump, seed):
    bump = min(bump, frames)
    mask = make_code("rowwise", (h, w), frames=frames, bump=bump, rng=seed)
    assert (mask == mask[:, :, :1]).all(), "every pixel of a row shares its row's bump"
    rows = mask[:, :, 0]  # (N, H)
    assert (rows.sum(0) == bump).all()
    rep = check_code(mask[:, :, :1])
    assert rep.single_bump and rep.fixed_bump and rep.bump_length == bump
    if 7 * bump >= frames:
        for y in range(max(h - 6, 0)):
            assert rows[:, y : y + 7].any(1).all(), f"rows {y}..{y + 6} miss a sub-frame"
    starts = row_starts(h, frames=frames, bump=bump, rng=seed)
    assert starts.min() >= 0 and starts.max() <= frames - bump


def test_rowwise_is_random_not_periodic():
    s = row_starts(400, frames=16, bump=4, rng=1)
    assert (s[7:] != s[:-7]).mean() > 0.3
    assert check_code(make_code("rowwise", (40, 40), frames=36, bump=6, rng=2)).window_coverage


@settings(max_examples=30, deadline=None)
@given(h=st.integers(1, 30), w=st.integers(1, 9), frames=st.integers(1, 20))
def test_thinout_reads_row_y_in_subframe_y_mod_n(h, w, frames):
    mask = thinout_code((h, w), frames=frames)
    assert (mask.sum(0) == 1).all(), "every pixel open exactly one sub-frame"
    y = np.arange(h)
    assert (mask[y % frames, y, :] == 1).all()
    if h >= 7 and w >= 7:
        assert check_code(mask).window_coverage == (frames <= 7)


@settings(max_examples=30, deadline=None)
@given(frames=st.integers(1, 64), oy=st.integers(0, 8), ox=st.integers(0, 8))
def test_grid_every_cell_covers_all_subframes(frames, oy, ox):
    n = int(np.ceil(np.sqrt(frames)))
    mask = grid_code((2 * n + 9, 2 * n + 9), frames=frames)
    assert (mask.sum(0) == 1).all()
    cell = mask[:, oy : oy + n, ox : ox + n]  # any n x n window, aligned or not
    assert cell.any((1, 2)).all()
    yy, xx = np.mgrid[0 : mask.shape[1], 0 : mask.shape[2]]
    k = (yy % n) * n + (xx % n)
    assert (mask.argmax(0) == k % frames).all()
    assert check_code(mask).window_coverage == (n <= 7)


def test_grid_examples():
    m = make_code("grid", (6, 6), frames=4)  # n = 2: a 2x2 Bayer-like tiling
    assert m[:, 0, 0].argmax() == 0 and m[:, 0, 1].argmax() == 1 and m[:, 1, 0].argmax() == 2
    assert m[:, 1, 1].argmax() == 3 and m[:, 2, 2].argmax() == 0
    m = make_code("grid", (6, 6), frames=5)  # n = 3, positions 5..8 reuse sub-frames 0..3
    assert [m[:, 2, x].argmax() for x in range(3)] == [1, 2, 3]


@pytest.mark.parametrize("frames", [1, 2, 7, 16, 33])
def test_flutter_is_global_and_half_open(frames):
    mask = make_code("flutter", (9, 10), frames=frames, rng=frames)
    seq = mask[:, 0, 0]
    assert (mask == seq[:, None, None]).all(), "the same sequence for every pixel"
    assert seq.sum() == (frames + 1) // 2 >= 1


def test_flutter_sequences_vary_with_the_seed():
    seqs = {tuple(make_code("flutter", (1, 1), frames=12, rng=s)[:, 0, 0]) for s in range(20)}
    assert len(seqs) > 10


@settings(max_examples=20, deadline=None)
@given(p=st.floats(0.05, 1.0), seed=st.integers(0, 2**31))
def test_shifting_is_one_pattern_shifted_along_x(p, seed):
    mask = make_code("shifting", (12, 15), frames=6, p=p, rng=seed)
    for t in range(6):
        assert np.array_equal(mask[t], np.roll(mask[0], t, axis=1))


@pytest.mark.parametrize("name", ["bernoulli", "shifting"])
def test_bernoulli_codes_open_fraction_and_p_check(name):
    mask = make_code(name, (200, 200), frames=4, p=0.3, rng=0)
    assert abs(mask.mean() - 0.3) < 0.01
    with pytest.raises(InputError, match=f"code {name}: p"):
        make_code(name, (8, 8), frames=4, p=0.0)


def test_file_code_npy_and_tiff(tmp_path):
    from codedvideo.formats.io import write_multipage_tiff

    mask = make_code("hitomi", (20, 24), frames=8, bump=2, rng=4)
    np.save(tmp_path / "m.npy", mask)
    write_multipage_tiff(tmp_path / "m.tif", mask * 255)  # a mask image: open at the image's full scale
    for path in (tmp_path / "m.npy", tmp_path / "m.tif"):
        got = load_code_file(path, frames=8, shape=(20, 24))
        assert got.dtype == np.uint8 and np.array_equal(got, mask)
        assert np.array_equal(load_code_file(path), mask)
    with pytest.raises(InputError, match=r"m\.npy.*N = 8.*N = 4"):
        load_code_file(tmp_path / "m.npy", frames=4)
    with pytest.raises(InputError, match=r"m\.tif.*\(20, 24\).*\(20, 20\)"):
        load_code_file(tmp_path / "m.tif", frames=8, shape=(20, 20))
    np.save(tmp_path / "bad.npy", mask * 3)
    with pytest.raises(InputError, match=r"bad\.npy.*outside \[0, 1\]"):
        load_code_file(tmp_path / "bad.npy")
    with pytest.raises(InputError, match=r"missing\.npy"):
        load_code_file(tmp_path / "missing.npy")
    with pytest.raises(InputError, match="code file: a mask file is read by"):
        make_code("file", (20, 24), frames=8)


def test_unknown_code_and_bad_bump():
    with pytest.raises(InputError, match="unknown code 'zigzag'"):
        make_code("zigzag", (8, 8), frames=4)
    with pytest.raises(InputError, match="bump length"):
        make_code("rowwise", (8, 8), frames=4, bump=5)


def test_check_code_counts_uncovered_windows():
    mask = make_code("hitomi", (20, 20), frames=8, bump=2, rng=0)
    assert check_code(mask).uncovered_windows == 0
    mask[:, 10, 10] = 0
    mask[:, 10:12, 10:12] = 0
    rep = check_code(mask)
    assert rep.never_open_pixels == 4
    # knock out every pixel open in sub-frame 0 inside one 7x7 window
    m2 = make_code("hitomi", (7, 7), frames=8, bump=2, rng=0)
    m2[:, m2[0] == 1] = 0
    rep2 = check_code(m2)
    assert not rep2.window_coverage and rep2.uncovered_windows == 1


def test_names_are_selectable_everywhere():
    from codedvideo.app.cli import _parser
    from codedvideo.engine.config import CodeConfig, CodeName

    assert set(get_args(CodeName)) == set(CODE_NAMES)
    sim = next(a for a in _parser()._subparsers._group_actions[0].choices["simulate"]._actions if a.dest == "code")
    assert tuple(sim.choices) == CODE_NAMES
    assert CodeConfig(name="file", path="m.npy").path == "m.npy"
    with pytest.raises(ValueError, match="code.path"):
        CodeConfig(name="file")
    with pytest.raises(ValueError, match="only used with name: file"):
        CodeConfig(name="grid", path="m.npy")


def test_codes_check_reads_the_per_capture_masks_simulate_writes(tmp_path, capsys):
    """simulate --new-code-per-capture writes (T, N, H, W): codes check reports every capture (it refused it)."""
    import json

    from codedvideo.app.cli import main

    assert main(["-q", "simulate", "synth:default", "--frames", "8", "--size", "32", "32", "--captures", "3",
                 "--new-code-per-capture", "--output", str(tmp_path / "cap")]) == 0
    capsys.readouterr()
    assert main(["codes", "check", str(tmp_path / "cap" / "mask.npy")]) == 0
    report = json.loads(capsys.readouterr().out)
    masks = np.load(tmp_path / "cap" / "mask.npy")
    assert report["captures"] == 3 and len(report["per_capture"]) == 3
    assert report["single_bump"] and report["fixed_bump"] and report["window_coverage"]
    assert [r["open_fraction"] for r in report["per_capture"]] == [float(m.mean()) for m in masks]


def test_codes_check_reads_a_calibrated_mask_with_leakage_by_its_openings(tmp_path, capsys):
    """Reported: a hitomi L = 2 mask measured with 2 % leakage was called a global shutter (bump length 8)."""
    from codedvideo.app.cli import main

    code = make_code("hitomi", (32, 32), frames=8, bump=2, rng=0).astype(np.float32)
    rep = check_code(code * 0.9 + 0.02)
    assert not rep.binary and rep.single_bump and rep.fixed_bump and rep.bump_length == 2
    assert rep.window_coverage and rep.never_open_pixels == 0 and rep.open_threshold == pytest.approx(0.46)
    # one code per capture with different bump lengths: not one fixed bump
    np.save(tmp_path / "m.npy", np.stack([make_code("hitomi", (32, 32), frames=8, bump=2, rng=0),
                                         make_code("hitomi", (32, 32), frames=8, bump=3, rng=1)]))
    capsys.readouterr()
    assert main(["codes", "check", str(tmp_path / "m.npy")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [c["bump_length"] for c in out["per_capture"]] == [2, 3]
    assert out["fixed_bump"] is False and out["bump_length"] is None and out["single_bump"] is True


def test_codes_check_has_no_coverage_verdict_for_a_mask_smaller_than_a_window():
    rep = check_code(make_code("hitomi", (7, 3), frames=8, bump=2, rng=0))
    assert rep.window_coverage is None and rep.uncovered_windows is None  # it said "true" (and "false" for 1x1)
