"""The layers hold: freescale_core imports nothing above it, and no module imports itself
back through a cycle."""

from __future__ import annotations

from freescale_core.codekey import module_imports as _walk


def _module_imports() -> dict[str, set[str]]:
    """Every project module -> the project modules it imports (at any depth of the file):
    the walk stage keys hash (freescale_core.codekey)."""
    return _walk()


def test_core_imports_nothing_above_it():
    bad = {m: sorted(d for d in ds if d.split(".")[0] in ("tasks", "flows"))
           for m, ds in _module_imports().items() if m.startswith("freescale_core")}
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
