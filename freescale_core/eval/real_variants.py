"""Stability families on real scenes (issue 16): a captured scene made harder on purpose.

:func:`write_real_variant` reads a scene (any format the engine reads; distorted cameras are
undistorted first) and writes a derived COLMAP scene (one PINHOLE camera per image, the
sparse points with empty tracks) into a new folder, atomically (built under a temporary name
beside it and renamed into place; a folder that exists is complete and is reused, so cached
evaluation points keyed on its fingerprint stay valid). The base scene's held-out views
(its ``ood`` split: the last 30% in capture order) are kept unchanged and listed in
``heldout.txt`` (the engine then holds out exactly those, whatever the view count), so the
held-out PSNR of a variant is measured on the same photos and poses as the base's. Families:

* ``few<N>`` (``few3``, ``few5``, ``few8``): only ``N`` training views, evenly spaced over
  the base's training views in capture order (refused when the base has ``<= N``);
* ``dark``: every image (training and held-out) scaled to ``DARK_GAIN`` (15%) of its
  brightness plus Gaussian read noise of ``DARK_NOISE`` (2) grey levels, fixed seed, written
  as PNG; PSNR is then on the dark scale (20 log10(1 / 0.15) = 16.5 dB above the
  exposure-normalised one for the same relative error);
* ``rotnoise<deg>`` (``rotnoise1``, ``rotnoise3``): the *training* views' poses rotated about
  their centres by a random axis, angle ~ N(0, deg); ``transnoise<frac>`` (``transnoise0.02``,
  ``transnoise0.05``): their centres moved by N(0, frac x camera-path length) per axis
  (:func:`freescale_core.eval.pose_noise.perturb_colmap_poses`, the procedural families'
  code). Held-out poses stay exact, so held-out PSNR measures what the noisy training poses
  cost.

A variant's folder is ``<base>--<family>`` (the scene id the tables show) with
``variant.json`` saying how it was made. Object masks of the base are carried over.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import uuid
from pathlib import Path

import numpy as np

REAL_FAMILIES = ("few3", "few5", "few8", "dark", "rotnoise1", "rotnoise3", "transnoise0.02",
                 "transnoise0.05")
DARK_GAIN = 0.15
DARK_NOISE = 2.0
SEP = "--"
_FAMILY = re.compile(r"^(few)(\d+)$|^(dark)$|^(rotnoise)(\d+(?:\.\d+)?)$|"
                     r"^(transnoise)(\d+(?:\.\d+)?)$")


def parse_family(family: str) -> tuple[str, float]:
    """``("few", N)``, ``("dark", 0)``, ``("rotnoise", deg)`` or ``("transnoise", frac)``."""
    m = _FAMILY.match(family)
    if not m:
        raise ValueError(f"unknown real-scene family {family!r}: expected few<N>, dark, "
                         "rotnoise<deg> or transnoise<fraction>")
    g = [x for x in m.groups() if x is not None]
    return g[0], float(g[1]) if len(g) > 1 else 0.0


def is_family(name: str) -> bool:
    return name == "failures" or _FAMILY.match(name) is not None


def describe_variant(name: str) -> str:
    """One line for a variant's folder name ``<base>--<family>``."""
    base, _, family = name.rpartition(SEP)
    kind, v = parse_family(family)
    how = {"few": f"{v:.0f} evenly spaced training views",
           "dark": f"images x{DARK_GAIN:g} + noise sigma {DARK_NOISE:g} grey levels",
           "rotnoise": f"training poses rotated ~N(0, {v:g} deg)",
           "transnoise": f"training centres moved ~N(0, {v:g} x path length)"}[kind]
    return f"real scene {base}: {how}; held-out views unchanged"


def write_real_variant(base: str | Path, family: str, out_dir: str | Path,
                       seed: int = 0) -> Path:
    """Write the ``family`` variant of the scene at ``base`` into ``out_dir`` (see the module
    doc); return the folder. Raises ValueError for an unknown family or one the scene cannot
    have (``few<N>`` with ``N`` >= its training views)."""
    import cv2

    from freescale_core.scene.io import load_scene
    from freescale_core.scene.sample import _encode_png

    kind, v = parse_family(family)
    base, out = Path(base), Path(out_dir)
    if (out / "variant.json").is_file():
        return out
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        tmp.mkdir()
        scene = load_scene(base, scene_id=base.name, cache_dir=tmp / ".cache")
        train, test = scene.split("ood")
        if kind == "few":
            n = int(v)
            if n < 1 or n >= len(train):
                raise ValueError(f"{base.name} has {len(train)} training views: {family} "
                                 "would not remove any" if n >= len(train) else
                                 f"{family}: at least one view")
            train = train[np.unique(np.round(np.linspace(0, len(train) - 1, n)).astype(int))]
        keep = set(train.tolist()) | set(test.tolist())
        idx = [int(i) for i in scene.capture_order if int(i) in keep]
        names = [scene.image_names[i] for i in idx]
        if kind == "dark":
            names = [str(Path(nm).with_suffix(".png")) for nm in names]
        for k, (i, nm) in enumerate(zip(idx, names)):
            dst = tmp / "images" / nm
            dst.parent.mkdir(parents=True, exist_ok=True)
            if kind == "dark":
                rng = np.random.default_rng([seed, 17, k])
                img = scene.load_image(i).astype(np.float64) * DARK_GAIN
                img += rng.normal(0.0, DARK_NOISE, img.shape)
                dst.write_bytes(_encode_png(np.clip(np.round(img), 0, 255).astype(np.uint8)))
            else:
                shutil.copyfile(scene.image_paths[i], dst)
            if scene.has_masks:
                m = (tmp / "masks" / (nm + ".png"))
                m.parent.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(m), scene.load_mask(i).astype(np.uint8) * 255)
        from freescale_core.exports.colmap import write_model_text

        write_model_text(tmp / "sparse" / "0", scene.cameras, idx, names, scene.points_xyz,
                         scene.points_rgb)
        train_set = set(train.tolist())
        train_names = {names[k] for k, i in enumerate(idx) if i in train_set}
        if kind in ("rotnoise", "transnoise"):
            from freescale_core.eval.pose_noise import perturb_colmap_poses

            perturb_colmap_poses(tmp / "sparse" / "0" / "images.txt",
                                  v if kind == "rotnoise" else 0.0,
                                  v if kind == "transnoise" else 0.0, seed, only=train_names)
        held = [nm for nm in names if nm not in train_names]
        (tmp / "heldout.txt").write_text(
            "# held-out views of the base scene's ood split (kept unchanged)\n"
            + "\n".join(held) + "\n")
        shutil.rmtree(tmp / ".cache", ignore_errors=True)
        (tmp / "variant.json").write_text(json.dumps({
            "base": str(base.resolve()), "base_name": base.name, "family": family,
            "kind": kind, "value": v, "seed": seed, "n_views": len(idx),
            "n_train": len(train_names), "n_heldout": len(held),
            "base_n_views": len(scene), "describe": describe_variant(out.name)
            if SEP in out.name else family}, indent=1) + "\n")
        if out.exists():  # a concurrent writer finished first: keep its folder
            return out
        os.rename(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return out
