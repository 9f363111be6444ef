"""``freescale config show|fields``, and the help built from the pydantic configs: every field
of :class:`~schemas.pipeline.PipelineConfig` with its type, its default in each preset and its
one-line description.

Used by ``freescale run --help`` (the epilog), ``freescale config fields`` and
``docs/CONFIG.md`` (``python -m flows.cli.config --markdown > docs/CONFIG.md``), so the
three can never disagree with the schemas.
"""

from __future__ import annotations

import json
import sys
import typing
from dataclasses import dataclass
from typing import Any, Iterator

from pydantic import BaseModel

from flows.cli.common import _Fmt, _console, _parse_set

__all__ = ["FieldDoc", "iter_fields", "field_docs", "help_epilog", "config_markdown",
           "one_line", "add_parsers"]

PRESET_ORDER = ("paper", "cpu", "fast")


@dataclass(frozen=True)
class FieldDoc:
    name: str            # dotted path, as --set takes it
    type: str
    defaults: dict       # preset -> default value (JSON-able)
    doc: str             # the schema's description


def _type_name(ann: Any) -> str:
    origin = typing.get_origin(ann)
    if origin is typing.Literal:
        return "{" + ",".join(str(a) for a in typing.get_args(ann)) + "}"
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)):
        return " | ".join(_type_name(a) for a in typing.get_args(ann))
    if origin is not None:
        args = ", ".join(_type_name(a) for a in typing.get_args(ann))
        return f"{getattr(origin, '__name__', str(origin))}[{args}]"
    if ann is type(None):
        return "None"
    return getattr(ann, "__name__", str(ann))


def _is_model(ann: Any) -> bool:
    return isinstance(ann, type) and issubclass(ann, BaseModel)


def iter_fields(model: type[BaseModel], prefix: str = "") -> Iterator[tuple[str, Any, str]]:
    """``(dotted name, annotation, description)`` of every leaf field, in declaration order."""
    for k, f in model.model_fields.items():
        if _is_model(f.annotation):
            yield from iter_fields(f.annotation, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", f.annotation, (f.description or "")


def _get(d: dict, dotted: str):
    for p in dotted.split("."):
        d = d[p]
    return d


def field_docs() -> list[FieldDoc]:
    from schemas.pipeline import PipelineConfig

    dumps = {p: PipelineConfig.from_preset(p).model_dump(mode="json") for p in PRESET_ORDER}
    return [FieldDoc(name, _type_name(ann), {p: _get(dumps[p], name) for p in PRESET_ORDER}, doc)
            for name, ann, doc in iter_fields(PipelineConfig)]


def one_line(doc: str, width: int = 110) -> str:
    """The description's first sentence, at most ``width`` characters."""
    doc = " ".join(doc.split())
    for stop in (". ", "; "):
        if stop in doc:
            doc = doc.split(stop, 1)[0]
    return doc if len(doc) <= width else doc[: width - 3].rstrip() + "..."


def _v(x) -> str:
    return json.dumps(x) if not isinstance(x, str) else x


def _default_text(f: FieldDoc, preset: str) -> str:
    main = f.defaults[preset]
    others = [f"{p}: {_v(f.defaults[p])}" for p in PRESET_ORDER
              if p != preset and f.defaults[p] != main]
    return f"default: {_v(main)}" + (f" ({'; '.join(others)})" if others else "")


def help_epilog(preset: str = "cpu") -> str:
    """Every config field, one line each, for ``--help`` (defaults of ``preset``)."""
    lines = [f"config fields (--set KEY=VALUE; defaults of the '{preset}' preset, other presets "
             "in parentheses where they differ; docs/CONFIG.md has the measurements):"]
    for f in field_docs():
        lines.append(f"  {f.name} ({f.type}, {_default_text(f, preset)})")
        lines.append(f"      {one_line(f.doc)}")
    return "\n".join(lines)


def config_markdown() -> str:
    """``docs/CONFIG.md``: every field, its default per preset and its one-line doc."""
    out = ["# Configuration reference", "",
           "Generated from `schemas/` by `python -m flows.cli.config --markdown > docs/CONFIG.md`",
           "(a test checks it is current). Set any field with `--set KEY=VALUE` on `freescale run`",
           "or in a deployment's `config` parameter; `freescale config show --preset P --set ...`",
           "prints the resolved config. Preset `auto` (the default) is `paper` where CUDA is",
           "present and `cpu` otherwise. Measurements and the reasons behind the defaults are in",
           "[RECON.md](RECON.md), [SELECTION.md](SELECTION.md), [FIDELITY.md](FIDELITY.md) and",
           "[CONFIG_NOTES.md](CONFIG_NOTES.md).", ""]
    section = None
    for f in field_docs():
        top = f.name.split(".")[0] if "." in f.name else "pipeline"
        if top != section:
            section = top
            out += ["", f"## `{top}`", "", "| field | type | paper | cpu | fast | doc |",
                    "|---|---|---|---|---|---|"]
        cells = [f"`{f.name}`", f.type.replace("|", "\\|")]
        cells += [f"`{_v(f.defaults[p])}`".replace("|", "\\|") for p in PRESET_ORDER]
        cells.append(one_line(f.doc, 200).replace("|", "\\|"))
        out.append("| " + " | ".join(cells) + " |")
    return "\n".join(out) + "\n"


def add_parsers(sub) -> None:
    from schemas.pipeline import PRESET_CHOICES

    cf = sub.add_parser("config", help="the pipeline config: resolved values, every field"
                        ).add_subparsers(dest="sub", required=True)
    s = cf.add_parser("show", help="print the resolved config of a preset + overrides",
                      formatter_class=_Fmt)
    s.add_argument("--preset", choices=PRESET_CHOICES, default="auto",
                   help="auto: paper with CUDA, cpu without")
    s.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="override a field, as for run")
    s.add_argument("--json", action="store_true", help="JSON instead of YAML")
    s.set_defaults(fn=cmd_config_show)
    s = cf.add_parser("fields", help="every config field: type, default per preset, doc",
                      formatter_class=_Fmt)
    s.add_argument("--json", action="store_true", help="one JSON object per field")
    s.set_defaults(fn=cmd_config_fields)


def cmd_config_show(a) -> int:
    from schemas.pipeline import PipelineConfig

    try:
        cfg = PipelineConfig.from_preset(a.preset, _parse_set(a.set))
    except ValueError as e:
        print(f"error: invalid config: {e}", file=sys.stderr)
        return 2
    d = cfg.model_dump(mode="json")
    if a.json:
        print(json.dumps(d, indent=2))
        return 0
    import yaml

    head = f"# preset {a.preset} -> {cfg.preset}" if a.preset == "auto" else f"# preset {cfg.preset}"
    print(head + (f", overrides {_parse_set(a.set)}" if a.set else ""))
    class _Dumper(yaml.SafeDumper):  # block mappings, short lists on one line
        pass

    _Dumper.add_representer(list, lambda dm, v: dm.represent_sequence(
        "tag:yaml.org,2002:seq", v, flow_style=True))
    print(yaml.dump(d, Dumper=_Dumper, sort_keys=False, width=100).rstrip())
    return 0


def cmd_config_fields(a) -> int:
    docs = field_docs()
    if a.json:
        for f in docs:
            print(json.dumps({"name": f.name, "type": f.type, "defaults": f.defaults,
                              "doc": f.doc}))
        return 0
    from rich.table import Table

    t = Table(title=f"{len(docs)} config fields (--set KEY=VALUE); docs/CONFIG.md")
    t.add_column("field", no_wrap=True)
    for c in ("type", "paper", "cpu", "fast"):
        t.add_column(c, overflow="fold", max_width=22)
    t.add_column("doc", overflow="fold", min_width=50)
    for f in docs:
        t.add_row(f.name, f.type, *[json.dumps(f.defaults[p]) for p in ("paper", "cpu", "fast")],
                  one_line(f.doc))
    _console().print(t)
    return 0


if __name__ == "__main__":
    if "--markdown" in sys.argv:
        sys.stdout.write(config_markdown())
    else:
        print(help_epilog())
