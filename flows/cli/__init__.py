"""``freescale`` command line: sample scene, inspect, run, resume, browse scenes, training
shards, export, config, report, the downstream flows (refine, train-lvsm), serve."""

# One module per command group, each with ``add_parsers(sub)`` and its ``cmd_*`` functions:
# folder (sample-scene, inspect), run (run, resume), scenes, shards, export, config, report,
# refine, lvsm (train-lvsm), fixer (train-fixer, fixer pairs|score), evaluate, serve.
# This module holds the entry point and the wiring only.

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DO_NOT_TRACK", "1")
# the temporary API server of a local run starts slowly on a loaded 2-core machine
os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")

from flows.cli.common import _Fmt, _parse_set, _version  # noqa: E402, F401  (_parse_set: re-exported)

__all__ = ["build_parser", "main"]


def build_parser() -> argparse.ArgumentParser:
    from flows.cli import (config, evaluate, export, fixer, folder, lvsm, refine, report, run,
                           scenes, serve, shards)

    p = argparse.ArgumentParser(prog="freescale", description=__doc__, formatter_class=_Fmt)
    p.add_argument("--version", action="version", version=f"freescale {_version()}")
    sub = p.add_subparsers(dest="cmd", required=True)
    _add = sub.add_parser

    def add_parser(name, **kw):  # every sub-command shows its defaults
        kw.setdefault("formatter_class", _Fmt)
        return _add(name, **kw)

    sub.add_parser = add_parser
    # in the order `freescale --help` lists them
    for group in (folder, run, scenes, shards, export, config, report, refine, lvsm):
        group.add_parsers(sub)
    fixer.add_train_fixer_parser(sub)
    evaluate.add_parsers(sub)
    fixer.add_fixer_parser(sub)
    serve.add_parsers(sub)
    return p


# command groups that start no Prefect flow: they skip the reaper, whose import of Prefect's
# server costs seconds (``scenes ls`` of 10,000 scenes: 6-13 s with it, 1.2 s without)
NO_FLOWS = frozenset(f"flows.cli.{m}" for m in ("scenes", "shards", "export", "config", "folder"))


def main(argv: list[str] | None = None) -> int:
    a = build_parser().parse_args(argv)
    if a.fn.__module__ not in NO_FLOWS:
        from flows.reaper import install

        install()  # a temporary Prefect server dies with this process, even after SIGKILL
    try:
        return int(a.fn(a) or 0)
    except BrokenPipeError:  # `freescale scenes show ... | head`: the reader left
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
