"""Procedural textures for the sample-scene family (no files, no downloads).

A texture is described by a :class:`ProceduralTextureSpec` (kind, frequency, octaves,
colours, seed) and made by :func:`procedural_texture` as a ``uint8 [S, S, 3]`` image that
tiles seamlessly (every pattern is periodic over the texture: integer frequencies, lattice
noise with wrapped lattice indices), so it can repeat over a ground plane or a wall.

Kinds:

* ``noise``: fractal value noise (``octaves`` layers, frequency doubling, amplitude halving)
  mapped through a colour ramp ``colors[0] -> colors[1] (-> colors[2])``.
* ``checker``: ``frequency`` x ``frequency`` checkerboard of ``colors[0]`` / ``colors[1]``,
  lightly modulated by noise of the given octaves.
* ``stripes``: ``frequency`` smooth stripes across the texture (along u or v per seed),
  warped by noise.
* ``dots``: a ``frequency`` x ``frequency`` grid of discs (``colors[1]``) with jittered radii
  on a noisy ``colors[0]`` background.

Same spec -> same bytes (pure numpy float64 arithmetic, seeded ``numpy.random.Generator``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

Vec3 = tuple[float, float, float]
TextureKind = Literal["noise", "checker", "stripes", "dots"]
TEXTURE_KINDS: tuple[str, ...] = ("noise", "checker", "stripes", "dots")
# Generated side in pixels before the scene's resize to its texture size (anti-aliasing).
GEN_SIZE = 512


class ProceduralTextureSpec(BaseModel):
    """A procedural texture (stored in ``scene.json``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: TextureKind
    frequency: int = Field(4, ge=1, le=128, description="Pattern repeats per texture side.")
    octaves: int = Field(3, ge=1, le=8, description="Noise layers (detail).")
    colors: list[Vec3] = Field(description="2-3 RGB colours in [0, 1].", min_length=2,
                               max_length=3)
    seed: int = Field(0, description="Noise seed.")


def _value_noise(rng: np.random.Generator, size: int, freq: int, octaves: int) -> np.ndarray:
    """Tileable fractal value noise ``[size, size]`` in [0, 1]."""
    x = (np.arange(size) + 0.5) / size  # [size]
    out = np.zeros((size, size))
    total = 0.0
    for o in range(octaves):
        f = freq * (2 ** o)
        lattice = rng.random((f, f))
        p = x * f
        i0 = np.floor(p).astype(np.int64)
        t = p - i0
        t = t * t * (3.0 - 2.0 * t)  # smoothstep
        i0 %= f
        i1 = (i0 + 1) % f
        # bilinear over the wrapped lattice: rows (v) then columns (u)
        a = lattice[i0][:, i0] * (1 - t)[None, :] + lattice[i0][:, i1] * t[None, :]
        b = lattice[i1][:, i0] * (1 - t)[None, :] + lattice[i1][:, i1] * t[None, :]
        layer = a * (1 - t)[:, None] + b * t[:, None]
        amp = 0.5 ** o
        out += amp * layer
        total += amp
    return out / total


def _ramp(v: np.ndarray, colors: np.ndarray) -> np.ndarray:
    """Map ``v [H, W]`` in [0, 1] through the piecewise-linear colour ramp ``colors [K, 3]``."""
    k = len(colors) - 1
    s = np.clip(v, 0.0, 1.0) * k
    i = np.minimum(np.floor(s).astype(np.int64), k - 1)
    t = (s - i)[..., None]
    return colors[i] * (1 - t) + colors[i + 1] * t


def procedural_texture(spec: ProceduralTextureSpec, size: int = GEN_SIZE) -> np.ndarray:
    """The texture ``uint8 [size, size, 3]`` described by ``spec`` (tileable)."""
    rng = np.random.default_rng([spec.seed, 77])
    cols = np.asarray(spec.colors, dtype=np.float64)  # [K, 3]
    f, oct_ = spec.frequency, spec.octaves
    noise = _value_noise(rng, size, max(1, f), oct_)  # [S, S]
    x = (np.arange(size) + 0.5) / size
    U, V = np.meshgrid(x, x)  # U along columns, V along rows
    if spec.kind == "noise":
        # stretch contrast: fractal noise concentrates near 0.5
        img = _ramp(np.clip((noise - 0.5) * 2.2 + 0.5, 0, 1), cols)
    elif spec.kind == "checker":
        chk = ((np.floor(U * f) + np.floor(V * f)) % 2).astype(np.float64)
        img = cols[0] * (1 - chk[..., None]) + cols[1] * chk[..., None]
        img = img * (0.8 + 0.4 * noise[..., None])
    elif spec.kind == "stripes":
        coord = U if rng.random() < 0.5 else V
        warp = _value_noise(rng, size, 2, 2) - 0.5
        s = 0.5 + 0.5 * np.sin(2 * np.pi * (coord * f + 0.6 * warp))
        img = _ramp(s, cols) * (0.85 + 0.3 * noise[..., None])
    elif spec.kind == "dots":
        radii = rng.uniform(0.18, 0.42, (f, f))
        cu, cv = np.floor(U * f).astype(np.int64), np.floor(V * f).astype(np.int64)
        du, dv = U * f - cu - 0.5, V * f - cv - 0.5
        inside = (du * du + dv * dv) < radii[cv, cu] ** 2
        bg = cols[0] * (0.75 + 0.5 * noise[..., None])
        fg = cols[-1] * np.ones_like(bg)
        img = np.where(inside[..., None], fg, bg)
    else:  # pragma: no cover (Literal)
        raise ValueError(f"unknown texture kind {spec.kind!r}")
    return np.floor(np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
