"""The layers hold: freescale_core imports nothing above it, and no module imports itself
back through a cycle."""

from __future__ import annotations

from freescale_core.codekey import REPO, _imports_of, module_files, module_imports


def _raw_imports() -> dict[str, set[str]]:
    """Every product module -> every module name it imports (at any depth of the file)."""
    return {m: _imports_of(m, f) for m, f in module_files().items()}


def _module_imports() -> dict[str, set[str]]:
    """Every project module -> the project modules it imports: the walk stage keys hash."""
    return module_imports()


def test_core_imports_nothing_above_it():
    bad = {m: sorted(d for d in ds if d.split(".")[0] in ("tasks", "flows"))
           for m, ds in _module_imports().items() if m.startswith("freescale_core")}
    assert not {m: d for m, d in bad.items() if d}, bad


def test_product_imports_nothing_from_the_lab():
    """``lab/`` (research scripts, legacy arms, dated results) sits beside the product: no module
    of freescale_core, schemas, tasks or flows imports it, at any depth."""
    bad = {m: sorted(d for d in ds if d.split(".")[0] == "lab") for m, ds in _raw_imports().items()}
    assert not {m: d for m, d in bad.items() if d}, bad


def test_no_import_cycles_between_modules():
    """Cycles through package ``__init__`` files aside (a package importing its own
    submodules is not a cycle of the code), no module reaches itself."""
    g = _module_imports()
    g = {m: {d for d in ds if not m.startswith(d + ".")} for m, ds in g.items()}
    cycles = []
    state: dict[str, int] = {}

    def visit(m, stack):
        state[m] = 1
        for d in sorted(g.get(m, ())):
            if state.get(d) == 1:
                cycles.append(stack[stack.index(d):] + [d] if d in stack else [m, d])
            elif d not in state:
                visit(d, stack + [d])
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m, [m])
    assert not cycles, cycles


# The layers of freescale_core, lowest first (docs/ARCHITECTURE.md): a module may import its own
# package and any package of a lower layer, never one above. Packages in one tuple are peers.
CORE_LAYERS = (
    ("errors", "threads", "files", "codekey", "geometry", "raster"),
    ("scene",),
    ("recon",),
    ("select", "fixer"),
    ("freeviews",),
    ("store",),
    ("exports",),
    ("downstream",),
    ("eval",),
)
_RANK = {pkg: i for i, layer in enumerate(CORE_LAYERS) for pkg in layer}


def _core_package(mod: str) -> str | None:
    parts = mod.split(".")
    return parts[1] if parts[0] == "freescale_core" and len(parts) > 1 else None


def upward_imports() -> dict[str, list[str]]:
    """freescale_core module -> the freescale_core modules above its layer that it imports."""
    out = {}
    for m, ds in _module_imports().items():
        p = _core_package(m)
        if p is None:
            continue
        up = sorted(d for d in ds if _core_package(d) is not None
                    and _RANK[_core_package(d)] > _RANK[p])
        if up:
            out[m] = up
    return out


def test_every_core_package_has_a_layer():
    pkgs = {f.parent.name if f.name == "__init__.py" else f.stem
            for f in (REPO / "freescale_core").glob("*") if not f.name.startswith("_")
            and (f.suffix == ".py" or (f / "__init__.py").is_file())}
    assert pkgs - {"data"} <= set(_RANK), sorted(pkgs - set(_RANK))


def test_no_import_runs_up_the_layers():
    """scene/geometry/raster < recon < select < freeviews < store < exports < downstream < eval:
    shared helpers live in the layer below their users (e.g. ``scene.images.resize_area``,
    ``scene.oracle``, ``store.scene_views``), with re-exports under the old names."""
    assert not upward_imports(), upward_imports()
