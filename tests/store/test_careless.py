"""Careless use of the store, the shards and the exports: nothing outside what a command owns
is deleted, bad paths give one line naming them (issue: nothing lost, nothing stale)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from freescale_core.errors import StoreError
from freescale_core.exports import export
from freescale_core.store.shards import pack, read_manifest, verify

REPO = Path(__file__).resolve().parents[2]
R = 16


def _cli(*args, **kw):
    return subprocess.run([sys.executable, "-m", "flows.cli", *map(str, args)], cwd=REPO,
                          capture_output=True, text=True,
                          env=dict(os.environ, PYTHONPATH=str(REPO), COLUMNS="200"), **kw)


@pytest.fixture
def store_copy(dataset_store, tmp_path) -> Path:
    """A writable copy of the sample store (sample_a only)."""
    dst = tmp_path / "data" / "store"
    shutil.copytree(dataset_store, dst, ignore=shutil.ignore_patterns("_work"))
    for d in (dst / "scenes").iterdir():
        if d.name != "sample_a":
            shutil.rmtree(d)
    return dst


# --------------------------------------------------------------------------- export
@pytest.mark.parametrize("where", ["store", "parent", "inside"])
def test_export_overwrite_never_deletes_a_store(store_copy, where):
    out = {"store": store_copy, "parent": store_copy.parent,
           "inside": store_copy / "scenes" / "sample_a"}[where]
    n_before = sum(1 for _ in store_copy.rglob("*"))
    with pytest.raises(StoreError, match="store"):
        export("colmap", store_copy, out, overwrite=True)
    assert sum(1 for _ in store_copy.rglob("*")) == n_before


def test_export_overwrite_never_deletes_shards(store_copy, tmp_path):
    sh = tmp_path / "sh"
    pack(store_copy, sh, resolution=R)
    for out in (sh, sh / "shards", tmp_path):
        with pytest.raises(StoreError, match="shards folder|store"):
            export("colmap", store_copy, out, overwrite=True)
    assert verify(sh) == []


def test_cli_export_overwrite_on_the_store_is_one_line(store_copy):
    p = _cli("export", "colmap", store_copy, store_copy.parent, "--overwrite")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.strip().count("\n") == 0 and "holds the store" in p.stderr
    assert (store_copy / "scenes" / "sample_a" / "CURRENT").is_file()


def test_export_under_a_file_is_one_line(store_copy, tmp_path):
    f = tmp_path / "afile"
    f.write_text("x")
    p = _cli("export", "colmap", store_copy, f / "out")
    assert p.returncode == 2 and "Traceback" not in p.stderr and str(f) in p.stderr


# --------------------------------------------------------------------------- shards pack
def test_pack_never_deletes_a_users_folder(store_copy, tmp_path):
    out = tmp_path / "sh"
    (out / "shards" / "my_photos").mkdir(parents=True)
    (out / "shards" / "my_photos" / "a.jpg").write_bytes(b"jpeg")
    (out / "shards" / "000077.zarr").mkdir()  # a user's folder with a shard-like name
    pack(store_copy, out, resolution=R)
    assert (out / "shards" / "my_photos" / "a.jpg").read_bytes() == b"jpeg"
    assert (out / "shards" / "000077.zarr").is_dir()
    assert verify(out) == []


def test_same_scene_from_two_stores_keeps_both_rows(store_copy, tmp_path):
    other = tmp_path / "other" / "store"
    shutil.copytree(store_copy, other)
    out = tmp_path / "sh"
    pack(store_copy, out, resolution=R)
    pack(other, out, resolution=R)
    rows = read_manifest(out).to_pylist()
    assert sorted((r["source_store"], r["scene_id"]) for r in rows) == sorted(
        [(str(store_copy), "sample_a"), (str(other), "sample_a")])
    assert verify(out) == []


@pytest.mark.parametrize("what", ["missing", "file", "not_a_store"])
def test_pack_from_a_non_store_is_an_error(tmp_path, what):
    src = tmp_path / "src"
    if what == "file":
        src.write_text("x")
    elif what == "not_a_store":
        (src / "photos").mkdir(parents=True)
    p = _cli("shards", "pack", src, tmp_path / "out")
    assert p.returncode == 2 and "Traceback" not in p.stderr and str(src) in p.stderr, p.stderr
    assert "packed 0" not in p.stdout


def test_pack_into_the_store_is_refused(store_copy):
    p = _cli("shards", "pack", store_copy, store_copy)
    assert p.returncode == 2 and "Traceback" not in p.stderr and "store" in p.stderr, p.stderr
    assert not (store_copy / "shards").exists()


def test_pack_scenes_twice_packs_once(store_copy, tmp_path):
    res = pack(store_copy, tmp_path / "sh", scenes=["sample_a", "sample_a"], resolution=R)
    assert res.packed == ["sample_a"] and read_manifest(tmp_path / "sh").num_rows == 1


def test_pack_on_a_full_disk_is_one_line(store_copy, tmp_path, monkeypatch):
    import freescale_core.store.shards as S

    def full(path, scenes, R):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(S, "write_shard", full)
    with pytest.raises(StoreError, match="No space left"):
        pack(store_copy, tmp_path / "sh", resolution=R)
    assert not [p for p in (tmp_path / "sh" / "shards").iterdir()]


# --------------------------------------------------------------------------- reads verify
@pytest.fixture
def packed(store_copy, tmp_path) -> Path:
    out = tmp_path / "sh"
    pack(store_copy, out, resolution=R)
    return out


def _chunks(out: Path) -> list[Path]:
    return sorted(p for p in (out / "shards" / "000000.zarr" / "images").rglob("*")
                  if p.is_file() and p.name != "zarr.json")


def _fresh_process_cache():
    import freescale_core.store.dataset as D

    D._VERIFIED.clear()


@pytest.mark.parametrize("damage", ["flip", "delete", "pose"])
def test_a_damaged_shard_fails_naming_it(packed, damage):
    from freescale_core.store.dataset import ShardDataset

    _fresh_process_cache()
    if damage == "pose":
        c = sorted(p for p in (packed / "shards" / "000000.zarr" / "world_from_cam").rglob("*")
                   if p.is_file() and p.name != "zarr.json")[0]
    else:
        c = _chunks(packed)[3]
    if damage == "delete":
        c.unlink()
    else:
        b = bytearray(c.read_bytes())
        b[len(b) // 2] ^= 0xFF
        c.write_bytes(bytes(b))
    ds = ShardDataset(packed, seed=0, samples_per_scene=4)
    with pytest.raises(StoreError, match="000000.zarr does not match its SHA-256"):
        ds[0]
    p = _cli("shards", "verify", packed)
    assert p.returncode == 1 and "000000.zarr" in p.stderr and "Traceback" not in p.stderr


def test_shards_verify_passes_a_healthy_folder(packed):
    p = _cli("shards", "verify", packed)
    assert p.returncode == 0 and "1 of 1 shard(s) match" in p.stdout, p.stderr


def test_a_truncated_chunk_unverified_is_one_error_naming_the_shard(packed):
    from freescale_core.store.dataset import ShardDataset

    for c in _chunks(packed):
        c.write_bytes(c.read_bytes()[:5])
    ds = ShardDataset(packed, seed=0, samples_per_scene=4, verify=False)
    with pytest.raises(StoreError, match="000000.zarr cannot be read"):
        ds[0]


# --------------------------------------------------------------------------- owned bytes
def test_versions_and_exports_own_their_bytes(dataset_store, tmp_path):
    """A published version holds copies of the user's photos (never hard links), and an
    export copies the version's files: editing an exported image in place changes neither
    the version nor the capture."""
    from freescale_core.store.store import Store

    vdir = Store(dataset_store).current_version_dir("sample_a")
    imgs = sorted((vdir / "images").iterdir())
    assert imgs and all(p.stat().st_nlink == 1 for p in imgs)
    src = Path(json_source(vdir))
    out = tmp_path / "exp"
    export("colmap", dataset_store, out, scenes=["sample_a"])
    exported = sorted((out / "sample_a" / "images").iterdir())
    assert all(p.stat().st_nlink == 1 for p in exported)
    before = {p.name: p.read_bytes() for p in imgs}
    originals = {p.name: p.read_bytes() for p in (src / "images").iterdir()}
    with open(exported[0], "r+b") as f:
        f.seek(10)
        f.write(b"EDITED")
    assert {p.name: p.read_bytes() for p in imgs} == before
    assert {p.name: p.read_bytes() for p in (src / "images").iterdir()} == originals


def json_source(vdir: Path) -> str:
    """The scene folder a version was published from (its status' ``source``)."""
    import json

    return json.loads((vdir.parent / "status.json").read_text())["source"]


def test_own_copy_is_a_separate_file(tmp_path):
    from freescale_core.store.store import own_copy

    a = tmp_path / "a.png"
    a.write_bytes(b"abc")
    own_copy(a, tmp_path / "x" / "b.png")
    (tmp_path / "x" / "b.png").write_bytes(b"zzz")
    assert a.read_bytes() == b"abc" and a.stat().st_nlink == 1


@pytest.fixture
def small_tmpfs(tmp_path):
    """A real 64 kB tmpfs (a full disk); skipped where mounting is not permitted."""
    d = tmp_path / "full"
    d.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(d)],
                      capture_output=True).returncode != 0:
        pytest.skip("cannot mount a tmpfs here (needs root)")
    yield d
    subprocess.run(["umount", str(d)], capture_output=True)


def test_cli_pack_on_a_real_full_disk_is_one_line(store_copy, small_tmpfs):
    """zarr's abandoned chunk writes no longer print 'Task was destroyed' / 'Event loop is
    closed' tracebacks after the error line."""
    p = _cli("shards", "pack", store_copy, small_tmpfs / "sh", "--resolution", 64)
    assert p.returncode == 2 and "No space left on device" in p.stderr, p.stderr
    assert "Traceback" not in p.stderr and p.stderr.strip().count("\n") == 0, p.stderr
