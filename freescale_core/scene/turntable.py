"""A procedural turntable capture with object masks (tests and benchmarks for masks).

An object (three textured boxes, stacked) seen by cameras on a full circle around it, as a
turntable capture's poses are: the object is fixed in the world, the camera goes round. The
background does not belong to that world: in a real turntable capture it stands still while
the object turns, so relative to the object it turns too. Here every image gets its own
background (a window of a panorama that moves with the frame index); only the object is
3D-consistent. Each image has an exact object mask (the pixel-centre ray hits the object;
rendered without supersampling, so mask and colour agree pixel for pixel).

Written as a COLMAP scene (``images/``, ``masks/``, ``sparse/0`` with exact sparse points on
the object) or a nerfstudio one (``transforms.json`` with ``mask_path``), atomically. The
object's description goes to ``turntable.json`` (not ``scene.json``: the sample-scene oracle
would render the object on its sky, which is not the captured background).
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Literal

import numpy as np

from freescale_core.geometry.cameras import Cameras, look_at
from freescale_core.scene.sample import (
    BoxSpec,
    CameraSpec,
    FrameSpec,
    RenderSpec,
    SampleWorld,
    SceneSpec,
    _encode_png,
    _load_photo,
    _replace_dir,
    _texture_spec,
    sparse_points,
    write_colmap_text,
)

MaskNaming = Literal["same", "stem_png", "name_png"]


def turntable_layout(seed: int = 0) -> SceneSpec:
    """Three boxes stacked around the origin (about 1 m across), no ground, no walls."""
    rng = np.random.default_rng([seed, 10])
    yaw = rng.uniform(-20.0, 20.0, 3)
    boxes = [
        BoxSpec(name="base", center=(0.0, 0.0, 0.25), half_size=(0.45, 0.35, 0.25),
                yaw_deg=float(yaw[0]), side_texture="coffee", top_texture="colorwheel"),
        BoxSpec(name="mid", center=(0.05, -0.02, 0.7), half_size=(0.25, 0.25, 0.2),
                yaw_deg=float(35.0 + yaw[1]), side_texture="chelsea", top_texture="coins"),
        BoxSpec(name="top", center=(-0.02, 0.04, 1.0), half_size=(0.12, 0.16, 0.1),
                yaw_deg=float(70.0 + yaw[2]), side_texture="camera", top_texture="moon"),
    ]
    used = sorted({b.side_texture for b in boxes} | {b.top_texture for b in boxes})
    return SceneSpec(seed=seed, render=RenderSpec(supersample=1, texture_size=128),
                     textures=[_texture_spec(n) for n in used], quads=[], boxes=boxes)


def turntable_path(n_views: int = 24, width: int = 96, height: int = 72,
                   seed: int = 0) -> Cameras:
    """``n_views`` cameras on a full circle (radius 2.1 m, 1.4 m high) looking at the object,
    with a little height and aim jitter; ``fx = fy = 0.9 width``."""
    rng = np.random.default_rng([seed, 11])
    a = np.linspace(0.0, 2 * np.pi, n_views, endpoint=False) + rng.uniform(-0.05, 0.05, n_views)
    eye = np.stack([2.1 * np.cos(a), 2.1 * np.sin(a), 1.4 + rng.uniform(-0.1, 0.1, n_views)], -1)
    target = np.array([0.0, 0.0, 0.5]) + rng.uniform(-0.04, 0.04, (n_views, 3))
    wfc = look_at(eye, target, np.array([0.0, 0.0, 1.0]))
    f = 0.9 * width
    return Cameras(wfc, f, f, width / 2.0, height / 2.0, width, height)


def backgrounds(n_views: int, width: int, height: int, seed: int = 0) -> np.ndarray:
    """``[N, H, W, 3]`` uint8: a window of a panorama (two photos side by side) that moves
    by ``2 W / N`` per frame, tinted per frame: a background that changes in every image."""
    import cv2

    rng = np.random.default_rng([seed, 12])
    parts = [cv2.resize(np.ascontiguousarray(_load_photo(p)[..., :3]),
                        (3 * width // 2, height), interpolation=cv2.INTER_AREA)
             for p in ("astronaut", "chelsea")]
    pano = np.concatenate(parts, axis=1)
    out = np.empty((n_views, height, width, 3), np.uint8)
    for i in range(n_views):
        x0 = int(round(i * 2 * width / n_views))
        tint = rng.uniform(0.6, 1.0, 3)
        out[i] = np.clip(pano[:, x0:x0 + width] * tint, 0, 255).astype(np.uint8)
    return out


def _mask_name(name: str, naming: MaskNaming) -> str:
    stem = name.rsplit(".", 1)[0]
    return {"same": name, "stem_png": f"{stem}.png", "name_png": f"{name}.png"}[naming]


def render_turntable(spec: SceneSpec, cams: Cameras, seed: int = 0
                     ) -> tuple[np.ndarray, np.ndarray, SampleWorld]:
    """``(images [N, H, W, 3] uint8, masks [N, H, W] bool, world)`` of a capture."""
    world = SampleWorld(spec)
    n = len(cams)
    W, H = int(cams.width[0]), int(cams.height[0])
    bg = backgrounds(n, W, H, seed)
    imgs = np.empty((n, H, W, 3), np.uint8)
    masks = np.empty((n, H, W), bool)
    for i in range(n):
        rgb, depth = world.render_camera(cams, i)
        masks[i] = depth > 0
        imgs[i] = np.where(masks[i][..., None], rgb, bg[i])
    return imgs, masks, world


def turntable_spec(n_views: int = 24, width: int = 96, height: int = 72, seed: int = 0,
                   names: list[str] | None = None) -> SceneSpec:
    """The turntable's layout with its circle of ``n_views`` cameras as frames (``names``:
    image names, default ``frame_00000.png`` ...)."""
    cams = turntable_path(n_views, width, height, seed)
    names = names or [f"frame_{i:05d}.png" for i in range(n_views)]
    return turntable_layout(seed).model_copy(update=dict(
        camera=CameraSpec(width=width, height=height, fx=float(cams.fx[0]),
                          fy=float(cams.fy[0]), cx=float(cams.cx[0]), cy=float(cams.cy[0])),
        frames=[FrameSpec(image_id=i + 1, name=names[i],
                          world_from_cam=cams.world_from_cam[i].tolist())
                for i in range(n_views)]))


def write_turntable_scene(out_dir: str | Path, n_views: int = 24, width: int = 96,
                          height: int = 72, seed: int = 0, *,
                          fmt: Literal["colmap", "nerfstudio"] = "colmap",
                          masks: bool = True, mask_naming: MaskNaming = "same",
                          n_points: int = 600) -> Path:
    """Write a turntable capture (see the module docstring) to ``out_dir``, atomically.

    Args:
        fmt: ``colmap`` (``images/``, ``masks/``, ``sparse/0``) or ``nerfstudio``
            (``images/``, ``masks/``, ``transforms.json`` with ``mask_path`` per frame, no
            sparse points).
        masks: write the masks (False: the same capture without them).
        mask_naming: file name of the mask of ``frame_00000.png``: ``same``, ``stem_png``
            (``<stem>.png``) or ``name_png`` (``<name>.png``, COLMAP's convention).
        n_points: sparse points on the object (COLMAP), seen in >= 2 views.
    Returns:
        ``out_dir`` as a Path.
    """
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    names = [f"frame_{i:05d}.png" for i in range(n_views)]
    spec = turntable_spec(n_views, width, height, seed, names)
    imgs, m, world = render_turntable(spec, SampleWorld(spec).cameras, seed)
    cams = world.cameras
    tmp = out_dir.parent / f".{out_dir.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        (tmp / "images").mkdir(parents=True)
        for i in range(n_views):
            (tmp / "images" / names[i]).write_bytes(_encode_png(imgs[i]))
            if masks:
                mp = tmp / "masks" / _mask_name(names[i], mask_naming)
                mp.parent.mkdir(exist_ok=True)
                mp.write_bytes(_encode_grey(np.where(m[i], 255, 0).astype(np.uint8)))
        if fmt == "colmap":
            xyz, prgb, visible, uv = sparse_points(world, cams, n_points,
                                                   np.random.default_rng([seed, 2]))
            write_colmap_text(tmp / "sparse" / "0", cams, names, xyz, prgb, visible, uv)
        else:
            import pycolmap

            from freescale_core.scene.io.nerfstudio import transforms_dict

            cam = pycolmap.Camera(model="PINHOLE", width=width, height=height,
                                  params=np.array([cams.fx[0], cams.fy[0], cams.cx[0],
                                                   cams.cy[0]]))
            d = transforms_dict(names, cams.world_from_cam, [cam] * n_views)
            if masks:
                for fr, nm in zip(d["frames"], names):
                    fr["mask_path"] = f"masks/{_mask_name(nm, mask_naming)}"
            (tmp / "transforms.json").write_text(json.dumps(d, indent=1) + "\n")
        (tmp / "turntable.json").write_text(json.dumps(spec.model_dump(mode="json")) + "\n")
        _replace_dir(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def _encode_grey(m: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(m))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()
