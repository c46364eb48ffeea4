"""The cache is safe to share and verified: concurrent runs on one entry, damaged chunks, verify and clean.

Real Zarr stores on disk, real processes (and a real dask.distributed cluster).
"""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zarr

from codedvideo.app.cli import main
from codedvideo.model.codes import make_code
from codedvideo.solvers.dictionaries import dct_dictionary
from codedvideo.model.physics import simulate
from codedvideo.engine.windows import Execution, reconstruct_volume
from codedvideo.solvers.region import OmpSettings
from codedvideo.data.synth import make_scene
from cli_inputs import fails, reconstruct_args

SETTINGS = dict(max_atoms=6, tol_rms=2.0)
TILE = 16  # a 48x48 scene: 3 x 3 tiles, one volume chunk each

# Each process runs REPS rounds; in round i both processes meet at a file barrier, then reconstruct
# (or train) on the fresh cache ROOT/cache-i at the same moment.  One JSON line per round on stdout.
WORKER = r"""
import json, sys, time, traceback
from pathlib import Path
import numpy as np
root, tag, reps, job = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
for i in range(reps):
    (root / f"ready-{i}-{tag}").touch()
    t0 = time.monotonic()
    while len(list(root.glob(f"ready-{i}-*"))) < 2 and time.monotonic() - t0 < 120:
        time.sleep(0.001)
    try:
        if job == "train":
            from codedvideo.engine.config import PipelineConfig
            from codedvideo.engine.training import train_dictionary
            from codedvideo.formats.store import load_dictionary
            cfg = PipelineConfig.model_validate(dict(frames=4, cache=str(root / f"cache-{i}"), dictionary=dict(
                kind="learned", atoms=60, samples=1500, iterations=2, sparsity=3, clips=3)))
            path, meta = train_dictionary(cfg, progress=False)
            np.save(root / f"{tag}-{i}.npy", load_dictionary(path)[0])
            row = dict(ok=True, computed=not meta["reused"])
        else:
            from codedvideo.engine.windows import Execution, reconstruct_volume
            from codedvideo.solvers.region import OmpSettings
            d = np.load(root / "scene.npz")
            run = Execution(tile=int(sys.argv[6]), cache=root / f"cache-{i}", workers=1, progress=False,
                            scheduler=sys.argv[7] or None)
            vol, info = reconstruct_volume(d["coded"], d["mask"], d["D"], settings=OmpSettings(**json.loads(sys.argv[5])),
                                           run=run)
            np.save(root / f"{tag}-{i}.npy", vol)
            row = dict(ok=True, computed=info["tiles_computed"])
    except Exception:
        row = dict(ok=False, error=traceback.format_exc())
    print(json.dumps(dict(row, rep=i)), flush=True)
"""


@pytest.fixture(scope="module")
def scene():
    video = make_scene("default", frames=4, size=(48, 48))
    mask = make_code("hitomi", (48, 48), frames=4, bump=2, rng=1)
    return simulate(video, mask, sigma=2.0, rng=3), mask, dct_dictionary(4)


@pytest.fixture(scope="module")
def reference(scene, tmp_path_factory):
    coded, mask, D = scene
    vol, info = reconstruct_volume(coded, mask, D, settings=OmpSettings(**SETTINGS),
                                   run=Execution(tile=TILE, cache=tmp_path_factory.mktemp("ref"), progress=False))
    assert info["tiles"] == 9 and info["tiles_computed"] == 9
    return vol


def _race(root: Path, job: str, reps: int, *extra: str, timeout: float = 600) -> tuple[list, list]:
    """Two processes, ``reps`` rounds each on a fresh cache per round; their JSON rows per round."""
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    procs = [subprocess.Popen([sys.executable, "-c", WORKER, str(root), tag, str(reps), job, *extra],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for tag in "ab"]
    outs = [p.communicate(timeout=timeout) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    rows = [[json.loads(line) for line in out.splitlines() if line.startswith("{")] for out, _ in outs]
    assert [len(r) for r in rows] == [reps, reps], outs
    return rows[0], rows[1]


def _reconstruct_race(root: Path, scene, reps: int, scheduler: str = "") -> tuple[list, list]:
    coded, mask, D = scene
    root.mkdir(parents=True, exist_ok=True)
    np.savez(root / "scene.npz", coded=coded, mask=mask, D=D)
    return _race(root, "reconstruct", reps, json.dumps(SETTINGS), str(TILE), scheduler)


def _check_race(root: Path, a: list, b: list, reference: np.ndarray, n_tiles: int = 9) -> None:
    failed = [row["error"] for row in a + b if not row["ok"]]
    assert not failed, failed[0]
    for i, (ra, rb) in enumerate(zip(a, b)):
        # one run computed every tile, the other waited for the entry and reused them all
        assert sorted([ra["computed"], rb["computed"]]) == [0, n_tiles], (i, ra, rb)
        for tag in "ab":
            np.testing.assert_array_equal(np.load(root / f"{tag}-{i}.npy"), reference, err_msg=f"round {i} run {tag}")
        entries = sorted(p.name for p in (root / f"cache-{i}").iterdir())
        assert len(entries) == 2 and entries[0].endswith(".lock") and entries[1].endswith(".zarr"), entries  # no debris


# ----------------------------------------------------------------------------- concurrent runs
def test_two_processes_on_one_cache_twenty_times_all_succeed_bit_identical(scene, reference, tmp_path):
    """20 rounds of two processes reconstructing the same inputs into the same fresh cache at the same moment."""
    a, b = _reconstruct_race(tmp_path, scene, reps=20)
    _check_race(tmp_path, a, b, reference)


def test_two_dask_clients_on_one_cache_and_one_cluster_both_succeed(scene, reference, tmp_path):
    """The same race with the tiles running on the worker processes of one dask.distributed cluster."""
    import distributed  # a pinned dependency: a broken install fails, never skips
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        a, b = _reconstruct_race(tmp_path, scene, reps=4, scheduler=cluster.scheduler_address)
    _check_race(tmp_path, a, b, reference)


def test_two_processes_training_the_same_dictionary_both_succeed_and_one_reuses(tmp_path):
    """Two trainers of one dictionary cache entry: neither crashes, one trains, the other reuses its result."""
    a, b = _race(tmp_path, "train", 8)
    failed = [row["error"] for row in a + b if not row["ok"]]
    assert not failed, failed[0]
    ref = np.load(tmp_path / "a-0.npy")
    for i, (ra, rb) in enumerate(zip(a, b)):
        assert sorted([ra["computed"], rb["computed"]]) == [False, True], (i, ra, rb)
        for tag in "ab":
            np.testing.assert_array_equal(np.load(tmp_path / f"{tag}-{i}.npy"), ref)


# ----------------------------------------------------------------------------- damaged tiles
def _entry(cache: Path) -> Path:
    (entry,) = cache.glob("recon-*.zarr")
    return entry


def _flip_bit(path: Path) -> None:
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))


CENTRE = "volume/c/0/1/1"  # tile 4's volume chunk
DAMAGE = {
    "bit-flipped": lambda e: _flip_bit(e / CENTRE),
    "copied-over": lambda e: shutil.copyfile(e / "volume/c/0/0/0", e / CENTRE),
    "truncated": lambda e: (e / CENTRE).write_bytes((e / CENTRE).read_bytes()[: (e / CENTRE).stat().st_size // 2]),
    "emptied": lambda e: (e / CENTRE).write_bytes(b""),
    "deleted": lambda e: (e / CENTRE).unlink(),
    # every chunk of tile 0 (volume, statistics and checksum) over tile 4's: the checksum names its tile
    "copied-with-its-checksum": lambda e: [shutil.copyfile(e / a, e / b) for a, b in (
        ("volume/c/0/0/0", CENTRE), ("stats/c/0/0", "stats/c/4/0"), ("digest/c/0/0", "digest/c/4/0"))
        if (e / a).exists()],
}


def test_a_tile_whose_checksum_was_deleted_is_counted_as_damaged(scene, reference, tmp_path, caplog):
    """Reported: recomputed without a word and not counted in tiles_damaged."""
    coded, mask, D = scene
    s = OmpSettings(**SETTINGS)
    reconstruct_volume(coded, mask, D, settings=s, run=Execution(tile=TILE, cache=tmp_path, progress=False))
    (_entry(tmp_path) / "digest/c/4/0").unlink()
    with caplog.at_level("WARNING"):
        again, info = reconstruct_volume(coded, mask, D, settings=s,
                                         run=Execution(tile=TILE, cache=tmp_path, progress=False))
    np.testing.assert_array_equal(again, reference)
    assert info["tiles_computed"] == 1 and info["tiles_damaged"] == 1
    assert "tiles [4]" in caplog.text and "damaged" in caplog.text


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_volume_chunk_is_recomputed_not_returned(scene, reference, tmp_path, damage):
    coded, mask, D = scene
    s = OmpSettings(**SETTINGS)
    reconstruct_volume(coded, mask, D, settings=s, run=Execution(tile=TILE, cache=tmp_path, progress=False))
    entry = _entry(tmp_path)
    DAMAGE[damage](entry)
    try:  # the damage is real: read as it is, the store no longer holds the answer
        as_stored = np.asarray(zarr.open_group(str(entry), mode="r")["volume"][:])
        assert not np.array_equal(as_stored, reference, equal_nan=True)
    except AssertionError:
        raise
    except Exception:
        pass  # zarr cannot even decode it
    again, info = reconstruct_volume(coded, mask, D, settings=s,
                                     run=Execution(tile=TILE, cache=tmp_path, progress=False))
    np.testing.assert_array_equal(again, reference)
    assert info["tiles_computed"] == 1 and info["tiles_reused"] == 8 and info["tiles_damaged"] == 1
    # repaired in place: the next run reuses every tile
    third, info = reconstruct_volume(coded, mask, D, settings=s,
                                     run=Execution(tile=TILE, cache=tmp_path, progress=False))
    np.testing.assert_array_equal(third, reference)
    assert info["tiles_computed"] == 0


def _rewrite(path: Path, data: bytes) -> None:
    path.write_bytes(data)


ENTRY_DAMAGE = {
    "volume-zarr.json-deleted": lambda e: (e / "volume/zarr.json").unlink(),
    "volume-zarr.json-truncated": lambda e: _rewrite(e / "volume/zarr.json", (e / "volume/zarr.json").read_bytes()[:40]),
    "volume-zarr.json-emptied": lambda e: _rewrite(e / "volume/zarr.json", b""),
    "coded-array-deleted": lambda e: shutil.rmtree(e / "coded"),  # "claims complete inputs but has no coded array"
    "mask-chunk-bit-flipped": lambda e: _flip_bit(e / "mask/c/0/1/1"),
    "coded-chunk-copied-over": lambda e: shutil.copyfile(e / "coded/c/0/0", e / "coded/c/1/1"),
}


@pytest.mark.parametrize("damage", list(ENTRY_DAMAGE))
def test_a_damaged_zarr_json_or_input_array_rebuilds_the_entry(scene, reference, tmp_path, damage):
    """The entry of a run stopped after tiles 0-3 is damaged: the rerun rebuilds it rather than computing
    the remaining tiles from damaged inputs (or failing on damaged metadata)."""
    coded, mask, D = scene
    s = OmpSettings(**SETTINGS)
    reconstruct_volume(coded, mask, D, settings=s, run=Execution(tile=TILE, cache=tmp_path, progress=False))
    entry = _entry(tmp_path)
    for i in range(4, 9):  # as if stopped after 4 tiles: tiles 4-8 were never finished
        for name in ("stats", "digest"):
            (entry / name / "c" / str(i) / "0").unlink(missing_ok=True)
    ENTRY_DAMAGE[damage](entry)
    again, info = reconstruct_volume(coded, mask, D, settings=s,
                                     run=Execution(tile=TILE, cache=tmp_path, progress=False))
    np.testing.assert_array_equal(again, reference)
    assert info["tiles_computed"] == info["tiles"] == 9  # rebuilt as a whole
    assert sorted(p.name.rsplit(".", 1)[1] for p in tmp_path.iterdir()) == ["lock", "zarr"]  # no debris


def test_a_dictionary_entry_copied_over_another_is_trained_again(tmp_path):
    """A dictionary cache entry replaced by another (intact, checksum and all) is not taken for this one."""
    from codedvideo.engine.config import PipelineConfig
    from codedvideo.engine.training import train_dictionary
    from codedvideo.formats.store import load_dictionary

    cfgs = [PipelineConfig.model_validate(dict(frames=n, cache=str(tmp_path), dictionary=dict(kind="dct")))
            for n in (4, 2)]
    (p4, _), (p2, _) = (train_dictionary(c, progress=False) for c in cfgs)
    shutil.rmtree(p4)
    shutil.copytree(p2, p4)
    path, meta = train_dictionary(cfgs[0], progress=False)
    assert not meta["reused"] and meta["frames"] == 4
    np.testing.assert_array_equal(load_dictionary(path)[0], dct_dictionary(4))


# ----------------------------------------------------------------------------- verify and clean
def test_verify_reports_a_damaged_entry_and_clean_removes_only_that_one(scene, reference, tmp_path):
    from codedvideo.engine.cache import clean_cache, verify_cache
    from codedvideo.engine.config import PipelineConfig
    from codedvideo.engine.training import train_dictionary

    coded, mask, D = scene
    cache = tmp_path / "cache"
    reconstruct_volume(coded, mask, D, settings=OmpSettings(**SETTINGS),
                       run=Execution(tile=TILE, cache=cache, progress=False))
    damaged = _entry(cache)
    _, info = reconstruct_volume(coded, mask, D, settings=OmpSettings(max_atoms=4, tol_rms=2.0),
                                 run=Execution(tile=TILE, cache=cache, progress=False))
    healthy = Path(info["work_store"])
    dictionary, _ = train_dictionary(PipelineConfig.model_validate(dict(frames=4, cache=str(cache),
                                                                        dictionary=dict(kind="dct"))), progress=False)
    (cache / "report").mkdir()
    (cache / "report" / "0123456789abcdef.json").write_text(json.dumps(dict(
        key="0123456789abcdef", scene="default", frames=8, code="hitomi", bump=2, sigma=0.0, method="omp", psnr=30.0,
        ssim=0.9, seconds=1.0)))
    # the user's own things in the cache folder, some named like entries: never reported, never removed
    mine = [cache / "notes.txt", cache / "mine", cache / "recon-0123456789abcdef.zarr", cache / "dict-0123456789abcdef.zarr"]
    mine[0].write_text("mine")
    mine[1].mkdir()
    mine[2].mkdir()
    (mine[2] / "holiday.jpg").write_bytes(b"\xff\xd8")
    mine[3].write_text("a file, not a store")
    _flip_bit(damaged / CENTRE)

    report = {Path(r["entry"]): r for r in verify_cache(cache)}
    assert set(report) == {damaged, healthy, dictionary, cache / "report" / "0123456789abcdef.json"}, report
    assert report[damaged]["status"] == "broken" and "[4]" in report[damaged]["detail"], report[damaged]
    assert report[damaged]["kind"] == "reconstruction"
    assert {report[p]["status"] for p in (healthy, dictionary, cache / "report" / "0123456789abcdef.json")} == {"ok"}
    assert (report[dictionary]["kind"], report[cache / "report" / "0123456789abcdef.json"]["kind"]) == ("dictionary", "report")

    assert clean_cache(cache, broken_only=True) == [damaged]
    assert not damaged.exists() and healthy.exists() and dictionary.exists()
    assert all(p.exists() for p in mine)
    assert {r["status"] for r in verify_cache(cache)} == {"ok"}
    _, info = reconstruct_volume(coded, mask, D, settings=OmpSettings(max_atoms=4, tol_rms=2.0),
                                 run=Execution(tile=TILE, cache=cache, progress=False))
    assert info["tiles_computed"] == 0  # the healthy entry still serves

    removed = clean_cache(cache, broken_only=False)
    assert set(removed) == {healthy, dictionary, cache / "report" / "0123456789abcdef.json"}
    assert sorted(p.name for p in cache.iterdir()) == sorted(["notes.txt", "mine", "recon-0123456789abcdef.zarr",
                                                              "dict-0123456789abcdef.zarr", "report"])
    assert (mine[2] / "holiday.jpg").exists()


def test_verify_calls_an_entry_of_an_older_layout_stale_and_clean_removes_it(scene, tmp_path):
    """An entry written by another codedvideo version (here: the layout version changed) is never reused."""
    from codedvideo.engine.cache import clean_cache, verify_cache

    coded, mask, D = scene
    reconstruct_volume(coded, mask, D, settings=OmpSettings(**SETTINGS),
                       run=Execution(tile=TILE, cache=tmp_path, progress=False))
    entry = _entry(tmp_path)
    zarr.open_group(str(entry), mode="r+").attrs["format_version"] = 1
    (tmp_path / f".{entry.name}.tmp-12345-0123abcd").mkdir()  # what a run killed while creating it leaves
    (record, tmp) = sorted(verify_cache(tmp_path), key=lambda r: r["kind"])
    assert (record["entry"], record["status"]) == (str(entry), "stale")
    assert (tmp["kind"], tmp["status"]) == ("temporary", "leftover")
    assert sorted(clean_cache(tmp_path, broken_only=True)) == sorted([entry, tmp_path / f".{entry.name}.tmp-12345-0123abcd"])
    assert list(tmp_path.iterdir()) == []


def test_tile_tasks_share_an_opened_store_until_the_entry_is_rebuilt(scene, tmp_path):
    """WorkStore.opened hands the tasks of a process one opened store per entry; an entry rebuilt under the
    same name (other inputs) is opened afresh, so no task reads a stale layout."""
    from codedvideo.formats.store import WorkStore

    coded, mask, _ = scene
    path = tmp_path / "recon-x.zarr"
    made = WorkStore.create(path, coded, mask, tile=TILE, n_stats=7, n_tiles=9, attrs=dict(key="a"))
    assert WorkStore.opened(path) is made and WorkStore.opened(str(path)) is made
    shutil.rmtree(path)
    small = WorkStore.create(path, coded[:40, :40], mask[:, :40, :40], tile=TILE, n_stats=7, n_tiles=4,
                             attrs=dict(key="b"))
    again = WorkStore.opened(path)
    assert again is small and again is not made
    assert again.read_inputs(0, 40, 0, 40)[0].shape == (40, 40)
    np.testing.assert_array_equal(again.read_inputs(0, 40, 0, 40)[1], mask[:, :40, :40])


def test_a_dictionary_trained_on_a_video_is_keyed_by_what_the_video_holds(tmp_path):
    """The same name with other frames trains again; the same frames under another name reuse the entry."""
    from codedvideo.formats import io as cio
    from codedvideo.engine.config import PipelineConfig
    from codedvideo.engine.training import train_dictionary
    from codedvideo.formats.store import load_dictionary
    from codedvideo.data.synth import make_scene

    def train(video):
        cfg = PipelineConfig.model_validate(dict(frames=4, cache=str(tmp_path / "cache"), dictionary=dict(
            kind="learned", atoms=40, samples=800, iterations=1, sparsity=3, training=[str(video)])))
        path, meta = train_dictionary(cfg, progress=False)
        return load_dictionary(path)[0], meta["reused"]

    first, second = make_scene("default", frames=24, size=(40, 40)), make_scene("coins-translate", frames=24,
                                                                                 size=(40, 40))
    clip = cio.write_video(tmp_path / "clip.mkv", first)
    d1, reused = train(clip)
    assert not reused
    cio.write_video(clip, second)  # new frames, same name
    d2, reused = train(clip)
    assert not reused and not np.array_equal(d1, d2)
    (tmp_path / "elsewhere").mkdir()
    d3, reused = train(shutil.copy(clip, tmp_path / "elsewhere" / "renamed.mkv"))
    assert reused and np.array_equal(d2, d3)


# ----------------------------------------------------------------------------- a budget for working stores
def test_sizes_are_read_in_powers_of_1024_and_anything_else_is_refused():
    from codedvideo.engine.cache import parse_size

    assert [parse_size(t) for t in ("0", "123", "500M", "20G", "1.5T", "2GiB", ".5k", 7)] == [
        0, 123, 500 * 2**20, 20 * 2**30, int(1.5 * 2**40), 2 * 2**30, 512, 7]
    for bad in ("-1", "12X", "", "nan", "G", "20i", "5bk", float("inf"), -3):
        with pytest.raises(ValueError):
            parse_size(bad)


def _stores(tmp_path, count):
    """``count`` working stores of distinct 48x48 captures in one cache, made one after another."""
    from codedvideo.engine.windows import Execution, sparse_volumes

    video = make_scene("default", frames=4 * count, size=(48, 48))
    mask = make_code("hitomi", video.shape[1:], frames=4, bump=2, rng=1)
    codeds = [simulate(video[4 * t : 4 * t + 4], mask, sigma=1.0, rng=t) for t in range(count)]
    out = []
    for t in range(count):  # a job each: their stores are used in this order
        out += list(sparse_volumes(1, lambda _, t=t: (codeds[t], mask, None), dct_dictionary(4),
                                   settings=OmpSettings(**SETTINGS),
                                   run=Execution(tile=TILE, cache=tmp_path / "c", progress=False)))
    return codeds, mask, [Path(info["work_store"]) for _, _, info in out]


def test_a_cache_budget_removes_the_least_recently_used_stores_and_never_one_in_use(tmp_path):
    """Four stores and a budget for one and a half: the oldest go first, a store another run holds (or this
    job still uses) stays however old it is, and the dictionaries beside them are never touched."""
    from codedvideo.engine.cache import CacheBudget, _folder_bytes
    from codedvideo.formats.store import entry_lock

    _, _, stores = _stores(tmp_path, 4)
    (tmp_path / "c" / "dict-0123456789abcdef.zarr").mkdir()  # (not a working store: never sized nor removed)
    size = _folder_bytes(stores[0])
    budget = CacheBudget(tmp_path / "c", size + size // 2)
    assert set(budget.sizes) == set(stores) and budget.total() >= 4 * size * 0.9
    # the oldest is in use by "another run", the newest by this job (each lock a file of its own)
    with entry_lock(stores[0]) as held0, entry_lock(stores[3]) as held3:
        assert held0 and held3
        removed = budget.finished([stores[3]])
    assert removed == [stores[1], stores[2]]  # the oldest not in use, then the next; the two in use stay
    assert stores[0].is_dir() and stores[3].is_dir() and not stores[1].exists() and not stores[2].exists()
    assert (tmp_path / "c" / "dict-0123456789abcdef.zarr").is_dir()
    assert budget.total() > budget.budget  # (over it while they are in use)
    assert budget.finished([]) == [stores[0]]  # let go of: the oldest goes, and the rest fits
    assert budget.total() <= budget.budget and stores[3].is_dir()


def test_a_stream_within_a_cache_budget_gives_the_same_bits_and_reruns_from_what_is_left(tmp_path, monkeypatch):
    """Six captures in windows of one with a budget of about two stores: the result is bit for bit the
    unlimited job's, the cache stays within the budget, and a rerun computes again what was removed (least
    recently used first: in a rerun that is the stores it is about to reach) to the same bits."""
    from codedvideo.engine import windows
    from codedvideo.engine.cache import _folder_bytes

    codeds, mask, stores = _stores(tmp_path, 6)  # the unlimited job, capture by capture
    unlimited = [np.asarray(v) for _, v, _ in windows.sparse_volumes(6, lambda i: (codeds[i], mask, None),
                                                                     dct_dictionary(4),
                                                                     settings=OmpSettings(**SETTINGS),
                                                                     run=Execution(tile=TILE, cache=tmp_path / "c",
                                                                                   progress=False))]
    size = _folder_bytes(stores[0])
    monkeypatch.setattr(windows, "WINDOW_TILES", 1)
    bounded = tmp_path / "bounded"

    def job():
        from codedvideo.engine.cache import CacheBudget

        budget = CacheBudget(bounded, 2 * size + size // 2)
        got = list(windows.sparse_volumes(6, lambda i: (codeds[i], mask, None), dct_dictionary(4),
                                          settings=OmpSettings(**SETTINGS),
                                          run=Execution(tile=TILE, cache=bounded, progress=False), budget=budget))
        return got, budget

    first, budget = job()
    for (_, got, info), want in zip(first, unlimited):
        np.testing.assert_array_equal(got, want)
    assert len(budget.removed) == 4 and budget.total() <= budget.budget
    assert sum(_folder_bytes(p) for p in bounded.glob("recon-*.zarr")) <= budget.budget
    again, budget = job()
    assert budget.total() <= budget.budget
    for (_, got, _), want in zip(again, unlimited):
        np.testing.assert_array_equal(got, want)


def test_a_cache_budget_that_is_not_a_size_is_one_line_before_any_work(tmp_path):
    rng = np.random.default_rng(0)
    np.save(tmp_path / "coded.npy", rng.uniform(0, 255, (2, 16, 16)).astype(np.float32))
    np.save(tmp_path / "mask.npy", (rng.random((2, 16, 16)) < 0.5).astype(np.uint8))
    proc = subprocess.run([sys.executable, "-m", "codedvideo.app.cli", "-q", "reconstruct", "--coded",
                           str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"), "--output",
                           str(tmp_path / "r.npy"), "--cache", str(tmp_path / "c"), "--cache-budget", "20X"],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "--cache-budget" in proc.stderr and "20X" in proc.stderr
    assert not (tmp_path / "r.npy").exists() and not (tmp_path / "c").exists()


def test_a_job_whose_stores_may_not_fit_the_disk_is_said_before_any_work(tmp_path, monkeypatch):
    """The working stores a stream will make, against the free space under the cache: one warning line naming
    the cache, the sizes and --cache-budget before the job starts; with a budget that fits, none."""
    import shutil as sh
    from collections import namedtuple

    from codedvideo.app.cli import main

    rng = np.random.default_rng(0)
    np.save(tmp_path / "coded.npy", rng.uniform(0, 255, (4, 16, 16)).astype(np.float32))
    np.save(tmp_path / "mask.npy", (rng.random((2, 16, 16)) < 0.5).astype(np.uint8))
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(sh, "disk_usage", lambda path: usage(10**9, 10**9 - 12000, 12000))  # 12000 bytes free
    args = ["reconstruct", "--coded", str(tmp_path / "coded.npy"), "--mask", str(tmp_path / "mask.npy"),
            "--method", "dct", "--cache", str(tmp_path / "c")]
    import warnings

    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        assert main(["-q", *args, "--output", str(tmp_path / "a.npy")]) == 0
    said = [str(w.message) for w in said if "free" in str(w.message)]
    assert len(said) == 1 and "--cache-budget" in said[0] and str(tmp_path / "c") in said[0]
    assert "about 15 KiB (4 stores of about 3.8 KiB)" in said[0] and "12 KiB free" in said[0]
    # a budget counts what a job holds at once: the budget and the stores in use beside it
    from codedvideo.engine.cache import cache_room_problem

    assert cache_room_problem(tmp_path / "c", 1000, 2, 16, 16, None) is not None
    assert cache_room_problem(tmp_path / "c", 1000, 2, 16, 16, 1, in_use=3) is None  # 1 B + 3 x 3840 B
    assert cache_room_problem(tmp_path / "c", 1000, 2, 16, 16, 1, in_use=4) is not None
    monkeypatch.setattr(sh, "disk_usage", lambda path: usage(10**9, 0, 10**9))
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        assert main(["-q", *args, "--output", str(tmp_path / "b.npy")]) == 0
    assert not [w for w in said if "free" in str(w.message)]


def test_cache_verify_of_a_file_says_it_is_not_a_folder(tmp_path, capsys):
    (tmp_path / "f").write_text("x")
    capsys.readouterr()
    assert main(["-q", "cache", "verify", str(tmp_path / "f")]) == 2
    assert "not a folder" in capsys.readouterr().err


def _one_store(files, tmp_path):
    assert main(["-q", *map(str, reconstruct_args(files, tmp_path))]) == 0
    stores = list((tmp_path / "cache").glob("recon-*.zarr"))
    assert len(stores) == 1
    return stores[0]


def test_cache_verify_counts_a_finished_tile_whose_digest_was_deleted_as_damaged(files, tmp_path, capsys):
    store = _one_store(files, tmp_path)
    chunks = sorted(p for p in (store / "digest").rglob("*") if p.is_file() and p.name != "zarr.json")
    assert chunks  # one chunk a tile
    chunks[0].unlink()
    capsys.readouterr()
    assert main(["cache", "verify", str(tmp_path / "cache")]) == 1
    record = json.loads(capsys.readouterr().out.splitlines()[0])
    assert record["entry"] == str(store) and record["status"] == "broken", record
    assert "digest" in record["detail"], record


def test_a_tile_never_computed_is_still_partial_not_damaged(files, tmp_path, capsys):
    """The other side: a tile with neither its results nor its digest (a job stopped before it) is work left."""
    store = _one_store(files, tmp_path)
    for name in ("digest", "stats"):
        chunks = sorted(p for p in (store / name).rglob("*") if p.is_file() and p.name != "zarr.json")
        chunks[0].unlink()
    capsys.readouterr()
    assert main(["cache", "verify", str(tmp_path / "cache")]) == 0
    assert json.loads(capsys.readouterr().out.splitlines()[0])["status"] == "partial"


def test_tiles_that_fail_their_checksum_are_a_codedvideo_warning_line(files, tmp_path):
    """Run as a process: the lines the command prints to stderr (pytest's own log handler hides them in-process)."""
    store = _one_store(files, tmp_path)
    chunk = next(p for p in sorted((store / "volume").rglob("*")) if p.is_file() and p.name != "zarr.json")
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF
    chunk.write_bytes(bytes(data))
    proc = subprocess.run([sys.executable, "-m", "codedvideo.app.cli", "-q", *map(str, reconstruct_args(files, tmp_path))],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if "computing them again" in line]
    assert lines and all(line.startswith("codedvideo: warning: cache entry ") for line in lines), proc.stderr


def test_a_cache_budget_of_0_is_refused(files, tmp_path, capsys):
    for value in ("0", "0M", "0.0G"):
        err = fails(capsys, [*reconstruct_args(files, tmp_path), "--cache-budget", value], "--cache-budget", value,
                    root=tmp_path)
        assert "> 0" in err or "greater than 0" in err, err
    cfg = tmp_path / "p.yaml"
    cfg.write_text(f"reconstruct: {{cache_budget: 0}}\noutput: {{dir: {tmp_path / 'out'}}}\ncache: {tmp_path / 'c'}\n")
    fails(capsys, ["run", cfg], "reconstruct.cache_budget", root=tmp_path)


def test_a_tiles_misfit_map_is_checked_with_it(tmp_path):
    # the non-local method's tiles carry the misfit their projection took away; a changed misfit fails the digest
    from codedvideo.formats.store import WorkStore, write_tiles

    rng = np.random.default_rng(0)
    coded = rng.random((TILE, TILE)).astype(np.float32)
    mask = (rng.random((4, TILE, TILE)) < 0.5).astype(np.uint8)
    store = WorkStore.create(tmp_path / "s.zarr", coded, mask, tile=TILE, n_stats=7, n_tiles=1, attrs=dict(key="a"))
    (tile,) = store.tiles()
    volume, stats = rng.random((4, TILE, TILE)).astype(np.float32), np.arange(7.0)
    misfit = rng.normal(0, 1, (TILE, TILE)).astype(np.float32)
    write_tiles([(store, tile.index, tile.core)], volume, stats, misfit)
    ok, damaged, read, _, found = store.read_verified([tile])
    assert ok.all() and np.array_equal(found, misfit) and np.array_equal(read, volume)
    store.array("misfit")[0, 0] = misfit[0, 0] + 1
    ok, damaged, *_ = store.read_verified([tile])
    assert not ok.any() and damaged.all()
