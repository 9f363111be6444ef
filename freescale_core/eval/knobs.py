"""Named knobs of the evaluation sweep, each mapped onto existing ``PipelineConfig`` fields.

A knob value is ``adaptive`` (the engine's own per-scene rule, where it has one), a number or
a name. :func:`apply_knob` returns nested overrides for ``PipelineConfig.from_preset``;
:func:`chosen_value` reads back, from a finished point, the value the engine really used
(for ``adaptive``: what the rule chose for that scene), which the sizing comparison halves
and doubles.

| knob | adaptive | a value sets |
|---|---|---|
| ``grid_r`` | ``select.grid.resolution=auto`` | ``select.grid.resolution`` (R voxels per axis) |
| ``candidates`` | the preset's pool | ``select.candidates.n_traj`` so that modes x n_traj x frames ~ pool |
| ``resolution`` | ``recon.detail_psnr_db=35`` (detail rule, under the preset's long side) | ``recon.max_long_side``, detail rule off |
| ``gaussians`` | the budget rule (points / pixels) | ``recon.budget_min = recon.cap_gaussians`` = value |
| ``steps`` | the preset's schedule with the plateau stop | ``recon.max_iterations`` (schedule scaled) |
| ``seconds`` | none | ``recon.max_seconds`` |
| ``visibility`` | - | ``select.visibility.mode`` (frustum, occlusion) |
| ``reference`` | - | ``freeview.reference.rule`` (graph, pose) |
| ``rectifier`` | - | ``freeview.rectifier.backend`` (none, reproject, fixer) |
| ``masks`` | - | ``ingest.masks`` (auto: read the scene's object masks; ignore) |
"""

from __future__ import annotations

from typing import Any

from schemas.pipeline import PipelineConfig

KNOBS = ("grid_r", "candidates", "resolution", "gaussians", "steps", "seconds", "visibility",
         "reference", "rectifier", "masks")
# knobs that change the reconstruction (the others act after it: selection, free views)
RECON_KNOBS = ("resolution", "gaussians", "steps", "seconds", "masks")
DETAIL_PSNR_DB = 35.0  # the paper / cpu presets' detail rule


def _num(knob: str, value: Any) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"knob {knob}: expected a number or 'adaptive', got {value!r}") from None


def apply_knob(base: PipelineConfig, knob: str, value: Any) -> dict:
    """Nested overrides that set ``knob`` to ``value`` on top of ``base``."""
    if knob not in KNOBS:
        raise ValueError(f"unknown knob {knob!r}; expected one of {list(KNOBS)}")
    adaptive = isinstance(value, str) and value == "adaptive"
    r, s = base.recon, base.select
    if knob == "grid_r":
        return {"select": {"grid": {"resolution": "auto" if adaptive
                                    else int(_num(knob, value))}}}
    if knob == "candidates":
        c = s.candidates
        per = len(c.modes) * c.frames_per_traj
        n = c.n_traj if adaptive else max(1, round(_num(knob, value) / per))
        return {"select": {"candidates": {"n_traj": int(n)}}}
    if knob == "resolution":
        if adaptive:
            return {"recon": {"detail_psnr_db": DETAIL_PSNR_DB}}
        return {"recon": {"max_long_side": int(_num(knob, value)), "detail_psnr_db": None}}
    if knob == "gaussians":
        if adaptive:
            return {}
        n = int(_num(knob, value))
        return {"recon": {"budget_min": n, "cap_gaussians": n}}
    if knob == "steps":
        if adaptive:
            return {}
        n = int(_num(knob, value))
        f = n / max(1, r.max_iterations)
        return {"recon": {
            "max_iterations": n, "min_iterations": min(n, max(1, int(r.min_iterations * f))),
            "densify_from": max(1, int(r.densify_from * f)),
            "densify_until": max(2, int(r.densify_until * f)),
            "densify_every": max(1, int(r.densify_every * f)),
            "plateau_window": max(5, int(r.plateau_window * f))}}
    if knob == "seconds":
        return {"recon": {"max_seconds": None if adaptive else _num(knob, value)}}
    if knob == "visibility":
        return {"select": {"visibility": {"mode": str(value)}}}
    if knob == "reference":
        return {"freeview": {"reference": {"rule": str(value)}}}
    if knob == "masks":
        return {"ingest": {"masks": str(value)}}
    return {"freeview": {"rectifier": {"backend": str(value)}}}


def chosen_value(knob: str, row: dict) -> float | None:
    """The value of ``knob`` a finished point used (from its result row), or None."""
    key = {"grid_r": "grid_R", "candidates": "n_candidates", "resolution": "train_long_side",
           "gaussians": "n_gaussians_budget", "steps": "iterations"}.get(knob)
    v = row.get(key) if key else None
    try:
        return None if v is None or v != v else float(v)
    except TypeError:
        return None


def scaled_value(knob: str, chosen: float, factor: float) -> int:
    """``chosen x factor`` as a knob value (grid R kept in [8, 512])."""
    v = int(round(chosen * factor))
    if knob == "grid_r":
        v = min(512, max(8, v))
    return max(1, v)
