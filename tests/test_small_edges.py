"""The smaller edges of issue 29: a finished tile whose digest is gone is damaged to `cache verify`, the cache's
"computing them again" lines are warnings like the others, a cache budget of 0 and a `stages:` list with
duplicates or out of pipeline order are refused in one line before any work.
"""
import json
import subprocess
import sys

import pytest

from codedvideo.app.cli import main
from cli_inputs import fails, reconstruct_args


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


@pytest.mark.parametrize("stages,names", [
    ("[simulate, reconstruct, reconstruct]", ["stages", "reconstruct", "twice"]),
    ("[train, train]", ["stages", "train", "twice"]),
    ("[evaluate, reconstruct, simulate]", ["stages", "order", "train, simulate, reconstruct, evaluate"]),
    ("[reconstruct, train]", ["stages", "order"]),
])
def test_stages_with_duplicates_or_out_of_pipeline_order_are_refused(tmp_path, capsys, stages, names):
    cfg = tmp_path / "p.yaml"
    cfg.write_text(f"stages: {stages}\noutput: {{dir: {tmp_path / 'out'}}}\ncache: {tmp_path / 'c'}\n")
    fails(capsys, ["run", cfg], "p.yaml", *names, root=tmp_path)
