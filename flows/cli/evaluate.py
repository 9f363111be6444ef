"""``freescale evaluate SCENES``: the evaluate-engine flow (flows/evaluate_engine.py)."""

from __future__ import annotations

import sys
from pathlib import Path

from flows.cli.common import _one_line_validation, _parse_set


def add_parsers(sub) -> None:
    """``freescale evaluate SCENES``: the evaluate-engine flow (flows/evaluate_engine.py)."""
    s = sub.add_parser("evaluate", help="sweep knobs over scenes: seconds per scene vs accuracy, "
                       "a Pareto chart, sizing and stability tables (docs/EVALUATION.md)")
    s.add_argument("scenes", nargs="*", help="scene folders, proc:NAME (proc:sizes, "
                   "proc:failures), real:NAME or real:all, real:NAME@FAMILY (few<N>, dark, "
                   "rotnoise<deg>, transnoise<frac>; real:failures: all); --quick alone: "
                   "proc:tiny")
    s.add_argument("--out", default="data/eval", help="output folder (points are cached there)")
    s.add_argument("--preset", default=None, choices=["paper", "cpu", "fast"],
                   help="preset of the base point (default fast)")
    s.add_argument("--knob", action="append", default=[], metavar="NAME=V1,V2",
                   help="sweep a knob, e.g. --knob grid_r=32,64,adaptive (names: grid_r "
                   "candidates resolution gaussians steps seconds visibility reference rectifier "
                   "masks)")
    s.add_argument("--presets", nargs="*", default=None, help="presets as labelled points")
    s.add_argument("--preset-set", action="append", default=[], metavar="PRESET:KEY=VALUE",
                   help="override a field of a preset's labelled point, e.g. cpu:recon.max_seconds=60")
    s.add_argument("--sizing", nargs="*", default=None,
                   help="knobs compared adaptive vs half vs double (grid_r gaussians resolution "
                   "candidates steps)")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a PipelineConfig field of every point")
    s.add_argument("--real-knobs", choices=["all", "recon"], default=None,
                   help="on real scenes sweep all knobs or only those that change the "
                   "reconstruction (held-out PSNR)")
    s.add_argument("--true-psnr", type=float, default=None, help="dB for a free view to be true")
    s.add_argument("--eval-long-side", type=int, default=None, metavar="PX",
                   help="held-out PSNR/SSIM of every point at this long side per scene "
                   "(default 512; never upscaled)")
    s.add_argument("--downstream", nargs="*", default=None, choices=["refine"],
                   help="downstream gain per point: refine = 3DGS refinement with vs without "
                   "the free views (cached with the point)")
    s.add_argument("--refine-steps", type=int, default=None, help="refinement steps per arm "
                   "(default 150)")
    s.add_argument("--refine-seeds", nargs="+", type=int, default=None,
                   help="refinement seeds (default 0)")
    s.add_argument("--refine-set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a RefineConfig field of the comparison, e.g. "
                   "recon.max_long_side=64")
    s.add_argument("--seeds", nargs="+", type=int, default=None,
                   help="run every point once per pipeline seed; means and spread are shown")
    s.add_argument("--quick", action="store_true", help="tiny scene, tiny budgets, two knob "
                   "values and the fast preset (minutes)")
    s.set_defaults(fn=cmd_evaluate)


def cmd_evaluate(a) -> int:
    from flows.evaluate_engine import evaluate_engine
    from freescale_core.eval.sweep import quick_config
    from schemas.evaluate import EvaluateConfig

    base = quick_config().model_dump() if a.quick else {}
    scenes = a.scenes or (["proc:tiny"] if a.quick else [])
    if not scenes:
        print("error: name at least one scene (or use --quick)", file=sys.stderr)
        return 2
    if a.preset:
        base["preset"] = a.preset
    if a.set:
        base["overrides"] = _deep_merge_dicts(base.get("overrides", {}), _parse_set(a.set))
    knobs = dict(base.get("knobs", {}))
    for k in a.knob:
        name, _, vals = k.partition("=")
        knobs[name.strip()] = [_knob_value(v) for v in vals.split(",") if v.strip()]
    base["knobs"] = knobs
    po = dict(base.get("preset_overrides", {}))
    for item in a.preset_set:
        preset, _, kv = item.partition(":")
        po[preset] = _deep_merge_dicts(po.get(preset, {}), _parse_set([kv]))
    base["preset_overrides"] = po
    # options given on the command line replace the (quick) defaults: argument -> field
    for arg, field in (("presets", "presets"), ("sizing", "sizing"),
                       ("true_psnr", "true_psnr_db"), ("real_knobs", "real_knobs"),
                       ("eval_long_side", "eval_long_side"), ("downstream", "downstream"),
                       ("refine_steps", "refine_steps"), ("refine_seeds", "refine_seeds"),
                       ("seeds", "seeds")):
        if getattr(a, arg) is not None:
            base[field] = getattr(a, arg)
    if a.refine_set:
        base["refine_overrides"] = _parse_set(a.refine_set)
    try:
        cfg = EvaluateConfig.model_validate(base)
    except ValueError as e:
        print(f"error: invalid evaluation config: {_one_line_validation(e)}", file=sys.stderr)
        return 2
    err = _evaluate_preflight(scenes, cfg)
    if err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    r = evaluate_engine(scenes=scenes, out=a.out, config=cfg)
    print(f"{r['n_points']} points ({len(r['computed'])} computed, {len(r['cached'])} cached)")
    for k, v in r["files"].items():
        print(f"  {k}: {v}")
    for s in r["skipped"]:
        print(f"  skipped: {s}")
    print(f"  tables: {Path(a.out) / 'tables.md'}")
    return 0


def _evaluate_preflight(scenes: list[str], cfg) -> str | None:
    """Everything ``evaluate`` can check before the flow starts (no Prefect server, no
    traceback): the scene names, the seeds, the presets of ``--preset-set``, a ``preset``
    given through ``--set``, and every point's config (knob names and values, ``--set``
    keys). None when fine."""
    from freescale_core.eval.real_variants import is_family
    from freescale_core.eval.scenes import _SPECS
    from freescale_core.eval.sweep import plan_points

    for s in scenes:
        if s.startswith("proc:"):
            name = s[5:]
            if name not in _SPECS and name not in ("sizes", "failures"):
                return (f"unknown evaluation scene {s!r}; expected proc: with one of "
                        f"{['sizes', 'failures', *_SPECS]}")
        elif s.startswith("real:"):
            _, _, family = s[5:].partition("@")
            if family and not is_family(family):
                return (f"unknown real-scene family {family!r} in {s!r}; expected few<N>, dark, "
                        "rotnoise<deg>, transnoise<frac> or failures")
    bad = [x for x in [*cfg.seeds, *cfg.refine_seeds] if x < 0]
    if bad:
        return f"seeds must be >= 0, got {bad}"
    if "preset" in cfg.overrides:
        return (f"--set preset={cfg.overrides['preset']} is not a field of a point: use "
                "--preset (the base point) or --presets (labelled points)")
    extra = sorted(set(cfg.preset_overrides) - set(cfg.presets))
    if extra:
        return (f"--preset-set names preset(s) {extra} that are not in --presets "
                f"{cfg.presets}: add them to --presets, or --set for every point")
    try:
        plan_points([Path(".")], cfg)
    except ValueError as e:  # an unknown knob, a bad knob value, a bad --set
        return f"invalid evaluation point: {_one_line_validation(e)}"
    return None


def _knob_value(v: str):
    v = v.strip()
    for t in (int, float):
        try:
            return t(v)
        except ValueError:
            pass
    return v


def _deep_merge_dicts(a: dict, b: dict) -> dict:
    from schemas.pipeline import _deep_merge

    return _deep_merge(a, b)
