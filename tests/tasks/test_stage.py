"""tasks.stage.run_stage: the checkpoint/status protocol behind resume."""

from __future__ import annotations

import pytest

from freescale_core.store.store import Store
from tasks import stage as stage_mod
from tasks.stage import run_stage


def _compute(calls):
    def compute(work):
        calls.append(1)
        (work / "out.txt").write_text("x")
        return ["out.txt"], {"n_things": 7, "note": "hello"}
    return compute


def test_cache_hit_skips_compute_and_keeps_counts(tmp_path):
    calls = []
    run_stage(str(tmp_path), "s", "grid", {"a": 1}, [], ("tasks.stage",), 0, _compute(calls))
    ref = run_stage(str(tmp_path), "s", "grid", {"a": 1}, [], ("tasks.stage",), 0, _compute(calls))
    assert len(calls) == 1 and ref.result["n_things"] == 7
    assert Store(tmp_path).read_status("s")["counts"]["n_things"] == 7
    run_stage(str(tmp_path), "s", "grid", {"a": 2}, [], ("tasks.stage",), 0, _compute(calls))
    assert len(calls) == 2  # another config: computed again


def test_killed_between_checkpoint_and_status_restores_counts(tmp_path, monkeypatch):
    """A SIGKILL after the checkpoint is written but before the status update must not lose the
    stage's counts: the next run takes the checkpoint and restores them (this was a real,
    timing-dependent failure of the flow's kill test)."""
    calls = []
    real_update = Store.update_status

    def dying_update(self, scene_id, **fields):
        if "counts" in fields:
            raise KeyboardInterrupt("killed")
        return real_update(self, scene_id, **fields)

    monkeypatch.setattr(Store, "update_status", dying_update)
    with pytest.raises(KeyboardInterrupt):
        run_stage(str(tmp_path), "s", "grid", {"a": 1}, [], ("tasks.stage",), 0, _compute(calls))
    monkeypatch.setattr(Store, "update_status", real_update)
    store = Store(tmp_path)
    assert store.stage_done("s", "grid", stage_mod.stage_key("grid", {"a": 1}, [],
                                                             ("tasks.stage",), 0)) is not None
    assert "n_things" not in store.read_status("s").get("counts", {})
    run_stage(str(tmp_path), "s", "grid", {"a": 1}, [], ("tasks.stage",), 0, _compute(calls))
    assert len(calls) == 1  # not recomputed
    st = store.read_status("s")
    assert st["counts"]["n_things"] == 7 and "grid" in st["seconds"]


def test_user_ply_takes_the_highest_iteration_numerically(tmp_path):
    from tasks.scene_tasks import user_ply

    for it in (7000, 30000, 500):
        d = tmp_path / "point_cloud" / f"iteration_{it}"
        d.mkdir(parents=True)
        (d / "point_cloud.ply").write_bytes(b"ply")
    assert user_ply(str(tmp_path)).parent.name == "iteration_30000"
    (tmp_path / "gaussians.ply").write_bytes(b"ply")
    assert user_ply(str(tmp_path)).name == "gaussians.ply"


def test_input_fingerprint_sees_edits_and_ignores_hidden(tmp_path):
    import os

    from freescale_core.scene.fingerprint import input_fingerprint

    (tmp_path / "images").mkdir()
    (tmp_path / "sparse").mkdir()
    img = tmp_path / "images" / "a.png"
    img.write_bytes(b"png")
    f = tmp_path / "sparse" / "images.txt"
    f.write_bytes(b"1234")
    fp0 = input_fingerprint(tmp_path)
    (tmp_path / ".freescale_cache").mkdir()
    (tmp_path / ".freescale_cache" / "x").write_bytes(b"cache")
    assert input_fingerprint(tmp_path) == fp0
    st = f.stat()
    f.write_bytes(b"4321")  # same size, same mtime: the content hash still sees it
    os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    fp1 = input_fingerprint(tmp_path)
    assert fp1 != fp0
    img.write_bytes(b"PNG!")  # an image: size changed
    assert input_fingerprint(tmp_path) != fp1


def test_input_fingerprint_hashes_image_content_and_caches_by_identity(tmp_path, monkeypatch):
    """An image edited in place with its size and mtime restored changes the fingerprint;
    an unchanged file is not read again (digest cached by size, mtime, ctime, inode)."""
    import os

    import freescale_core.scene.fingerprint as F

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    scene = tmp_path / "scene"
    (scene / "images").mkdir(parents=True)
    img = scene / "images" / "a.jpg"
    img.write_bytes(b"\xff\xd8" + b"x" * 2_000_000)  # 2 MB: above any "small file" limit
    fp0 = F.input_fingerprint(scene)
    st = img.stat()
    with open(img, "r+b") as f:  # same size, same inode
        f.seek(1000)
        f.write(b"y")
    os.utime(img, ns=(st.st_atime_ns, st.st_mtime_ns))  # same mtime
    assert img.stat().st_size == st.st_size and img.stat().st_mtime_ns == st.st_mtime_ns
    assert F.input_fingerprint(scene) != fp0
    calls = []
    real = F.file_digest
    monkeypatch.setattr(F, "file_digest", lambda p: calls.append(p) or real(p))
    F._MEMO.clear()  # a new process: the digests come from the on-disk cache
    fp1 = F.input_fingerprint(scene)
    assert calls == [] and F.input_fingerprint(scene) == fp1
