"""Knobs of the procedural sample-scene family (``freescale_core.scene.family``).

The default config is the classic sample scene (``write_sample_scene(..., family=
SceneFamilyConfig())`` writes the same bytes as ``write_sample_scene(...)``). Ranges are
``(lo, hi)`` inclusive and drawn per scene from its seed.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

PathKind = Literal["arc", "walkthrough", "forward", "orbit"]


class SceneFamilyConfig(BaseModel):
    """Which scenes the family draws (layout, textures, room, capture path)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    layout: Literal["classic", "random"] = Field(
        "classic", description="'classic': the sample scene's five boxes, brick/grass walls "
        "(seed jitters them by +-0.1 m); 'random': room, walls, boxes and posters drawn "
        "from the ranges below.")
    n_boxes: tuple[int, int] = Field((3, 8), description="random: objects on the ground.")
    box_half_size: tuple[float, float] = Field(
        (0.12, 0.55), description="random: half extent of a box along each axis, metres.")
    stack_prob: float = Field(0.25, ge=0, le=1, description="random: chance a box is stacked "
                              "on an earlier one.")
    n_posters: tuple[int, int] = Field((0, 3), description="random: pictures on the walls.")
    room_half_size: tuple[float, float] = Field(
        (3.0, 5.0), description="random: half size of the room along x and y, metres.")
    wall_height: tuple[float, float] = Field((1.6, 3.0), description="random: metres.")
    n_walls: tuple[int, int] = Field((2, 4), description="random: walls (of 4 sides); open "
                                     "sides show sky and ground.")
    textures: Literal["photo", "procedural", "mixed"] = Field(
        "photo", description="'photo': scikit-image photos (classic); 'procedural': every "
        "texture generated (freescale_core.scene.textures); 'mixed': each texture either.")
    texture_kinds: tuple[Literal["noise", "checker", "stripes", "dots"], ...] = Field(
        ("noise", "checker", "stripes", "dots"), min_length=1,
        description="Procedural kinds to draw from.")
    texture_frequency: tuple[int, int] = Field(
        (2, 12), description="Procedural pattern repeats per texture (detail / frequency).")
    texture_octaves: tuple[int, int] = Field((1, 4), description="Procedural noise layers.")
    saturation: tuple[float, float] = Field((0.15, 0.85), description="Colour saturation.")
    value: tuple[float, float] = Field((0.25, 0.95), description="Colour brightness (HSV V).")
    path: Literal["arc", "walkthrough", "forward", "orbit", "any"] = Field(
        "arc", description="Capture path: 'arc' (walk ~arc_deg around the objects closing in; "
        "the classic layout uses the classic 76 deg arc), 'walkthrough' (walk straight through "
        "the room looking ahead), 'forward' (LLFF-like: a small spiral of parallel cameras "
        "facing the objects), 'orbit' (full circle around the objects), 'any' (one of the "
        "four per seed).")
    arc_deg: float = Field(76.0, gt=0, le=360, description="Generic arc: angle walked, degrees.")
    camera_height: tuple[float, float] = Field((1.3, 1.8), description="Generic paths: mean "
                                               "camera height, metres.")
    forward_extent: float = Field(0.3, gt=0, description="Forward-facing: spiral radius, m.")
    focal: float = Field(0.8, gt=0, description="fx = fy = focal * width (0.8: 64 deg HFOV).")

    @model_validator(mode="after")
    def _check(self) -> SceneFamilyConfig:
        for name in ("n_boxes", "box_half_size", "n_posters", "room_half_size", "wall_height",
                     "n_walls", "texture_frequency", "texture_octaves", "saturation", "value",
                     "camera_height"):
            lo, hi = getattr(self, name)
            if lo > hi or lo < 0:
                raise ValueError(f"{name}={(lo, hi)} must satisfy 0 <= lo <= hi")
        if self.n_boxes[0] < 1:
            raise ValueError("n_boxes must allow at least one object")
        if self.n_walls[1] > 4:
            raise ValueError("n_walls: a room has at most 4 walls")
        if self.texture_frequency[0] < 1 or self.texture_octaves[0] < 1:
            raise ValueError("texture_frequency and texture_octaves must be >= 1")
        if self.room_half_size[0] < 2.5:
            raise ValueError("room_half_size must be >= 2.5 m (cameras need room around "
                             "the objects)")
        return self
