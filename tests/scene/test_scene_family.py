"""The procedural scene family (freescale_core.scene.family, .textures).

Default config = classic scene byte for byte; determinism; diversity between seeds; every
capture path gives proper upright cameras that see the objects from free space; the oracle
re-renders family scenes (procedural textures included) exactly; off-path poses are away from
the capture and look at objects.
"""

from __future__ import annotations

import numpy as np
import pytest

from freescale_core.geometry.raycast import cast_pinhole
from freescale_core.scene.family import (
    off_path_poses,
    write_family_scene,
    PATH_KINDS,
    box_clearance,
    family_capture,
    family_layout,
    write_family,
)
from freescale_core.scene.sample import SampleWorld, SceneSpec, write_sample_scene
from freescale_core.scene.scene import read_rgb
from freescale_core.scene.textures import ProceduralTextureSpec, procedural_texture
from schemas.scene_family import SceneFamilyConfig
from tests.scene.test_sample_scene import _tree_digest

TINY = dict(n_views=6, width=64, height=48, n_points=150)
RANDOM = SceneFamilyConfig(layout="random", textures="mixed", path="any")


def _box_fraction(world: SampleWorld, T: np.ndarray, fx: float, W: int = 32, H: int = 24):
    """(share of pixels on an object, share hitting any surface) at a low resolution."""
    hits = cast_pinhole(world.quads, T, fx, fx, W / 2, H / 2, W, H, 0.01)
    return float((hits.quad >= len(world.spec.quads)).mean()), float((hits.quad >= 0).mean())


def test_default_config_is_the_classic_scene_byte_for_byte(tmp_path):
    a = write_sample_scene(tmp_path / "a", seed=3, **TINY)
    b = write_family_scene(tmp_path / "b", seed=3, family=SceneFamilyConfig(), **TINY)
    assert _tree_digest(a) == _tree_digest(b)
    assert family_layout(3) == family_layout(3, SceneFamilyConfig()) and \
        family_layout(3).family is None


def test_family_scene_is_deterministic_and_oracle_exact(tmp_path):
    cfg = SceneFamilyConfig(layout="random", textures="procedural", path="orbit")
    a = write_family_scene(tmp_path / "a", seed=5, family=cfg, **TINY)
    b = write_family_scene(tmp_path / "b", seed=5, family=cfg, **TINY)
    assert _tree_digest(a) == _tree_digest(b)
    world = SampleWorld.load(a)
    assert world.spec.family is not None and world.spec.family.path == "orbit"
    assert all(t.procedural is not None for t in world.spec.textures)
    for i in (0, 3):
        rgb, _ = world.render_camera(world.cameras, i)
        np.testing.assert_array_equal(rgb, read_rgb(a / "images" / world.image_names[i]))
    # the oracle refuses a scene whose procedural texture no longer matches its hash
    raw = world.spec.model_dump(mode="json")
    raw["textures"][0]["procedural"]["seed"] += 1
    with pytest.raises(ValueError, match="procedural texture differs"):
        SampleWorld.from_spec(SceneSpec.model_validate(raw))


def test_two_seeds_differ_substantially(tmp_path):
    imgs = {}
    for seed in (0, 1):
        d = write_family_scene(tmp_path / f"s{seed}", seed=seed, family=RANDOM, **TINY)
        imgs[seed] = np.stack([read_rgb(p) for p in sorted((d / "images").glob("*.png"))])
    diff = np.abs(imgs[0].astype(float) - imgs[1].astype(float)).mean()
    assert diff > 25.0, diff  # the classic scene's seeds differ far less (same layout/photos)
    spec0, spec1 = family_layout(0, RANDOM), family_layout(1, RANDOM)
    assert [b.center for b in spec0.boxes] != [b.center for b in spec1.boxes]


def test_layout_knobs_are_respected():
    cfg = SceneFamilyConfig(layout="random", n_boxes=(6, 6), box_half_size=(0.1, 0.2),
                            n_walls=(4, 4), room_half_size=(4.0, 4.0), stack_prob=0.0)
    spec = family_layout(2, cfg)
    assert len(spec.boxes) == 6
    assert all(0.1 <= h <= 0.2 for b in spec.boxes for h in b.half_size)
    assert sum(q.name.startswith("wall") for q in spec.quads) == 4
    assert all(b.center[2] == b.half_size[2] for b in spec.boxes)  # nothing stacked


@pytest.mark.parametrize("path", PATH_KINDS)
def test_every_path_gives_valid_cameras_looking_at_objects(path):
    cfg = SceneFamilyConfig(layout="random", path=path)
    for seed in (0, 7):
        spec = family_layout(seed, cfg)
        cams = family_capture(spec, cfg, 12, 64, 48, seed)
        R = cams.world_from_cam[:, :3, :3]
        np.testing.assert_allclose(np.einsum("nji,njk->nik", R, R),
                                   np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
        assert np.all(R[:, 2, 1] < -0.5)  # image down is world down: upright
        steps = np.linalg.norm(np.diff(cams.centers, axis=0), axis=1)
        assert steps.max() < 3 * np.median(steps) + 1e-6  # video-like, no jumps
        x0, x1, y0, y1 = spec.family.bounds
        c = cams.centers
        assert np.all((c[:, 0] >= x0 - 0.1) & (c[:, 0] <= x1 + 0.1)
                      & (c[:, 1] >= y0 - 0.1) & (c[:, 1] <= y1 + 0.1))
        assert box_clearance(c, spec).min() > 0.1  # never inside an object
        world = SampleWorld(spec)
        fr = np.array([_box_fraction(world, cams.world_from_cam[i], 0.8 * 32)
                       for i in range(len(cams))])
        assert np.median(fr[:, 0]) > 0.05, (path, seed, fr[:, 0])  # objects in view
        assert fr[:, 1].min() > 0.5  # mostly surfaces, not sky


def test_procedural_textures_tile_and_differ():
    seen = []
    for kind in ("noise", "checker", "stripes", "dots"):
        spec = ProceduralTextureSpec(kind=kind, frequency=4, octaves=3,
                                     colors=[(0.1, 0.2, 0.3), (0.9, 0.8, 0.2)], seed=1)
        t = procedural_texture(spec, 128).astype(float)
        np.testing.assert_array_equal(t, procedural_texture(spec, 128))
        assert t.std() > 10
        # seamless: the wrap-around step (both axes) is no larger than the largest step
        # between interior columns / rows (a checker's cell edges are such steps)
        for a in (0, 1):
            steps = np.abs(np.diff(t, axis=a)).mean(axis=(1 - a, 2))
            seam = np.abs(np.take(t, 0, axis=a) - np.take(t, -1, axis=a)).mean()
            assert seam <= steps.max() + 1.0, (kind, a, seam, steps.max())
        seen.append(t)
    assert all(np.abs(a - b).mean() > 5 for i, a in enumerate(seen) for b in seen[i + 1:])


def test_off_path_poses_are_new_and_see_objects(tmp_path):
    for cfg, seed in ((RANDOM, 4), (None, 0)):
        d = write_family_scene(tmp_path / f"s{seed}", seed=seed, family=cfg, **TINY)
        world = SampleWorld.load(d)
        cams = off_path_poses(world, 9, seed=1, min_distance=0.5)
        again = off_path_poses(world, 9, seed=1, min_distance=0.5)
        np.testing.assert_array_equal(cams.world_from_cam, again.world_from_cam)
        dist = np.linalg.norm(cams.centers[:, None] - world.cameras.centers[None], axis=2)
        assert dist.min() >= 0.5
        assert np.ptp(cams.centers[:, 2]) > 0.5  # other heights than a walking capture
        fr = np.array([_box_fraction(world, cams.world_from_cam[i], float(cams.fx[i]) / 2)
                       for i in range(len(cams))])
        assert np.all(fr[:, 0] > 0.02), fr[:, 0]
        rgb, depth = world.render_camera(cams, 0)
        assert rgb.shape == (48, 64, 3) and (depth > 0).mean() > 0.5


def test_write_family(tmp_path):
    dirs = write_family(tmp_path / "fam", 2, seed=10, n_views=5, width=32, height=24,
                        n_points=50)
    assert [d.name for d in dirs] == ["scene_0000", "scene_0001"]
    assert all(len(list((d / "images").glob("*.png"))) == 5 for d in dirs)
    assert SampleWorld.load(dirs[1]).spec.seed == 11
