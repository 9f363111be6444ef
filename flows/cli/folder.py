"""``freescale sample-scene DIR`` and ``freescale inspect SCENE_DIR``: commands on one scene folder."""

from __future__ import annotations

import json
import sys
import time

from flows.cli.common import _console, _fmt


def add_parsers(sub) -> None:
    s = sub.add_parser("sample-scene", help="write the embedded procedural sample scene")
    s.add_argument("dir")
    s.add_argument("--views", type=int, default=36, help="captured views")
    s.add_argument("--width", type=int, default=256, help="image width (px)")
    s.add_argument("--height", type=int, default=192, help="image height (px)")
    s.add_argument("--seed", type=int, default=0, help="scene seed")
    s.set_defaults(fn=cmd_sample_scene)

    s = sub.add_parser("inspect", help="describe a scene folder without processing it")
    s.add_argument("scene_dir")
    s.add_argument("--json", action="store_true")
    s.set_defaults(fn=cmd_inspect)


def cmd_sample_scene(a) -> int:
    from freescale_core.scene.sample import write_sample_scene

    t0 = time.perf_counter()
    try:
        p = write_sample_scene(a.dir, n_views=a.views, width=a.width, height=a.height,
                               seed=a.seed)
    except ValueError as e:  # e.g. --views 1: "n_views must be >= 2"
        print(f"error: sample scene {a.dir}: {e}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: sample scene {a.dir} cannot be written: {e.strerror or e}"
              f"{f' ({e.filename})' if getattr(e, 'filename', None) else ''}", file=sys.stderr)
        return 2
    print(f"sample scene written to {p} ({a.views} views, {a.width}x{a.height}) "
          f"in {time.perf_counter() - t0:.1f} s")
    return 0


def cmd_inspect(a) -> int:
    from freescale_core.errors import SceneError
    from freescale_core.scene.describe import inspect_scene

    try:
        info = inspect_scene(a.scene_dir)
    except SceneError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if a.json:
        print(json.dumps(info, indent=2, default=str))
        return 0
    from rich.table import Table

    from rich.markup import escape

    t = Table(title=escape(f"scene {info.get('scene_id', a.scene_dir)}"), show_header=False)
    for k, v in info.items():
        t.add_row(_fmt(k), _fmt(json.dumps(v, default=str)) if isinstance(v, (list, dict)) else _fmt(v))
    _console().print(t)
    return 0
