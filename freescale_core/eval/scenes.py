"""Named procedural scenes of the evaluation (issue 16): sizes and failure families.

Every scene is written by the sample-scene writer (:func:`freescale_core.scene.sample.
write_scene`), so :class:`freescale_core.scene.sample.SampleWorld` is its exact oracle and
``scene.json`` holds the *true* cameras even when the COLMAP model on disk does not (noisy
poses). Names:

* sizes / detail: ``small`` (classic layout, 16 views, 64x48), ``medium`` (classic, 24 views,
  96x72), ``large`` (random room with procedural high-frequency textures, 32 views, 128x96);
  ``tiny`` (12 views, 48x36: the tests' scene);
* failure families (classic layout, 96x72 unless said): ``few3``, ``few5``, ``few8`` (views
  along the classic arc), ``short_baseline`` (LLFF-like spiral of radius 3 cm),
  ``dark`` (exposure 0.12: every colour times 0.12), ``textureless`` (procedural textures of
  one low frequency, almost no colour), ``specular`` (a strong white Blinn-Phong highlight,
  view-dependent), ``turntable`` (an orbit around the objects; the background stays fixed,
  the renderer has no moving background), ``large_gap`` (36 views along the arc with the
  middle 40% removed), ``turntable_bg`` (:mod:`freescale_core.scene.turntable`: three stacked
  boxes on a full circle of 24 views 96x72 with a background that changes in every image, the
  way a turntable's background turns relative to the object; exact object masks in
  ``masks/``; no ``scene.json`` oracle, so only held-out PSNR and counts are scored; sweep
  ``--knob masks=ignore`` for the same capture without its masks), ``noisy_rot1`` / ``noisy_rot3`` (the COLMAP poses rotated by a random
  axis, angle ~ N(0, 1 or 3 deg)), ``noisy_trans2`` / ``noisy_trans5`` (camera centres moved by
  N(0, 2% or 5% of the scene's camera-path length) per axis).

:func:`write_eval_scene` writes a scene only when its folder does not exist yet (same name ->
same bytes), so cached evaluation points keyed on the folder's fingerprint stay valid.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from freescale_core.eval.pose_noise import perturb_colmap_poses
from schemas.scene_family import SceneFamilyConfig

SIZE_SCENES = ("small", "medium", "large")
FAILURE_SCENES = ("few3", "few5", "few8", "short_baseline", "dark", "textureless", "specular",
                  "turntable", "turntable_bg", "large_gap", "noisy_rot1", "noisy_rot3", "noisy_trans2",
                  "noisy_trans5")
SCENES = ("tiny", *SIZE_SCENES, *FAILURE_SCENES)

# name -> (family overrides, render overrides, n_views, width, height, extra)
_W, _H = 96, 72
_TEXTURELESS = dict(layout="random", textures="procedural", texture_kinds=("noise",),
                    texture_frequency=(1, 1), texture_octaves=(1, 1), saturation=(0.0, 0.05),
                    value=(0.55, 0.7))
_SPECS: dict[str, tuple[dict, dict, int, int, int, dict]] = {
    "tiny": ({}, {}, 12, 48, 36, {}),
    "small": ({}, {}, 16, 64, 48, {}),
    "medium": ({}, {}, 24, _W, _H, {}),
    "large": (dict(layout="random", textures="procedural", texture_frequency=(8, 16),
                   texture_octaves=(3, 4), path="arc", arc_deg=120.0), {}, 32, 128, 96, {}),
    "few3": ({}, {}, 3, _W, _H, {}),
    "few5": ({}, {}, 5, _W, _H, {}),
    "few8": ({}, {}, 8, _W, _H, {}),
    "short_baseline": (dict(layout="random", path="forward", forward_extent=0.03), {}, 24, _W,
                       _H, {}),
    "dark": ({}, dict(exposure=0.12), 24, _W, _H, {}),
    "textureless": (_TEXTURELESS, {}, 24, _W, _H, {}),
    "specular": ({}, dict(specular=0.9, shininess=12.0), 24, _W, _H, {}),
    "turntable": (dict(layout="random", path="orbit"), {}, 24, _W, _H, {}),
    "turntable_bg": ({}, {}, 24, _W, _H, dict(writer="turntable", masks=True)),
    "large_gap": ({}, {}, 36, _W, _H, dict(gap=(0.3, 0.7))),
    "noisy_rot1": ({}, {}, 24, _W, _H, dict(rot_deg=1.0)),
    "noisy_rot3": ({}, {}, 24, _W, _H, dict(rot_deg=3.0)),
    "noisy_trans2": ({}, {}, 24, _W, _H, dict(trans_frac=0.02)),
    "noisy_trans5": ({}, {}, 24, _W, _H, dict(trans_frac=0.05)),
}


def describe(name: str) -> str:
    """One line: how the named scene is made (a procedural name, or a real-scene variant
    ``<base>--<family>``: :mod:`freescale_core.eval.real_variants`)."""
    from freescale_core.eval.real_variants import SEP, describe_variant

    if name not in _SPECS and SEP in name:
        try:
            return describe_variant(name)
        except ValueError:
            raise KeyError(name) from None
    fam, rend, n, w, h, extra = _SPECS[name]
    parts = [f"{n} views {w}x{h}"]
    parts += [f"{k}={v}" for k, v in {**fam, **rend, **extra}.items()]
    return ", ".join(parts)


def write_eval_scene(name: str, out_dir: str | Path, seed: int = 0) -> Path:
    """Write the named scene into ``out_dir`` (unless it exists); return the folder."""
    from freescale_core.scene.family import family_capture, family_layout
    from freescale_core.scene.sample import write_scene

    if name not in _SPECS:
        raise ValueError(f"unknown evaluation scene {name!r}; expected one of {list(_SPECS)}")
    out = Path(out_dir)
    if (out / "scene.json").is_file() or (out / "turntable.json").is_file():
        return out
    fam, rend, n, w, h, extra = _SPECS[name]
    if extra.get("writer") == "turntable":
        from freescale_core.scene.turntable import write_turntable_scene

        return write_turntable_scene(out, n, w, h, seed, fmt="colmap", masks=extra["masks"])
    fcfg = SceneFamilyConfig(**fam)
    spec = family_layout(seed, fcfg)
    if rend:
        spec = spec.model_copy(update={"render": spec.render.model_copy(update=rend)})
    cams = family_capture(spec, fcfg, n, w, h, seed)
    if "gap" in extra:
        a, b = (int(round(f * n)) for f in extra["gap"])
        cams = cams.subset(np.r_[0:a, b:n])
    write_scene(out, spec, cams, w, h, seed, n_points=1500)
    if "rot_deg" in extra or "trans_frac" in extra:
        perturb_colmap_poses(out / "sparse" / "0" / "images.txt", extra.get("rot_deg", 0.0),
                             extra.get("trans_frac", 0.0), seed)
    return out


REAL_SCENES = ("buddha", "dtu_scan24", "kermit", "llff_fern", "strecha_fountain-P11")


def datasets_dir() -> Path:
    """The shared real scenes: ``$FREESCALE_DATASETS``, else ``../shared/datasets`` beside the
    checkout (as the tests and benchmarks look them up)."""
    import os

    return Path(os.environ.get("FREESCALE_DATASETS",
                               Path(__file__).resolve().parents[3] / "shared" / "datasets"))


def resolve_scenes(specs: list[str], out: str | Path) -> tuple[list[Path], list[str]]:
    """Scene folders of an evaluation: ``proc:NAME`` (written into ``out/scenes/NAME``),
    ``proc:sizes`` / ``proc:failures`` (the groups), ``real:NAME`` / ``real:all`` (the shared
    datasets; absent ones are skipped with the reason), real-scene stability variants
    ``real:NAME@FAMILY`` (``NAME`` a shared scene or ``all``, ``FAMILY`` one of
    :data:`freescale_core.eval.real_variants.REAL_FAMILIES`, any ``few<N>`` /
    ``rotnoise<deg>`` / ``transnoise<frac>``, or ``failures`` for all of them; ``real:FAMILY``
    and ``real:failures`` mean ``real:all@...``; written into ``out/scenes/NAME--FAMILY``), or a
    folder. Returns ``(paths, skipped reasons)``."""
    from freescale_core.eval.real_variants import REAL_FAMILIES, SEP, is_family, \
        write_real_variant

    paths: list[Path] = []
    skipped: list[str] = []
    groups = {"sizes": SIZE_SCENES, "failures": FAILURE_SCENES}
    for s in specs:
        if s.startswith("proc:"):
            name = s[5:]
            for n in groups.get(name, (name,)):
                paths.append(write_eval_scene(n, Path(out) / "scenes" / n).resolve())
        elif s.startswith("real:"):
            name, _, family = s[5:].partition("@")
            if not family and name not in REAL_SCENES and is_family(name):
                name, family = "all", name
            families = REAL_FAMILIES if family == "failures" else (family,) if family else ()
            root = datasets_dir()
            for n in (REAL_SCENES if name == "all" else (name,)):
                p = root / n
                if not ((p / "sparse" / "0").is_dir() or (p / "transforms.json").is_file()):
                    skipped.append(f"{n}: not found under {root} (set FREESCALE_DATASETS)")
                    continue
                if not families:
                    paths.append(p.resolve())
                for f in families:
                    vname = f"{n}{SEP}{f}"
                    try:
                        paths.append(write_real_variant(p, f, Path(out) / "scenes" /
                                                        vname).resolve())
                    except ValueError as e:
                        skipped.append(f"{vname}: {e}")
        else:
            p = Path(s).expanduser()
            if not p.is_dir():
                skipped.append(f"{s}: no such scene folder")
            else:
                paths.append(p.resolve())
    out_paths: list[Path] = []
    for p in paths:
        if p not in out_paths:
            out_paths.append(p)
    return out_paths, skipped
