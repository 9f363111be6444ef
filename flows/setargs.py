"""``--set key=value`` parsing shared by the CLI modules."""

from __future__ import annotations

import json


def parse_set(items: list[str]) -> dict:
    """``a.b.c=1`` strings -> nested dict; values parsed as JSON when possible."""
    out: dict = {}
    for it in items or []:
        if "=" not in it:
            raise SystemExit(f"--set expects key=value, got {it!r}")
        k, v = it.split("=", 1)
        try:
            val = json.loads(v)
        except json.JSONDecodeError:
            val = v
        d = out
        parts = k.split(".")
        for p in parts[:-1]:
            d = d.setdefault(p, {})
        d[parts[-1]] = val
    return out
