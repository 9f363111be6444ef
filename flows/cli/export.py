"""``freescale export FORMAT STORE OUT``: scenes of a store in another tool's format."""

from __future__ import annotations

import sys


def add_parsers(sub) -> None:
    s = sub.add_parser("export", help="export scenes of a store to another tool's format")
    s.add_argument("format", choices=["nerfstudio", "lvsm", "gsplat", "colmap"])
    s.add_argument("store")
    s.add_argument("out")
    s.add_argument("--scenes", nargs="+", default=None, help="scene ids (default: every ok scene)")
    s.add_argument("--free-views", choices=["train", "val"], default="train",
                   help="nerfstudio: free views as extra training views or as val_filenames")
    s.add_argument("--depth", action="store_true", help="nerfstudio: write 16-bit depth PNGs")
    s.add_argument("--overwrite", action="store_true", help="replace an existing OUT")
    s.set_defaults(fn=cmd_export)


def cmd_export(a) -> int:
    from freescale_core.errors import StoreError
    from freescale_core.exports import export

    opts: dict = {"overwrite": a.overwrite}
    if a.format == "nerfstudio":
        opts.update(free_views=a.free_views, depth=a.depth)
    try:
        res = export(a.format, a.store, a.out, a.scenes or None, **opts)
    except (StoreError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # a full disk, a read-only mount: nothing half-written is left
        print(f"error: export to {a.out} failed: {e.strerror or e}"
              f"{f' ({e.filename})' if getattr(e, 'filename', None) else ''}", file=sys.stderr)
        return 2
    print(res.summary())
    return 0
