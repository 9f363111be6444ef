"""``freescale serve``: a local Prefect server serving the deployments."""

from __future__ import annotations

import os


def add_parsers(sub) -> None:
    s = sub.add_parser("serve", help="start a local Prefect server and serve the deployments")
    s.add_argument("--port", type=int, default=int(os.environ.get("PREFECT_PORT", 4200)))
    s.set_defaults(fn=cmd_serve)


def cmd_serve(a) -> int:
    from flows.serve import main as serve_main

    return serve_main(port=a.port)
