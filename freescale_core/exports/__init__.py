"""Exports of a store to other tools' formats, one module per target tool:
:mod:`.nerfstudio`, :mod:`.lvsm`, :mod:`.gsplat`, :mod:`.colmap` (see ``docs/DATASET.md``).
Each ``export(store_root, out, scenes=None, ..., overwrite=False) -> ExportResult`` builds
``out`` in a temporary folder and renames it into place.
"""

FORMATS = ("nerfstudio", "lvsm", "gsplat", "colmap")


def export(fmt: str, store_root, out, scenes=None, **opts):
    """Run the exporter of ``fmt`` (one of :data:`FORMATS`)."""
    import importlib

    if fmt not in FORMATS:
        raise ValueError(f"unknown export format {fmt!r}; expected one of {FORMATS}")
    mod = importlib.import_module(f"freescale_core.exports.{fmt}")
    return mod.export(store_root, out, scenes, **opts)
