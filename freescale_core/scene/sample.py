"""The embedded sample scene: a procedural, textured courtyard with an exact oracle.

What it is: a small outdoor-corner / tabletop scene made only of textured rectangles
(:mod:`freescale_core.geometry.raycast`): a 14 m x 14 m ground plane (tiled gravel), a brick back
wall and a side wall (2.2 m high, tiled brick / grass), two photo "posters" on the walls and
five boxes (one stacked, all yawed) whose faces carry photos bundled with scikit-image
(``coffee``, ``chelsea``, ``astronaut``, ``camera``, ``immunohistochemistry``, ``coins``...,
read from the package's own PNG files, never downloaded). Shading is Lambertian under a fixed
directional light plus ambient, i.e. view-independent, so a 3D Gaussian Splatting fit can
reproduce it; pixels whose ray misses every surface show a sky gradient that depends only on
the ray's world elevation.

Units and frames: world units are metres (boxes 0.25-1.2 m, walls 2.2 m, camera height
~1.5 m, camera-to-scene distance 3-4.4 m), world +z is up, the ground is ``z = 0``. Cameras
use the project's conventions (:mod:`freescale_core.geometry.cameras`: OpenCV axes,
``world_from_cam``, pixel centres at ``i + 0.5``).

The capture: ``n_views`` frames along a smooth, handheld-like arc (about 76 degrees around
the scene while walking from 4.3 m to 3.1 m towards it, gentle height bob and small
position / aim / roll jitter), ordered like video frames (capture order = file order), which
is what a DL3DV capture looks like to the engine. On disk it is a normal scene folder:
``images/frame_00000.png ...``, a COLMAP text model in ``sparse/0`` (one PINHOLE camera,
poses, and sparse points with consistent tracks: points are sampled where pixel rays hit
the scene and kept if exactly visible, by ray casting, in >= 2 views), and ``scene.json``,
the full description from which :class:`SampleWorld` rebuilds the scene.

What the oracle is for: :meth:`SampleWorld.render` renders the *true* image and depth at
any pose and intrinsics exactly as the training images were made (same supersampling, same
filtering; re-rendering a training pose reproduces its PNG bit for bit). This turns the
engine's free views (METHOD.md stages 3-9) from "plausible" into "measurable": the true
error (PSNR, depth error) of a free view rendered from the reconstruction can be computed
against ground truth, and quality filters can be checked against it.

Scene family: ``family.write_family_scene(..., family=SceneFamilyConfig(...))`` draws other layouts,
procedural textures, rooms and capture paths (:mod:`freescale_core.scene.family`); the default
config is this scene byte for byte. :func:`family.off_path_poses` gives evaluation
cameras the capture never visited.

Rendering: 2 x 2 supersampling (box filter) for colour, trilinear mip-mapped textures;
depth is the camera-frame z of the hit through the exact pixel centre (not averaged), and
``0.0`` where the ray hits nothing (sky). Surfaces are one-sided: a camera inside a box sees
through its walls.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from freescale_core.geometry.cameras import Cameras, cam_from_world_to_colmap, invert_pose, look_at
from freescale_core.errors import MissingInputError, SceneError, ShapeError
from freescale_core.geometry.raycast import Quads, TextureBank, box_faces, cast_pinhole, cast_rays
from freescale_core.scene.textures import ProceduralTextureSpec, procedural_texture

SCENE_FORMAT = "freescale-sample-scene"
SCENE_VERSION = 1
# Rays (sub-samples) per rendering band: bounds the oracle's memory for large images
# (~30 float64 arrays of this length); bands are bit-identical to a one-shot render.
RENDER_BAND_SAMPLES = 1 << 18

Vec3 = tuple[float, float, float]
Vec2 = tuple[float, float]

# Texture catalogue: name -> (skimage.data function, RGB tint). Only PNG files that ship
# inside scikit-image are used (no pooch download, and no JPEG whose decoding could vary).
TEXTURE_CATALOGUE: dict[str, tuple[str, Vec3]] = {
    "gravel": ("gravel", (0.85, 0.80, 0.72)),
    "brick": ("brick", (0.95, 0.62, 0.48)),
    "grass": ("grass", (0.55, 0.80, 0.45)),
    "astronaut": ("astronaut", (1.0, 1.0, 1.0)),
    "coffee": ("coffee", (1.0, 1.0, 1.0)),
    "chelsea": ("chelsea", (1.0, 1.0, 1.0)),
    "ihc": ("immunohistochemistry", (1.0, 1.0, 1.0)),
    "camera": ("camera", (0.80, 0.85, 1.0)),
    "coins": ("coins", (1.0, 0.90, 0.70)),
    "moon": ("moon", (0.90, 0.90, 0.95)),
    "colorwheel": ("colorwheel", (1.0, 1.0, 1.0)),
}


# --------------------------------------------------------------------------- spec (scene.json)
class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class TextureSpec(_Spec):
    """One texture: a scikit-image sample photo, centre-cropped square, tinted; or (scene
    family) a procedural texture, then ``source`` is ``"procedural"`` and ``source_sha256``
    hashes the generated uint8 image."""

    name: str = Field(description="Name the quads refer to.")
    source: str = Field(description="Function of skimage.data that returns the photo.")
    tint: Vec3 = Field((1.0, 1.0, 1.0), description="RGB multiplier (grey photos become RGB).")
    source_sha256: str = Field(description="SHA-256 of the uint8 photo as skimage returns it.")
    procedural: ProceduralTextureSpec | None = Field(
        None, exclude_if=lambda v: v is None,
        description="Procedural texture (freescale_core.scene.textures); None = photo.")


class QuadSpec(_Spec):
    """A one-sided textured rectangle (see :class:`freescale_core.geometry.raycast.Quads`)."""

    name: str
    center: Vec3 = Field(description="Centre, metres (world).")
    right: Vec3 = Field(description="Unit in-plane axis, texture +u.")
    up: Vec3 = Field(description="Unit in-plane axis, texture -v; normal = right x up.")
    half_size: Vec2 = Field(description="Half sizes along right and up, metres.")
    texture: str
    period: Vec2 = Field(description="Metres per texture copy along right and up.")
    wrap: bool = Field(True, description="Repeat (True) or clamp (False) the texture.")


class BoxSpec(_Spec):
    """A box standing upright, yawed about +z; every face shows its photo once."""

    name: str
    center: Vec3 = Field(description="Centre, metres (world).")
    half_size: Vec3 = Field(description="Half extents along the box's x, y, z, metres.")
    yaw_deg: float = Field(description="Rotation about world +z, degrees.")
    side_texture: str
    top_texture: str


class RenderSpec(_Spec):
    """How images are made (the oracle must use the same)."""

    supersample: int = Field(2, ge=1, description="Colour samples per pixel per axis (box filter).")
    near: float = Field(0.01, gt=0, description="Hits closer than this camera z (m) are ignored.")
    texture_size: int = Field(256, description="Square texture side in texels (power of two).")
    ambient: float = Field(0.45, ge=0, le=1, description="Ambient share of Lambertian shading.")
    light_dir: Vec3 = Field((0.35, -0.6, 1.0), description="Direction towards the light (world).")
    sky_horizon: Vec3 = (0.80, 0.85, 0.90)
    sky_zenith: Vec3 = (0.35, 0.55, 0.85)
    below_horizon: Vec3 = (0.55, 0.55, 0.52)
    miss_depth: float = Field(0.0, description="Depth written where a ray hits nothing.")
    # failure families (issue 16); the defaults leave scene.json and the images unchanged
    exposure: float = Field(1.0, gt=0, exclude_if=lambda v: v == 1.0,
                            description="Every colour (surfaces and sky) times this (dark: < 1).")
    specular: float = Field(0.0, ge=0, exclude_if=lambda v: v == 0.0,
                            description="Strength of a white Blinn-Phong highlight (view-dependent).")
    shininess: float = Field(24.0, gt=0, exclude_if=lambda v: v == 24.0,
                             description="Blinn-Phong exponent of the highlight.")


class CameraSpec(_Spec):
    """The one PINHOLE camera shared by all frames."""

    model: Literal["PINHOLE"] = "PINHOLE"
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float


class FrameSpec(_Spec):
    """One captured frame."""

    image_id: int = Field(description="COLMAP IMAGE_ID (1-based, capture order).")
    name: str = Field(description="Image file name under images/.")
    world_from_cam: list[list[float]] = Field(description="4x4 pose, OpenCV camera axes.")


class FamilyInfo(_Spec):
    """Where a scene of the family (:mod:`freescale_core.scene.family`) keeps its content and
    where cameras may stand (used to draw off-path evaluation poses)."""

    layout: str = Field(description="Layout generator ('classic' | 'random').")
    path: str = Field(description="Capture path kind ('arc' | 'walkthrough' | 'forward' | "
                      "'orbit').")
    content_center: Vec3 = Field(description="Centre of the objects, metres.")
    content_radius: float = Field(description="Horizontal radius holding every object, metres.")
    bounds: tuple[float, float, float, float] = Field(
        description="Camera region (xmin, xmax, ymin, ymax), metres: inside the walls.")


class SceneSpec(_Spec):
    """Everything in ``scene.json``: geometry, textures, rendering, camera path."""

    format: Literal["freescale-sample-scene"] = SCENE_FORMAT
    version: int = SCENE_VERSION
    seed: int
    units: str = "metres"
    up_axis: Vec3 = (0.0, 0.0, 1.0)
    render: RenderSpec = RenderSpec()
    textures: list[TextureSpec]
    quads: list[QuadSpec]
    boxes: list[BoxSpec]
    camera: CameraSpec | None = None
    frames: list[FrameSpec] = []
    n_points: int = Field(0, description="Number of sparse points in sparse/0/points3D.txt.")
    family: FamilyInfo | None = Field(
        None, exclude_if=lambda v: v is None,
        description="Scene-family metadata (None for the classic sample scene).")


# --------------------------------------------------------------------------- textures
@functools.lru_cache(maxsize=32)
def _load_photo(source: str) -> np.ndarray:
    """The uint8 photo ``skimage.data.<source>()`` (cached, read-only)."""
    import skimage.data

    fn = getattr(skimage.data, source, None)
    if fn is None:
        raise ValueError(f"skimage.data has no sample image {source!r}")
    img = np.asarray(fn())
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    img = np.ascontiguousarray(img.astype(np.uint8))
    img.setflags(write=False)
    return img


def _texture_from_photo(photo: np.ndarray, tint: Vec3, size: int) -> np.ndarray:
    """uint8 photo ``[h, w(, c)]`` -> float32 ``[size, size, 3]``: centre crop, resize, tint."""
    import cv2

    img = photo if photo.ndim == 3 else photo[..., None].repeat(3, axis=2)
    img = img[..., :3]
    h, w = img.shape[:2]
    s = min(h, w)
    y0, x0 = (h - s) // 2, (w - s) // 2
    img = np.ascontiguousarray(img[y0:y0 + s, x0:x0 + s])
    img = cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)
    return img.astype(np.float32) / 255.0 * np.asarray(tint, dtype=np.float32)


def _texture_spec(name: str) -> TextureSpec:
    source, tint = TEXTURE_CATALOGUE[name]
    digest = hashlib.sha256(_load_photo(source).tobytes()).hexdigest()
    return TextureSpec(name=name, source=source, tint=tint, source_sha256=digest)


# --------------------------------------------------------------------------- layout
def _smooth_noise(rng: np.random.Generator, s: np.ndarray, amp: float, dims: int) -> np.ndarray:
    """Smooth handheld-like wobble ``[len(s), dims]``: three random low-frequency sines."""
    out = np.zeros((len(s), dims))
    for k in (1, 2, 3):
        freq = rng.uniform(1.0, 2.5, dims) * k
        phase = rng.uniform(0, 2 * np.pi, dims)
        out += (amp / k) * np.sin(2 * np.pi * freq * s[:, None] + phase)
    return out


def sample_layout(seed: int = 0, texture_size: int = 256) -> SceneSpec:
    """The scene geometry for ``seed`` (no cameras): walls, posters, ground, 5 boxes.

    The seed jitters box positions (+-0.1 m) and yaws (+-15 deg) and permutes the box photos;
    the overall arrangement is fixed so every seed gives a sensible scene.
    """
    rng = np.random.default_rng([seed, 0])
    photos = ["coffee", "chelsea", "ihc", "camera", "coins"]
    order = rng.permutation(len(photos))
    tops = ["moon", "colorwheel", "coins", "coffee", "camera"]
    # (centre xy, half size, base yaw, stacked-on index or None)
    base = [
        ((-0.9, 0.6), (0.45, 0.35, 0.40), 15.0, None),
        ((0.55, 0.95), (0.35, 0.35, 0.60), -20.0, None),
        ((0.95, -0.45), (0.30, 0.25, 0.20), 40.0, None),
        ((-0.15, -0.55), (0.18, 0.22, 0.13), 70.0, None),
        ((0.05, -0.05), (0.20, 0.20, 0.18), 35.0, 0),
    ]
    boxes: list[BoxSpec] = []
    for i, (xy, half, yaw, on) in enumerate(base):
        jxy = rng.uniform(-0.1, 0.1, 2)
        jyaw = float(rng.uniform(-15.0, 15.0))
        if on is None:
            cx, cy, z0 = xy[0] + jxy[0], xy[1] + jxy[1], 0.0
        else:  # stacked on box `on`, offset relative to its centre
            below = boxes[on]
            cx = below.center[0] + xy[0] + 0.5 * jxy[0]
            cy = below.center[1] + xy[1] + 0.5 * jxy[1]
            z0 = below.center[2] + below.half_size[2]
        boxes.append(BoxSpec(
            name=f"box{i}", center=(float(cx), float(cy), float(z0 + half[2])),
            half_size=half, yaw_deg=float(yaw + jyaw),
            side_texture=photos[order[i]], top_texture=tops[i],
        ))
    wall_h = 1.1
    quads = [
        QuadSpec(name="ground", center=(0.0, 0.0, 0.0), right=(1.0, 0.0, 0.0), up=(0.0, 1.0, 0.0),
                 half_size=(7.0, 7.0), texture="gravel", period=(1.2, 1.2)),
        QuadSpec(name="back_wall", center=(0.0, 2.5, wall_h), right=(1.0, 0.0, 0.0),
                 up=(0.0, 0.0, 1.0), half_size=(6.0, wall_h), texture="brick", period=(1.6, 1.6)),
        QuadSpec(name="side_wall", center=(-3.0, -1.0, wall_h), right=(0.0, 1.0, 0.0),
                 up=(0.0, 0.0, 1.0), half_size=(3.5, wall_h), texture="grass", period=(1.4, 1.4)),
        QuadSpec(name="poster_back", center=(-0.6, 2.49, 1.35), right=(1.0, 0.0, 0.0),
                 up=(0.0, 0.0, 1.0), half_size=(0.55, 0.55), texture="astronaut",
                 period=(1.1, 1.1), wrap=False),
        QuadSpec(name="poster_side", center=(-2.99, 0.4, 1.2), right=(0.0, 1.0, 0.0),
                 up=(0.0, 0.0, 1.0), half_size=(0.6, 0.45), texture="chelsea",
                 period=(1.2, 0.9), wrap=False),
    ]
    used = sorted({q.texture for q in quads} | {b.side_texture for b in boxes}
                  | {b.top_texture for b in boxes})
    return SceneSpec(seed=seed, render=RenderSpec(texture_size=texture_size),
                     textures=[_texture_spec(n) for n in used], quads=quads, boxes=boxes)


def capture_path(n_views: int = 36, width: int = 256, height: int = 192,
                 seed: int = 0) -> Cameras:
    """A video-like handheld path of ``n_views`` cameras looking at the scene.

    The camera walks a ~76 degree arc around the scene centre while closing in from 4.3 m to
    3.1 m, at ~1.5 m height with a gentle bob, plus smooth position (+-3 cm), aim (+-6 cm)
    and roll (~1.5 deg) wobble. Intrinsics: ``fx = fy = 0.8 * width`` (64 deg horizontal
    field of view), principal point at the image centre.

    Returns:
        ``Cameras`` of length ``n_views`` in capture order.
    """
    if n_views < 2:
        raise ValueError(f"n_views must be >= 2, got {n_views}")
    rng = np.random.default_rng([seed, 1])
    s = np.linspace(0.0, 1.0, n_views)
    target0 = np.array([0.0, 0.35, 0.35])
    phi = np.radians(38.0 - 76.0 * s)
    r = 4.3 - 1.2 * s
    height_m = 1.5 + 0.12 * np.sin(2 * np.pi * 1.2 * s + rng.uniform(0, 2 * np.pi))
    eye = np.stack([target0[0] + r * np.sin(phi), target0[1] - r * np.cos(phi), height_m], -1)
    eye = eye + _smooth_noise(rng, s, 0.03, 3)
    target = target0 + _smooth_noise(rng, s, 0.06, 3)
    up = np.concatenate([_smooth_noise(rng, s, 0.025, 2), np.ones((n_views, 1))], axis=1)
    world_from_cam = look_at(eye, target, up)
    # Guard: camera +y (image down) must point away from world up, else turn the camera
    # 180 deg about its viewing axis (an early look_at had this handedness slip).
    flipped = np.einsum("ni,ni->n", world_from_cam[:, :3, 1], up) > 0
    world_from_cam[flipped, :3, 0:2] *= -1.0
    f = 0.8 * width
    return Cameras(world_from_cam, f, f, width / 2.0, height / 2.0, width, height)


# --------------------------------------------------------------------------- the world
class SampleWorld:
    """The sample scene as a renderable world (the ground-truth oracle).

    Build with :meth:`from_spec` or :meth:`load`; the training cameras (if the spec has them)
    are in :attr:`cameras` with :attr:`image_names`.
    """

    def __init__(self, spec: SceneSpec, photos: dict[str, np.ndarray] | None = None):
        self.spec = spec
        rs = spec.render
        names = [t.name for t in spec.textures]
        tex_index = {n: i for i, n in enumerate(names)}
        texs = []
        for t in spec.textures:
            if t.procedural is not None:
                photo = photos[t.name] if photos and t.name in photos else procedural_texture(
                    t.procedural)
            else:
                photo = (photos[t.source] if photos and t.source in photos
                         else _load_photo(t.source))
            texs.append(_texture_from_photo(photo, t.tint, rs.texture_size))
        self.textures = TextureBank(np.stack(texs))

        c, r, u, h, tid, per, wrap = [], [], [], [], [], [], []
        for q in spec.quads:
            c.append(q.center), r.append(q.right), u.append(q.up), h.append(q.half_size)
            tid.append(tex_index[q.texture]), per.append(q.period), wrap.append(q.wrap)
        for b in spec.boxes:
            bc, br, bu, bh = box_faces(np.array(b.center), np.array(b.half_size), b.yaw_deg)
            c.extend(bc), r.extend(br), u.extend(bu), h.extend(bh)
            for k in range(6):
                tid.append(tex_index[b.top_texture if k >= 4 else b.side_texture])
                per.append(2.0 * bh[k]), wrap.append(False)
        right = np.asarray(r, dtype=np.float64)
        up = np.asarray(u, dtype=np.float64)
        light = np.asarray(rs.light_dir, dtype=np.float64)
        light = light / np.linalg.norm(light)
        normal = np.cross(right, up)
        shade = rs.ambient + (1.0 - rs.ambient) * np.maximum(0.0, normal @ light)
        self.quads = Quads(
            center=np.asarray(c, dtype=np.float64), right=right, up=up,
            half=np.asarray(h, dtype=np.float64), tex_id=np.asarray(tid, dtype=np.int64),
            period=np.asarray(per, dtype=np.float64), wrap=np.asarray(wrap, dtype=bool),
            shade=shade.astype(np.float32),
        )
        self.quad_names = [q.name for q in spec.quads] + [
            f"{b.name}.{f}" for b in spec.boxes for f in ("+x", "-x", "+y", "-y", "top", "bottom")]
        self.cameras: Cameras | None = None
        self.image_names: list[str] = [fr.name for fr in spec.frames]
        if spec.camera is not None and spec.frames:
            cam = spec.camera
            self.cameras = Cameras(np.array([fr.world_from_cam for fr in spec.frames]),
                                   cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_spec(cls, spec: SceneSpec) -> "SampleWorld":
        """World from a :class:`SceneSpec` (checks the texture photos' hashes)."""
        photos = {}
        for t in spec.textures:
            photo = (procedural_texture(t.procedural) if t.procedural is not None
                     else _load_photo(t.source))
            digest = hashlib.sha256(photo.tobytes()).hexdigest()
            what = ("the procedural texture" if t.procedural is not None
                    else f"skimage.data.{t.source}()")
            if digest != t.source_sha256:
                raise ValueError(f"texture {t.name!r}: {what} differs from "
                                 f"the image the scene was made with (sha256 {digest[:12]} != "
                                 f"{t.source_sha256[:12]})")
            photos[t.name if t.procedural is not None else t.source] = photo
        return cls(spec, photos)

    @classmethod
    def load(cls, scene_dir: str | Path) -> "SampleWorld":
        """World from ``scene_dir/scene.json`` (as written by :func:`write_sample_scene`).

        Raises:
            MissingInputError: no scene.json.
            SceneError: scene.json is not a valid sample-scene description.
        """
        scene_dir = Path(scene_dir)
        path = scene_dir / "scene.json"
        if not path.is_file():
            raise MissingInputError(scene_dir.name, "sample scene description is missing", path)
        try:
            spec = SceneSpec.model_validate_json(path.read_bytes())
            return cls.from_spec(spec)
        except (ValidationError, ValueError, KeyError) as e:
            raise SceneError(scene_dir.name, f"invalid sample scene description: {e}", path) from e

    # ---------------------------------------------------------------- rendering
    def _sky(self, elev: np.ndarray) -> np.ndarray:
        rs = self.spec.render
        hor = np.asarray(rs.sky_horizon, dtype=np.float32)
        zen = np.asarray(rs.sky_zenith, dtype=np.float32)
        low = np.asarray(rs.below_horizon, dtype=np.float32)
        w_up = (np.clip(elev, 0.0, 1.0) ** 0.7).astype(np.float32)[:, None]
        w_dn = np.clip(-4.0 * elev, 0.0, 1.0).astype(np.float32)[:, None]
        return hor + (zen - hor) * w_up + (low - hor) * w_dn

    def _shade_hits(self, hits, world_from_cam: np.ndarray, fx: float, fy: float, cx: float,
                    cy: float, row0: int = 0) -> np.ndarray:
        """Colour ``[H, W, 3]`` float32 of pinhole hits ``[H, W]`` (texture x shading or sky).

        Computed for every pixel (misses use a dummy quad) and selected at the end: cheaper
        than masking each array, and element-wise, so a pixel's value never depends on others.
        """
        H, W = hits.t.shape
        R = np.asarray(world_from_cam, dtype=np.float64)[:3, :3]
        xn = np.broadcast_to((np.arange(W, dtype=np.float64) + 0.5 - cx) / fx, (H, W)).ravel()
        rows = np.arange(row0, row0 + H, dtype=np.float64)
        yn = np.broadcast_to(((rows + 0.5 - cy) / fy)[:, None], (H, W)).ravel()
        dn = np.sqrt(xn * xn + yn * yn + 1.0)
        quad = hits.quad.ravel()
        hit = quad >= 0
        Q = self.quads
        q = np.maximum(quad, 0)
        t = np.where(hit, hits.t.ravel(), 1.0)
        n_c = Q.normal @ R  # [Q, 3] normals in camera axes
        cos = np.abs(n_c[q, 0] * xn + n_c[q, 1] * yn + n_c[q, 2]) / dn
        # world size of one sample's footprint (isotropic, partly widened at grazing angles)
        foot = t * dn / (np.sqrt(fx * fy) * np.sqrt(np.maximum(cos, 0.05)))
        per_r, per_u = Q.period[q, 0], Q.period[q, 1]
        texels = foot * self.textures.size / np.sqrt(per_r * per_u)
        lod = np.log2(np.maximum(texels, 1.0))
        u = (hits.a.ravel() + Q.half[q, 0]) / per_r
        v = (Q.half[q, 1] - hits.b.ravel()) / per_u
        col = self.textures.sample(Q.tex_id[q], u, v, lod, Q.wrap[q]) * Q.shade[q][:, None]
        rs = self.spec.render
        if rs.specular > 0:  # white Blinn-Phong highlight: depends on the viewing direction
            light = np.asarray(rs.light_dir, dtype=np.float64)
            l_c = (light / np.linalg.norm(light)) @ R  # light direction in camera axes
            d = np.stack([xn, yn, np.ones_like(xn)], 1) / dn[:, None]  # ray directions
            n = n_c[q]
            n = n * np.where((n * d).sum(1) > 0, -1.0, 1.0)[:, None]  # face the camera
            hv = l_c[None, :] - d
            hv /= np.linalg.norm(hv, axis=1, keepdims=True)
            lit = (n @ l_c) > 0
            spec = rs.specular * np.maximum(0.0, (n * hv).sum(1)) ** rs.shininess * lit
            col = col + spec.astype(np.float32)[:, None]
        miss = np.flatnonzero(~hit)
        if len(miss):
            xm, ym = xn[miss], yn[miss]
            col[miss] = self._sky((R[2, 0] * xm + R[2, 1] * ym + R[2, 2]) / dn[miss])
        if rs.exposure != 1.0:
            col = col * np.float32(rs.exposure)
        return col.reshape(H, W, 3)

    def render(self, world_from_cam: np.ndarray, fx: float, fy: float, cx: float, cy: float,
               width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """True image and depth of the scene from any pinhole camera.

        Exactly the procedure that made the scene's images: colour is the box-filtered mean
        of ``supersample^2`` sub-pixel rays (at ``(x + (i + 0.5) / s, y + (j + 0.5) / s)``),
        rounded to uint8; depth is the camera-frame z of the surface hit by the ray through
        the pixel centre ``(x + 0.5, y + 0.5)``.

        Args:
            world_from_cam: ``[4, 4]`` pose, OpenCV camera axes.
            fx, fy, cx, cy: intrinsics in pixels (COLMAP/OpenCV pixel-centre convention).
            width, height: image size in pixels.
        Returns:
            ``(rgb [H, W, 3] uint8, depth [H, W] float32 metres)``; depth is
            ``render.miss_depth`` (0.0) where the ray hits nothing (sky).
        """
        T = np.asarray(world_from_cam, dtype=np.float64)
        if T.shape != (4, 4):
            raise ShapeError("world_from_cam", T.shape, "[4, 4]")
        W, H = int(width), int(height)
        if W < 1 or H < 1:
            raise ValueError(f"image size must be positive, got {W}x{H}")
        ss = int(self.spec.render.supersample)
        band = max(1, RENDER_BAND_SAMPLES // (W * ss * ss))  # output rows per band
        rgb = np.empty((H, W, 3), dtype=np.uint8)
        depth = np.empty((H, W), dtype=np.float32)
        for y0 in range(0, H, band):
            y1 = min(H, y0 + band)
            rgb[y0:y1], depth[y0:y1] = self._render_rows(T, float(fx), float(fy), float(cx),
                                                         float(cy), W, H, y0, y1)
        return rgb, depth

    def _render_rows(self, T: np.ndarray, fx: float, fy: float, cx: float, cy: float, W: int,
                     H: int, y0: int, y1: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows ``[y0, y1)`` of :meth:`render` (bit-identical to the same rows of a full one)."""
        rs = self.spec.render
        ss = int(rs.supersample)
        h = y1 - y0
        hits = cast_pinhole(self.quads, T, fx * ss, fy * ss, cx * ss, cy * ss, W * ss, H * ss,
                            rs.near, rows=(y0 * ss, y1 * ss))
        col = self._shade_hits(hits, T, fx * ss, fy * ss, cx * ss, cy * ss, row0=y0 * ss)
        if ss > 1:
            blocks = col.reshape(h, ss, W, ss, 3)
            acc = np.zeros((h, W, 3), dtype=np.float32)
            for i in range(ss):  # fixed summation order (deterministic)
                for j in range(ss):
                    acc += blocks[:, i, :, j]
            col = acc / np.float32(ss * ss)
            depth_hits = cast_pinhole(self.quads, T, fx, fy, cx, cy, W, H, rs.near, rows=(y0, y1))
        else:
            depth_hits = hits
        rgb = np.floor(np.clip(col, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        depth = np.where(depth_hits.quad >= 0, depth_hits.t, rs.miss_depth).astype(np.float32)
        return rgb, depth

    def render_camera(self, cameras: Cameras, i: int) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`render` for camera ``i`` of a ``Cameras`` batch."""
        return self.render(cameras.world_from_cam[i], cameras.fx[i], cameras.fy[i],
                           cameras.cx[i], cameras.cy[i], int(cameras.width[i]),
                           int(cameras.height[i]))

    # ---------------------------------------------------------------- surface queries
    def surface_color(self, quad: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Shaded full-resolution texture colour ``[P, 3]`` float32 at face coordinates."""
        Q = self.quads
        u = (a + Q.half[quad, 0]) / Q.period[quad, 0]
        v = (Q.half[quad, 1] - b) / Q.period[quad, 1]
        col = self.textures.sample(Q.tex_id[quad], u, v, np.zeros(len(quad)), Q.wrap[quad])
        return col * Q.shade[quad][:, None]

    def sample_surface(self, n: int, rng: np.random.Generator
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Uniform (area-weighted) random points on all surfaces.

        Includes hidden faces (box bottoms on the ground); the ground dominates by area.

        Returns:
            ``(xyz [n, 3] float64, normal [n, 3] float64, rgb [n, 3] uint8)``.
        """
        Q = self.quads
        p = Q.area / Q.area.sum()
        q = rng.choice(len(Q), size=n, p=p)
        a = rng.uniform(-1.0, 1.0, n) * Q.half[q, 0]
        b = rng.uniform(-1.0, 1.0, n) * Q.half[q, 1]
        xyz = Q.center[q] + a[:, None] * Q.right[q] + b[:, None] * Q.up[q]
        rgb = np.floor(np.clip(self.surface_color(q, a, b), 0, 1) * 255 + 0.5).astype(np.uint8)
        return xyz, Q.normal[q], rgb

    def cast(self, origins: np.ndarray, dirs: np.ndarray, near: float = 0.0):
        """Nearest hits of world rays (see :func:`freescale_core.geometry.raycast.cast_rays`)."""
        return cast_rays(self.quads, origins, dirs, near)


# --------------------------------------------------------------------------- sparse points
def sparse_points(world: SampleWorld, cameras: Cameras, n_points: int,
                  rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                     np.ndarray]:
    """SfM-like sparse points with exact tracks.

    Candidate points are where random pixel rays of random views hit the scene; a point is
    observed in a view when it projects inside the image, faces the camera and the ray from
    the camera centre reaches it unoccluded (exact ray cast). Points seen in >= 2 views are
    kept (the first ``n_points`` of them).

    Returns:
        ``(xyz [P, 3] float64, rgb [P, 3] uint8, visible [N, P] bool, uv [N, P, 2] float64)``
        where ``uv`` is the exact projection (valid where ``visible``).
    """
    N = len(cameras)
    n_cand = int(n_points * 1.6) + 64
    W, H = cameras.width, cameras.height
    vi = rng.integers(N, size=n_cand)
    px = rng.uniform(0.0, 1.0, n_cand) * W[vi]
    py = rng.uniform(0.0, 1.0, n_cand) * H[vi]
    d_cam = np.stack([(px - cameras.cx[vi]) / cameras.fx[vi],
                      (py - cameras.cy[vi]) / cameras.fy[vi], np.ones(n_cand)], -1)
    R = cameras.world_from_cam[vi, :3, :3]
    origins = cameras.world_from_cam[vi, :3, 3]
    hits = cast_rays(world.quads, origins, np.einsum("pij,pj->pi", R, d_cam),
                     world.spec.render.near)
    ok = hits.quad >= 0
    xyz = origins[ok] + hits.t[ok, None] * np.einsum("pij,pj->pi", R[ok], d_cam[ok])
    quad = hits.quad[ok]
    a, b = hits.a[ok], hits.b[ok]

    uv, z = cameras.project(xyz)  # [N, P, 2], [N, P]
    centers = cameras.centers
    normal = world.quads.normal[quad]  # [P, 3]
    facing = np.einsum("npk,pk->np", centers[:, None, :] - xyz[None], normal) > 0
    inside = ((z > world.spec.render.near) & (uv[..., 0] >= 0) & (uv[..., 0] < W[:, None])
              & (uv[..., 1] >= 0) & (uv[..., 1] < H[:, None]))
    cand_n, cand_p = np.nonzero(inside & facing)
    vis_hits = cast_rays(world.quads, centers[cand_n], xyz[cand_p] - centers[cand_n], 1e-9)
    seen = (vis_hits.quad == quad[cand_p]) & (np.abs(vis_hits.t - 1.0) < 1e-6)
    visible = np.zeros(z.shape, dtype=bool)
    visible[cand_n[seen], cand_p[seen]] = True

    keep = np.nonzero(visible.sum(axis=0) >= 2)[0][:n_points]
    col = world.surface_color(quad[keep], a[keep], b[keep])
    rgb = np.floor(np.clip(col, 0, 1) * 255 + 0.5).astype(np.uint8)
    return xyz[keep], rgb, visible[:, keep], uv[:, keep]


# --------------------------------------------------------------------------- COLMAP text
def _f(x: float) -> str:
    return repr(float(x))


def write_colmap_text(model_dir: Path, cameras: Cameras, names: list[str], xyz: np.ndarray,
                      rgb: np.ndarray, visible: np.ndarray, uv: np.ndarray) -> None:
    """Write ``cameras.txt``, ``images.txt``, ``points3D.txt`` (one shared PINHOLE camera).

    Floats are written with ``repr`` (shortest exact round trip). Image ids are 1-based in
    capture order; point ids are 1-based; each image's POINTS2D lists its observations in
    point-id order and each track names ``(IMAGE_ID, POINT2D_IDX)`` into those lists.
    """
    model_dir.mkdir(parents=True, exist_ok=True)
    N, P = visible.shape
    W, H = int(cameras.width[0]), int(cameras.height[0])
    with open(model_dir / "cameras.txt", "w", newline="\n") as fh:
        fh.write("# Camera list with one line of data per camera:\n"
                 "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n# Number of cameras: 1\n")
        fh.write(f"1 PINHOLE {W} {H} {_f(cameras.fx[0])} {_f(cameras.fy[0])} "
                 f"{_f(cameras.cx[0])} {_f(cameras.cy[0])}\n")
    quat, tvec = cam_from_world_to_colmap(invert_pose(cameras.world_from_cam))
    point2d_idx = np.cumsum(visible, axis=1) - 1  # [N, P] index of point p in image n's list
    n_obs = int(visible.sum())
    with open(model_dir / "images.txt", "w", newline="\n") as fh:
        fh.write("# Image list with two lines of data per image:\n"
                 "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                 "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
                 f"# Number of images: {N}, mean observations per image: {n_obs / max(N, 1)}\n")
        for n in range(N):
            pose = " ".join(_f(v) for v in (*quat[n], *tvec[n]))
            fh.write(f"{n + 1} {pose} 1 {names[n]}\n")
            ps = np.nonzero(visible[n])[0]
            obs = zip(uv[n, ps, 0].tolist(), uv[n, ps, 1].tolist(), (ps + 1).tolist())
            fh.write(" ".join(f"{x!r} {y!r} {p}" for x, y, p in obs) + "\n")
    with open(model_dir / "points3D.txt", "w", newline="\n") as fh:
        fh.write("# 3D point list with one line of data per point:\n"
                 "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                 f"# Number of points: {P}, mean track length: {n_obs / max(P, 1)}\n")
        xyz_l, rgb_l = xyz.tolist(), rgb.tolist()
        for p in range(P):
            ns = np.nonzero(visible[:, p])[0]
            track = " ".join(f"{n} {i}" for n, i in zip((ns + 1).tolist(),
                                                        point2d_idx[ns, p].tolist()))
            (x, y, z), (r, g, b) = xyz_l[p], rgb_l[p]
            fh.write(f"{p + 1} {x!r} {y!r} {z!r} {r} {g} {b} 0 {track}\n")


# --------------------------------------------------------------------------- writer
def _encode_png(rgb: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return buf.tobytes()


def write_sample_scene(out_dir: str | Path, n_views: int = 36, width: int = 256,
                       height: int = 192, seed: int = 0, *, n_points: int = 3000) -> Path:
    """Write the procedural sample scene as a COLMAP scene folder (atomically).

    Layout: ``images/frame_00000.png ...`` (capture order), ``sparse/0/{cameras,images,
    points3D}.txt`` and ``scene.json`` (:class:`SceneSpec`, from which
    :meth:`SampleWorld.load` rebuilds the oracle). Everything is written into a temporary
    folder next to ``out_dir`` and renamed into place at the end; an existing ``out_dir`` is
    replaced only once the new scene is complete. Same arguments -> byte-identical files.
    Other layouts, textures, rooms and capture paths: :func:`freescale_core.scene.family.
    write_family_scene` (same writer).

    Args:
        out_dir: scene folder to create (its parent must be writable).
        n_views: number of frames (>= 2).
        width, height: image size in pixels.
        seed: layout, path wobble and sparse-point sampling seed.
        n_points: maximum number of sparse points (seen in >= 2 views).
    Returns:
        ``out_dir`` as a ``Path``.
    """
    return write_scene(out_dir, sample_layout(seed), capture_path(n_views, width, height, seed),
                       width, height, seed, n_points=n_points)


def write_scene(out_dir: str | Path, spec: SceneSpec, cams: Cameras, width: int, height: int,
                seed: int, *, n_points: int = 3000) -> Path:
    """Write a scene folder for a layout ``spec`` seen from ``cams`` (the capture, in order):
    images, ``sparse/0`` and ``scene.json``, atomically (see :func:`write_sample_scene`)."""
    out_dir = Path(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    n_views = len(cams)
    names = [f"frame_{i:05d}.png" for i in range(n_views)]
    spec = spec.model_copy(update=dict(
        camera=CameraSpec(width=width, height=height, fx=float(cams.fx[0]),
                          fy=float(cams.fy[0]), cx=float(cams.cx[0]), cy=float(cams.cy[0])),
        frames=[FrameSpec(image_id=i + 1, name=names[i],
                          world_from_cam=cams.world_from_cam[i].tolist())
                for i in range(n_views)],
    ))
    world = SampleWorld(spec)
    cams = world.cameras  # exactly the poses in scene.json

    tmp = out_dir.parent / f".{out_dir.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        (tmp / "images").mkdir(parents=True)
        for i in range(n_views):
            rgb, _ = world.render_camera(cams, i)
            (tmp / "images" / names[i]).write_bytes(_encode_png(rgb))
        xyz, prgb, visible, uv = sparse_points(world, cams, n_points,
                                               np.random.default_rng([seed, 2]))
        write_colmap_text(tmp / "sparse" / "0", cams, names, xyz, prgb, visible, uv)
        spec = spec.model_copy(update=dict(n_points=int(len(xyz))))
        (tmp / "scene.json").write_text(
            json.dumps(spec.model_dump(mode="json"), indent=1) + "\n")
        _replace_dir(tmp, out_dir)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out_dir


def _replace_dir(src: Path, dst: Path) -> None:
    """Move the complete folder ``src`` to ``dst``, replacing ``dst`` if it exists."""
    if dst.exists() or dst.is_symlink():
        old = dst.parent / f".{dst.name}.old-{os.getpid()}-{uuid.uuid4().hex[:8]}"
        os.rename(dst, old)
        try:
            os.rename(src, dst)
        except OSError:
            os.rename(old, dst)
            raise
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(src, dst)
