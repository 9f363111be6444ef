"""Inputs behind symbolic links: read through the link, published and exported as bytes.

A scene may keep its photos behind symbolic links (``ln -s ~/photos/*.jpg scene/images/``),
wherever they point. The published version and every export hold a copy of the bytes, never
a link: moving or deleting the link's target later changes nothing published.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from freescale_core.scene.sample import write_sample_scene


@pytest.fixture
def linked_scene(tmp_path) -> tuple[Path, Path]:
    """The sample scene whose first image is a symbolic link to a file outside the scene
    folder; returns (scene folder, the link's target)."""
    scene = tmp_path / "scene"
    write_sample_scene(scene, n_views=8, width=48, height=36, seed=0)
    outside = tmp_path / "photos"
    outside.mkdir()
    img = sorted((scene / "images").iterdir())[0]
    target = outside / img.name
    shutil.move(img, target)
    os.symlink(target, img)
    return scene, target


def test_a_symlinked_image_outside_the_scene_is_published_as_bytes(linked_scene, tmp_path):
    """The version's copy of a linked image is a regular file with the target's bytes and
    stays readable once the target is gone (before: a copy of the link, left dangling)."""
    from freescale_core.scene.io import load_scene
    from freescale_core.store.layout import write_training_inputs

    scene_dir, target = linked_scene
    scene = load_scene(scene_dir, cache_dir=tmp_path / "cache")
    want = target.read_bytes()
    out = tmp_path / "v0001"
    write_training_inputs(out, scene)
    got = out / "images" / target.name
    assert not got.is_symlink() and got.stat().st_nlink == 1
    target.unlink()
    assert got.read_bytes() == want


def test_an_export_of_a_linked_file_holds_its_bytes(tmp_path):
    """The exports' one copy function follows a link (before: it copied the link)."""
    from freescale_core.exports.common import link_or_copy

    target = tmp_path / "elsewhere" / "a.png"
    target.parent.mkdir()
    target.write_bytes(b"\x89PNG bytes")
    link = tmp_path / "v" / "a.png"
    link.parent.mkdir()
    os.symlink(target, link)
    link_or_copy(link, tmp_path / "export" / "a.png")
    target.unlink()
    assert not (tmp_path / "export" / "a.png").is_symlink()
    assert (tmp_path / "export" / "a.png").read_bytes() == b"\x89PNG bytes"


def test_images_in_a_symlinked_folder_are_listed_and_a_loop_is_not_followed(tmp_path):
    """A folder of images behind a link counts like any other (before: skipped, so a folder
    scene lost those images and a COLMAP scene named them 'missing on disk'); a link back up
    to an ancestor is not walked."""
    from freescale_core.scene.io.common import list_images

    (tmp_path / "photos" / "day2").mkdir(parents=True)
    (tmp_path / "photos" / "day2" / "b.png").write_bytes(b"x")
    images = tmp_path / "scene" / "images"
    images.mkdir(parents=True)
    (images / "a.png").write_bytes(b"x")
    os.symlink(tmp_path / "photos" / "day2", images / "day2")
    os.symlink(images, images / "day2_again_loop")  # a loop back to images/
    (images / ".hidden").mkdir()
    (images / ".hidden" / "c.png").write_bytes(b"x")
    assert list_images(images) == ["a.png", "day2/b.png"]
    assert list_images(images, recursive=False) == ["a.png"]


def test_editing_a_linked_images_target_changes_the_input_fingerprint(linked_scene):
    from freescale_core.scene.fingerprint import input_fingerprint

    scene_dir, target = linked_scene
    before = input_fingerprint(scene_dir)
    b = bytearray(target.read_bytes())
    b[-20] ^= 0xFF
    target.write_bytes(bytes(b))
    assert input_fingerprint(scene_dir) != before
