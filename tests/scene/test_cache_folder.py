"""The atomic cache folder: concurrent builders of the same key never swap files under a reader."""

from __future__ import annotations

from pathlib import Path

from freescale_core.scene.io.common import build_cached_folder, read_manifest


def _writer(tag: str):
    def build(tmp: Path) -> dict:
        (tmp / "images").mkdir()
        (tmp / "images" / "a.jpg").write_text(tag)
        return {"files": ["images/a.jpg"]}
    return build


def test_same_key_installed_meanwhile_is_kept(tmp_path):
    """A second builder that finishes after the first installed the same key keeps the first
    folder: a process reading it (the first builder's caller) must not see it deleted."""
    target = tmp_path / "undistorted"
    held = {}

    def slow_build(tmp: Path) -> dict:
        # while this copy is being written, another process builds and installs the same key
        m, reused = build_cached_folder(target, "k", _writer("first"))
        held["manifest"], held["reused"] = m, reused
        held["inode"] = (target / "images" / "a.jpg").stat().st_ino
        return _writer("second")(tmp)

    m, reused = build_cached_folder(target, "k", slow_build)
    assert held["reused"] is False
    assert reused is True, "the later builder must take the installed folder, not replace it"
    assert (target / "images" / "a.jpg").read_text() == "first"
    assert (target / "images" / "a.jpg").stat().st_ino == held["inode"]
    assert m["files"] == ["images/a.jpg"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "temporaries left"


def test_stale_key_is_replaced_and_cleaned(tmp_path):
    target = tmp_path / "undistorted"
    build_cached_folder(target, "old", _writer("old"))
    m, reused = build_cached_folder(target, "new", _writer("new"))
    assert reused is False and read_manifest(target, "new") is not None
    assert (target / "images" / "a.jpg").read_text() == "new"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], "stale copy left"
