"""Helpers shared by the command modules: console, table cells, one-line errors, the
help formatter, the version."""

from __future__ import annotations

import argparse
import os

from flows.setargs import parse_set as _parse_set  # noqa: F401  (re-exported for the commands)


def _console():
    from rich.console import Console

    con = Console()
    if not con.is_terminal and "COLUMNS" not in os.environ:
        # piped / logged output: rich would assume 80 columns and wrap every header; a table
        # takes only the width it needs, so a wide limit costs nothing (the manifest view has
        # a dozen columns: at 160 its headers were cut to "scene_…")
        con = Console(width=400)
    return con


def _fmt(v) -> str:
    """A table cell as rich markup: values are escaped (an error ending in ``[/a/path]`` is
    text, not a closing markup tag)."""
    from rich.markup import escape

    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return escape(str(v))


def _one_line_validation(e: Exception) -> str:
    """A pydantic ValidationError (or any ValueError) as one line: each error's field and
    message, joined by '; '."""
    errs = getattr(e, "errors", None)
    if callable(errs):
        try:
            return "; ".join(
                (f"{'.'.join(map(str, x['loc']))}: " if x["loc"] else "")
                + x["msg"].removeprefix("Value error, ")
                + (f" (got {x['input']!r})" if x.get("type") == "extra_forbidden" else "")
                for x in errs())
        except Exception:  # noqa: BLE001 - fall back on the message
            pass
    return " ".join(str(e).split())


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("freescale")
    except Exception:  # noqa: BLE001 - not installed: the engine's own version
        from freescale_core import __version__

        return __version__



class _Fmt(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Defaults in every option's help; the epilog (the config fields) kept as written."""
