"""A family of procedural sample scenes: layouts, textures, rooms and capture paths.

Every scene is a :class:`freescale_core.scene.sample.SceneSpec` (so :class:`SampleWorld` is its
exact oracle) drawn from a seed and a :class:`schemas.scene_family.SceneFamilyConfig`:

* layout ``classic`` (the sample scene) or ``random`` (room of 2-4 walls, 3-8 boxes of
  random sizes and yaws, some stacked, posters on the walls);
* textures ``photo`` (scikit-image photos), ``procedural`` (:mod:`.textures`: noise, checker,
  stripes, dots of chosen frequency, octaves and colours) or ``mixed``;
* capture path ``arc``, ``walkthrough``, ``forward`` (LLFF-like), ``orbit`` or ``any``.

The default config reproduces the classic scene exactly (same spec, same cameras, so
:func:`write_family_scene` writes the same bytes). :func:`off_path_poses` draws evaluation
cameras at poses the capture never visited; :func:`write_family` writes many scenes.

Random streams (``numpy.random.default_rng([seed, k])``): k = 10 layout, 11 textures,
12 path kind, 1 capture path (as the classic one), 13 off-path poses.
"""

from __future__ import annotations

import colorsys
import hashlib
from pathlib import Path

import numpy as np

from freescale_core.geometry.cameras import Cameras, look_at
from freescale_core.scene.sample import (
    BoxSpec,
    FamilyInfo,
    QuadSpec,
    RenderSpec,
    SampleWorld,
    SceneSpec,
    TextureSpec,
    _smooth_noise,
    _texture_spec,
    capture_path,
    sample_layout,
    write_scene,
)
from freescale_core.scene.textures import ProceduralTextureSpec, procedural_texture
from schemas.scene_family import SceneFamilyConfig

__all__ = [
    "CLASSIC_INFO",
    "PATH_KINDS",
    "box_clearance",
    "family_capture",
    "family_info",
    "family_layout",
    "off_path_poses",
    "write_family",
]

PATH_KINDS = ("arc", "walkthrough", "forward", "orbit")
# The classic scene: objects around (0, 0.35), back wall y = 2.5, side wall x = -3, ground +-7.
CLASSIC_INFO = FamilyInfo(layout="classic", path="arc", content_center=(0.0, 0.35, 0.35),
                          content_radius=1.5, bounds=(-2.7, 6.5, -6.5, 2.2))
PHOTOS_SIDE = ("coffee", "chelsea", "ihc", "camera", "coins", "astronaut", "moon")
PHOTOS_TOP = ("moon", "colorwheel", "coins", "coffee", "camera")
PHOTOS_FLOOR = ("gravel", "grass", "brick")


def family_info(spec: SceneSpec) -> FamilyInfo:
    """The scene's family metadata (the classic scene's when it has none)."""
    return spec.family if spec.family is not None else CLASSIC_INFO


def _path_kind(seed: int, cfg: SceneFamilyConfig) -> str:
    if cfg.path != "any":
        return cfg.path
    return PATH_KINDS[int(np.random.default_rng([seed, 12]).integers(len(PATH_KINDS)))]


# --------------------------------------------------------------------------- textures
def _random_colors(rng: np.random.Generator, cfg: SceneFamilyConfig) -> list:
    k = int(rng.integers(2, 4))
    h0 = rng.random()
    cols = []
    for i in range(k):
        h = (h0 + rng.uniform(-0.15, 0.15) + (0.5 if i == 1 and rng.random() < 0.4 else 0)) % 1
        s = rng.uniform(*cfg.saturation)
        v = rng.uniform(*cfg.value)
        cols.append(tuple(float(c) for c in colorsys.hsv_to_rgb(h, s, v)))
    # make sure the pattern has contrast: spread the values
    cols.sort(key=sum)
    return cols


def _procedural_spec(name: str, rng: np.random.Generator,
                     cfg: SceneFamilyConfig) -> TextureSpec:
    p = ProceduralTextureSpec(
        kind=str(rng.choice(list(cfg.texture_kinds))),
        frequency=int(rng.integers(cfg.texture_frequency[0], cfg.texture_frequency[1] + 1)),
        octaves=int(rng.integers(cfg.texture_octaves[0], cfg.texture_octaves[1] + 1)),
        colors=_random_colors(rng, cfg), seed=int(rng.integers(2**31)))
    digest = hashlib.sha256(procedural_texture(p).tobytes()).hexdigest()
    return TextureSpec(name=name, source="procedural", source_sha256=digest, procedural=p)


def _assign_textures(spec: SceneSpec, seed: int, cfg: SceneFamilyConfig) -> SceneSpec:
    """Replace the spec's texture slots by procedural ones (all or ~half, per cfg.textures)."""
    if cfg.textures == "photo":
        return spec
    rng = np.random.default_rng([seed, 11])
    slots = [("q", i) for i in range(len(spec.quads))] + [
        (k, i) for i in range(len(spec.boxes)) for k in ("side", "top")]
    names: dict[tuple[str, int], str] = {}
    new_tex: list[TextureSpec] = []
    for slot in slots:
        if cfg.textures == "mixed" and rng.random() < 0.5:
            continue
        name = f"proc{len(new_tex)}"
        new_tex.append(_procedural_spec(name, rng, cfg))
        names[slot] = name
    quads = [q.model_copy(update={"texture": names.get(("q", i), q.texture)})
             for i, q in enumerate(spec.quads)]
    boxes = [b.model_copy(update={"side_texture": names.get(("side", i), b.side_texture),
                                  "top_texture": names.get(("top", i), b.top_texture)})
             for i, b in enumerate(spec.boxes)]
    used = {q.texture for q in quads} | {b.side_texture for b in boxes} | {
        b.top_texture for b in boxes}
    textures = [t for t in spec.textures if t.name in used] + new_tex
    return spec.model_copy(update=dict(quads=quads, boxes=boxes, textures=textures))


# --------------------------------------------------------------------------- layout
def _random_layout(seed: int, cfg: SceneFamilyConfig) -> tuple[SceneSpec, FamilyInfo]:
    rng = np.random.default_rng([seed, 10])
    Lx, Ly = (float(v) for v in rng.uniform(*cfg.room_half_size, 2))
    wall_h = float(rng.uniform(*cfg.wall_height))
    n_walls = int(rng.integers(cfg.n_walls[0], cfg.n_walls[1] + 1))
    sides = sorted(int(i) for i in rng.choice(4, n_walls, replace=False))
    g = max(Lx, Ly) + 3.0
    floor_tex = str(rng.choice(PHOTOS_FLOOR))
    quads = [QuadSpec(name="ground", center=(0.0, 0.0, 0.0), right=(1.0, 0.0, 0.0),
                      up=(0.0, 1.0, 0.0), half_size=(g, g), texture=floor_tex,
                      period=(float(rng.uniform(0.8, 2.0)),) * 2)]
    # (centre, right) of each inward-facing wall: +y, -y, +x, -x
    walls = [((0.0, Ly), (1.0, 0.0), Lx), ((0.0, -Ly), (-1.0, 0.0), Lx),
             ((Lx, 0.0), (0.0, -1.0), Ly), ((-Lx, 0.0), (0.0, 1.0), Ly)]
    bounds = [-g + 0.5, g - 0.5, -g + 0.5, g - 0.5]  # xmin xmax ymin ymax
    for k in sides:
        (wx, wy), (rx, ry), half = walls[k]
        per = float(rng.uniform(1.0, 2.2))
        quads.append(QuadSpec(
            name=f"wall{k}", center=(wx, wy, wall_h / 2), right=(rx, ry, 0.0),
            up=(0.0, 0.0, 1.0), half_size=(half, wall_h / 2),
            texture=str(rng.choice(PHOTOS_FLOOR)), period=(per, per)))
        bounds[[3, 2, 1, 0][k]] = [Ly, -Ly, Lx, -Lx][k] + (-0.35 if k in (0, 2) else 0.35)
    n_posters = int(rng.integers(cfg.n_posters[0], cfg.n_posters[1] + 1))
    for j in range(n_posters if sides else 0):
        k = int(rng.choice(sides))
        (wx, wy), (rx, ry), half = walls[k]
        hw, hh = float(rng.uniform(0.3, 0.6)), float(rng.uniform(0.25, 0.5))
        a = float(rng.uniform(-half + hw + 0.1, half - hw - 0.1))
        n_in = np.cross([rx, ry, 0.0], [0.0, 0.0, 1.0])  # inward normal
        c = (wx + a * rx + 0.01 * n_in[0], wy + a * ry + 0.01 * n_in[1],
             float(min(wall_h - hh - 0.05, rng.uniform(1.0, 1.6))))
        quads.append(QuadSpec(name=f"poster{j}", center=c, right=(rx, ry, 0.0),
                              up=(0.0, 0.0, 1.0), half_size=(hw, hh),
                              texture=str(rng.choice(PHOTOS_SIDE)), period=(2 * hw, 2 * hh),
                              wrap=False))
    # objects inside a disc leaving room for cameras all around
    r_max = max(1.0, min(Lx, Ly) - 1.7)
    n_boxes = int(rng.integers(cfg.n_boxes[0], cfg.n_boxes[1] + 1))
    boxes: list[BoxSpec] = []
    foot: list[tuple[float, float, float]] = []  # (x, y, radius) of ground boxes
    for i in range(n_boxes):
        half = rng.uniform(*cfg.box_half_size, 3)
        yaw = float(rng.uniform(0.0, 180.0))
        side, top = str(rng.choice(PHOTOS_SIDE)), str(rng.choice(PHOTOS_TOP))
        ground = [b for b in boxes if b.center[2] == b.half_size[2]]
        if ground and rng.random() < cfg.stack_prob:
            below = ground[int(rng.integers(len(ground)))]
            half[:2] = np.minimum(half[:2], 0.8 * np.asarray(below.half_size[:2]))
            cx = below.center[0] + rng.uniform(-0.3, 0.3) * below.half_size[0]
            cy = below.center[1] + rng.uniform(-0.3, 0.3) * below.half_size[1]
            z0 = below.center[2] + below.half_size[2]
        else:
            rad = float(np.hypot(half[0], half[1]))
            for _ in range(60):
                rr, th = r_max * np.sqrt(rng.random()), rng.uniform(0, 2 * np.pi)
                cx, cy = rr * np.cos(th), rr * np.sin(th)
                if all(np.hypot(cx - x, cy - y) > rad + r + 0.05 for x, y, r in foot):
                    break
            else:
                continue  # no room left: fewer objects
            foot.append((float(cx), float(cy), rad))
            z0 = 0.0
        boxes.append(BoxSpec(name=f"box{i}", center=(float(cx), float(cy), float(z0 + half[2])),
                             half_size=tuple(float(h) for h in half), yaw_deg=yaw,
                             side_texture=side, top_texture=top))
    xy = np.array([(x, y) for x, y, _ in foot])
    c = xy.mean(axis=0)
    rc = float(max(np.hypot(x - c[0], y - c[1]) + r for x, y, r in foot))
    cz = float(np.mean([b.center[2] for b in boxes]))
    used = sorted({q.texture for q in quads} | {b.side_texture for b in boxes}
                  | {b.top_texture for b in boxes})
    spec = SceneSpec(seed=seed, render=RenderSpec(), textures=[_texture_spec(n) for n in used],
                     quads=quads, boxes=boxes)
    info = FamilyInfo(layout="random", path="arc", content_center=(float(c[0]), float(c[1]), cz),
                      content_radius=rc, bounds=tuple(float(b) for b in bounds))
    return spec, info


def family_layout(seed: int, cfg: SceneFamilyConfig | None = None) -> SceneSpec:
    """The scene geometry (no cameras) for ``seed``; the default config gives
    :func:`sample_layout` ``(seed)`` unchanged (``spec.family`` None)."""
    cfg = cfg or SceneFamilyConfig()
    path = _path_kind(seed, cfg)
    if cfg.layout == "classic":
        spec, info = sample_layout(seed), CLASSIC_INFO
    else:
        spec, info = _random_layout(seed, cfg)
    spec = _assign_textures(spec, seed, cfg)
    if cfg.layout == "classic" and path == "arc" and cfg.textures == "photo":
        return spec
    return spec.model_copy(update={"family": info.model_copy(update={"path": path})})


# --------------------------------------------------------------------------- capture paths
def box_clearance(points: np.ndarray, spec: SceneSpec) -> np.ndarray:
    """Distance ``[P]`` from each point ``[P, 3]`` to the nearest box (0 inside one)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.full(len(p), np.inf)
    for b in spec.boxes:
        psi = np.radians(b.yaw_deg)
        d = p - np.asarray(b.center)
        lx = np.cos(psi) * d[:, 0] + np.sin(psi) * d[:, 1]
        ly = -np.sin(psi) * d[:, 0] + np.cos(psi) * d[:, 1]
        q = np.abs(np.stack([lx, ly, d[:, 2]], -1)) - np.asarray(b.half_size)
        out = np.minimum(out, np.linalg.norm(np.maximum(q, 0.0), axis=1))
    return out


def _room_radius(info: FamilyInfo) -> float:
    cx, cy, _ = info.content_center
    x0, x1, y0, y1 = info.bounds
    return float(min(cx - x0, x1 - cx, cy - y0, y1 - cy))


def _radii(info: FamilyInfo) -> tuple[float, float]:
    """(closest, farthest) camera distance from the content centre that fits the room."""
    r_room = _room_radius(info)
    lo = min(info.content_radius + 0.9, r_room)
    return lo, max(lo, r_room)


def _upright(world_from_cam: np.ndarray, up: np.ndarray) -> np.ndarray:
    flipped = np.einsum("ni,ni->n", world_from_cam[:, :3, 1], up) > 0
    world_from_cam[flipped, :3, 0:2] *= -1.0
    return world_from_cam


def family_capture(spec: SceneSpec, cfg: SceneFamilyConfig | None, n_views: int, width: int,
                   height: int, seed: int) -> Cameras:
    """The capture cameras (capture order) of a family scene.

    The classic layout with the arc path is :func:`capture_path` exactly. Other paths are
    drawn around ``spec.family`` (content centre / radius, camera bounds) with the classic
    path's smooth handheld wobble.
    """
    cfg = cfg or SceneFamilyConfig()
    if n_views < 2:
        raise ValueError(f"n_views must be >= 2, got {n_views}")
    info = family_info(spec)
    kind = info.path
    if info.layout == "classic" and kind == "arc":
        cams = capture_path(n_views, width, height, seed)
        if cfg.focal != 0.8:
            f = cfg.focal * width
            cams = Cameras(cams.world_from_cam, f, f, width / 2.0, height / 2.0, width, height)
        return cams
    rng = np.random.default_rng([seed, 1])
    s = np.linspace(0.0, 1.0, n_views)
    c = np.asarray(info.content_center, dtype=np.float64)
    r_lo, r_hi = _radii(info)
    h0 = rng.uniform(*cfg.camera_height)
    zdir = np.array([0.0, 0.0, 1.0])
    if kind in ("arc", "orbit"):
        phi0 = rng.uniform(0, 2 * np.pi)
        if kind == "arc":
            span = np.radians(cfg.arc_deg)
            r = r_hi - (r_hi - r_lo) * 0.6 * s
        else:
            span = 2 * np.pi * (1 - 1 / n_views)
            r = np.full(n_views, rng.uniform(r_lo, r_hi))
        phi = phi0 + span * s
        eye = np.stack([c[0] + r * np.cos(phi), c[1] + r * np.sin(phi),
                        h0 + 0.1 * np.sin(2 * np.pi * 1.2 * s + rng.uniform(0, 6.3))], -1)
        target = np.broadcast_to(c, eye.shape)
    elif kind == "forward":
        th = rng.uniform(0, 2 * np.pi)
        r = rng.uniform(r_lo, 0.5 * (r_lo + r_hi))
        p0 = np.array([c[0] + r * np.cos(th), c[1] + r * np.sin(th), h0])
        fwd = (c - p0) / np.linalg.norm(c - p0)
        right = np.cross(fwd, zdir)
        right /= np.linalg.norm(right)
        upv = np.cross(right, fwd)
        t = 2 * 2 * np.pi * s
        a = cfg.forward_extent * (0.4 + 0.6 * s)
        eye = (p0 + (a * np.cos(t))[:, None] * right + (0.6 * a * np.sin(t))[:, None] * upv
               + (0.1 * np.sin(np.pi * s))[:, None] * fwd)
        target = eye + 2.0 * r * fwd  # parallel optical axes
    elif kind == "walkthrough":
        th = rng.uniform(0, 2 * np.pi)
        d = np.array([np.cos(th), np.sin(th), 0.0])
        lat = np.array([-d[1], d[0], 0.0])
        r_room = _room_radius(info)
        along = (-0.95 + 0.75 * s) * r_room  # walk in, stop short of the objects
        best, best_clear = 0.0, -1.0
        for off in sorted(np.linspace(-1.0, 1.0, 21) * (info.content_radius + 0.5), key=abs):
            pts = c[None] + along[:, None] * d + off * lat
            pts[:, 2] = h0
            clear = float(box_clearance(pts, spec).min())
            if clear >= 0.4:
                best = off
                break
            if clear > best_clear:
                best, best_clear = off, clear
        eye = c[None] + along[:, None] * d + best * lat
        eye[:, 2] = h0 + 0.05 * np.sin(2 * np.pi * 3 * s)
        yaw = 0.25 * np.sin(2 * np.pi * 0.8 * s + rng.uniform(0, 6.3))
        look = np.cos(yaw)[:, None] * d + np.sin(yaw)[:, None] * lat
        target = eye + 2.0 * look - np.array([0.0, 0.0, 0.5])
    else:  # pragma: no cover (Literal)
        raise ValueError(f"unknown path kind {kind!r}")
    eye = eye + _smooth_noise(rng, s, 0.02, 3)
    target = target + _smooth_noise(rng, s, 0.04, 3)
    up = np.concatenate([_smooth_noise(rng, s, 0.02, 2), np.ones((n_views, 1))], axis=1)
    world_from_cam = _upright(look_at(eye, target, up), up)
    f = cfg.focal * width
    return Cameras(world_from_cam, f, f, width / 2.0, height / 2.0, width, height)


# --------------------------------------------------------------------------- evaluation poses
def off_path_poses(world: SampleWorld, n: int, seed: int = 0, min_distance: float = 0.5,
                   width: int | None = None, height: int | None = None) -> Cameras:
    """``n`` cameras at poses the capture never visited, each looking at an object.

    Three kinds in turn: *height* (a capture camera's direction from the objects but another
    height, 0.45-0.9 m or 2.2-3.0 m, and radius), *orbit* (any angle around the objects,
    height 1.0-2.3 m) and *across* (anywhere in the room, 0.6-2.6 m high, looking across at an
    object). A pose is kept when it is inside the camera bounds, >= 0.3 m from every box,
    >= ``min_distance`` from every capture camera centre, >= 0.8 m from its target, and the
    ray to its target (a box centre, jittered) first hits a box. Intrinsics: the capture's,
    scaled to ``width x height`` when given.

    Raises:
        ValueError: the scene has no capture cameras, or too few poses qualified.
    """
    if world.cameras is None:
        raise ValueError("off_path_poses needs a scene with capture cameras")
    spec, caps = world.spec, world.cameras
    info = family_info(spec)
    rng = np.random.default_rng([seed, 13])
    c = np.asarray(info.content_center)
    r_lo, r_hi = _radii(info)
    x0, x1, y0, y1 = info.bounds
    centers = caps.centers
    n_quads = len(spec.quads)
    boxes = np.array([b.center for b in spec.boxes])
    poses: list[np.ndarray] = []
    tries = 0
    while len(poses) < n and tries < 400 * max(n, 1):
        kind = (len(poses) + tries) % 3
        tries += 1
        if kind == 0:
            ref = centers[int(rng.integers(len(centers)))] - c
            th = np.arctan2(ref[1], ref[0])
            r = np.hypot(ref[0], ref[1]) + rng.uniform(-0.3, 0.3)
            h = rng.uniform(0.45, 0.9) if rng.random() < 0.5 else rng.uniform(2.2, 3.0)
            p = np.array([c[0] + r * np.cos(th), c[1] + r * np.sin(th), h])
        elif kind == 1:
            th, r = rng.uniform(0, 2 * np.pi), rng.uniform(r_lo, r_hi)
            p = np.array([c[0] + r * np.cos(th), c[1] + r * np.sin(th), rng.uniform(1.0, 2.3)])
        else:
            p = np.array([rng.uniform(x0, x1), rng.uniform(y0, y1), rng.uniform(0.6, 2.6)])
        tgt = boxes[int(rng.integers(len(boxes)))] + rng.normal(0, 0.1, 3)
        if not (x0 <= p[0] <= x1 and y0 <= p[1] <= y1):
            continue
        if np.linalg.norm(tgt - p) < 0.8 or box_clearance(p[None], spec)[0] < 0.3:
            continue
        if np.linalg.norm(centers - p, axis=1).min() < min_distance:
            continue
        hit = world.cast(p[None], (tgt - p)[None], 1e-6)
        if not hit.quad[0] >= n_quads:  # the first surface on the way must be an object
            continue
        up = np.array([0.0, 0.0, 1.0]) + rng.normal(0, 0.02, 3)
        poses.append(_upright(look_at(p[None], tgt[None], up[None]), up[None])[0])
    if len(poses) < n:
        raise ValueError(f"off_path_poses: only {len(poses)} of {n} poses qualified")
    W = int(caps.width[0]) if width is None else int(width)
    H = int(caps.height[0]) if height is None else int(height)
    sx, sy = W / float(caps.width[0]), H / float(caps.height[0])
    return Cameras(np.stack(poses), float(caps.fx[0]) * sx, float(caps.fy[0]) * sy,
                   float(caps.cx[0]) * sx, float(caps.cy[0]) * sy, W, H)


def write_family_scene(out_dir: str | Path, n_views: int = 24, width: int = 128,
                       height: int = 96, seed: int = 0, *, n_points: int = 2000,
                       family: SceneFamilyConfig | None = None) -> Path:
    """Write one scene of the family (layout, textures, room and capture path chosen by
    ``family`` and ``seed``) with the sample scene's writer; the default config gives the
    classic scene's bytes."""
    family = family or SceneFamilyConfig()
    spec = family_layout(seed, family)
    cams = family_capture(spec, family, n_views, width, height, seed)
    return write_scene(out_dir, spec, cams, width, height, seed, n_points=n_points)


# --------------------------------------------------------------------------- many scenes
def write_family(out_dir: str | Path, n_scenes: int, seed: int = 0,
                 family: SceneFamilyConfig | None = None, *, n_views: int = 24,
                 width: int = 128, height: int = 96, n_points: int = 2000,
                 prefix: str = "scene") -> list[Path]:
    """Write ``n_scenes`` scenes ``out_dir/{prefix}_{k:04d}`` (scene seeds ``seed + k``).

    Each is a full scene folder (images, sparse/0, scene.json) written atomically by
    :func:`write_family_scene`; default family: random layouts, mixed textures, any path.
    """
    family = family or SceneFamilyConfig(layout="random", textures="mixed", path="any")
    out = Path(out_dir)
    return [write_family_scene(out / f"{prefix}_{k:04d}", n_views, width, height, seed + k,
                               n_points=n_points, family=family) for k in range(n_scenes)]
