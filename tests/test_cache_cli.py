"""`codedvideo cache verify | clean` on a real cache: a damaged entry is reported (exit 1) and removed, others kept."""
import json

import numpy as np

from codedvideo.app.cli import main
from cli_inputs import reconstruct_args


def test_verify_reports_a_damaged_entry_and_clean_removes_only_it(files, tmp_path, capsys):
    cache = tmp_path / "cache"
    assert main(["-q", *map(str, reconstruct_args(files, tmp_path))]) == 0
    (cache / "notes.txt").write_text("not codedvideo's")
    capsys.readouterr()
    assert main(["cache", "verify", str(cache)]) == 0
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert records and {r["status"] for r in records} == {"ok"}
    store = next(cache.glob("recon-*.zarr"))
    chunk = next(p for p in (store / "volume").rglob("*") if p.is_file() and p.name != "zarr.json")
    data = bytearray(chunk.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte
    chunk.write_bytes(bytes(data))
    assert main(["cache", "verify", str(cache)]) == 1
    statuses = {json.loads(line)["entry"]: json.loads(line)["status"] for line in capsys.readouterr().out.splitlines()}
    assert statuses[str(store)] == "broken"
    assert main(["cache", "clean", "--broken", str(cache)]) == 0
    assert json.loads(capsys.readouterr().out)["removed"] == [str(store)]
    assert not store.exists() and (cache / "notes.txt").read_text() == "not codedvideo's"
    # the next run rebuilds the entry and gives the same answer as before
    first = np.load(tmp_path / "out" / "r.npy")
    assert main(["-q", *map(str, reconstruct_args(files, tmp_path))]) == 0
    np.testing.assert_array_equal(np.load(tmp_path / "out" / "r.npy"), first)


def test_clean_leaves_user_files_that_only_look_like_entries(tmp_path, capsys):
    """Reported: a user's JSON named like a report record, a folder named like an entry holding a user's file,
    and a user's Zarr store named like a dictionary entry were all removed by `cache clean`."""
    cache = tmp_path / "cache"
    (cache / "report").mkdir(parents=True)
    (cache / "report" / "0123456789abcdef.json").write_text('{"my": "results"}')
    (cache / "recon-0123456789abcdef.zarr").mkdir()
    (cache / "recon-0123456789abcdef.zarr" / "coded").write_text("my coded image")
    (cache / "dict-00000000000000ff.zarr").mkdir()
    (cache / "dict-00000000000000ff.zarr" / "zarr.json").write_text('{"note": 1}')
    (cache / "recon-00000000000000aa.zarr").mkdir()  # an entry emptied by hand: codedvideo's, removed
    for broken in ([], ["--broken"]):
        assert main(["-q", "cache", "clean", str(cache), *broken]) == 0
    assert (cache / "report" / "0123456789abcdef.json").read_text() == '{"my": "results"}'
    assert (cache / "recon-0123456789abcdef.zarr" / "coded").read_text() == "my coded image"
    assert (cache / "dict-00000000000000ff.zarr" / "zarr.json").exists()
    assert not (cache / "recon-00000000000000aa.zarr").exists()


def test_an_empty_cache_name_is_refused_not_the_current_folder(capsys):
    for command in ("verify", "clean"):
        assert main(["-q", "cache", command, ""]) == 2
        assert "name the cache folder" in capsys.readouterr().err


def test_clean_leaves_user_files_in_report_that_share_a_record_fields_or_name(tmp_path, capsys):
    """Reported: a user's JSON named like a record was removed when it shared one field with a record, and a
    lone .npy named like a volume was called broken and removed."""
    folder = tmp_path / "cache" / "report"
    folder.mkdir(parents=True)
    np.save(folder / "0123456789abcdef.npy", np.arange(10.0))
    mine = '{"scene": "my lab scene", "psnr": 31.2, "notes": "keep"}'
    (folder / "fedcba9876543210.json").write_text(mine)
    capsys.readouterr()
    assert main(["cache", "verify", str(tmp_path / "cache")]) == 0
    assert capsys.readouterr().out.strip() == ""  # neither is reported
    for broken in (["--broken"], []):
        assert main(["-q", "cache", "clean", str(tmp_path / "cache"), *broken]) == 0
    np.testing.assert_array_equal(np.load(folder / "0123456789abcdef.npy"), np.arange(10.0))
    assert (folder / "fedcba9876543210.json").read_text() == mine
    # a damaged record of ours (it names its own key) is still found, and removed with its volume
    (folder / "00000000000000aa.json").write_text('{"key": "00000000000000aa", "scene": "default", "psnr"')
    np.save(folder / "00000000000000aa.npy", np.zeros((2, 7, 7), np.float32))
    capsys.readouterr()
    assert main(["cache", "verify", str(tmp_path / "cache")]) == 1
    assert [json.loads(line)["status"] for line in capsys.readouterr().out.splitlines()] == ["broken"]
    assert main(["-q", "cache", "clean", "--broken", str(tmp_path / "cache")]) == 0
    assert sorted(p.name for p in folder.iterdir()) == ["0123456789abcdef.npy", "fedcba9876543210.json"]
