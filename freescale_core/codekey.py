"""Cache keys derived from the code: the one scheme for every cached thing.

A cached result (a stage checkpoint, an evaluate-engine sweep point, a held-out score, a
refinement arm) depends on the source of every project module its entry point imports,
directly or through other project modules, at any depth of a file (imports inside functions
too), plus the versions of the libraries that compute it. :func:`code_key` hashes exactly
that, so an edit anywhere a stage reaches invalidates the stage (and, through the upstream
keys, everything after it) and an edit it does not reach leaves it alone. Module lists are
never typed by hand.

The import graph is read with :mod:`ast` from the files (nothing is imported), the same walk
``tests/test_imports.py`` uses to hold the layers.
"""

from __future__ import annotations

import ast
import hashlib
from importlib import metadata
from pathlib import Path
from typing import Iterable

REPO = Path(__file__).resolve().parents[1]
LAYERS = ("freescale_core", "schemas", "tasks", "flows")
# the libraries whose version changes a computed number (rasterizer kernels, autograd, SfM)
DEPENDENCIES = ("torch", "numba", "pycolmap")

__all__ = ["DEPENDENCIES", "LAYERS", "REPO", "clear_cache", "code_key", "dependency_versions",
           "module_files", "module_imports", "reached"]


def module_files(root: Path = REPO) -> dict[str, Path]:
    """Every project module under ``root`` -> its file (``pkg`` -> ``pkg/__init__.py``)."""
    out: dict[str, Path] = {}
    for top in LAYERS:
        for f in sorted((Path(root) / top).rglob("*.py")):
            parts = list(f.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = f
    return out


def _imports_of(name: str, f: Path) -> set[str]:
    """Every dotted name module ``name`` (file ``f``) imports, anywhere in the file."""
    parts = name.split(".")
    is_pkg = f.name == "__init__.py"
    deps: set[str] = set()
    for node in ast.walk(ast.parse(f.read_text(), filename=str(f))):
        if isinstance(node, ast.Import):
            deps.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = parts if is_pkg else parts[:-1]
                base = base[:len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            deps.add(mod)
            deps.update(f"{mod}.{a.name}" for a in node.names)
    return deps


_GRAPHS: dict[str, dict[str, set[str]]] = {}


def module_imports(root: Path = REPO) -> dict[str, set[str]]:
    """Every project module -> the project modules it imports (at any depth of the file)."""
    key = str(Path(root).resolve())
    if key not in _GRAPHS:
        files = module_files(root)
        known = set(files)
        _GRAPHS[key] = {m: {d for d in _imports_of(m, f) if d in known and d != m}
                        for m, f in files.items()}
    return _GRAPHS[key]


def _parents(name: str) -> list[str]:
    """``a.b.c`` -> ``a``, ``a.b``: the packages whose ``__init__`` importing it runs."""
    p = name.split(".")
    return [".".join(p[:i]) for i in range(1, len(p))]


def reached(roots: Iterable[str], root: Path = REPO) -> set[str]:
    """The project modules importing ``roots`` runs: the roots, what they import
    transitively, and every package ``__init__`` on the way."""
    g = module_imports(root)
    todo = [m for r in roots for m in (*_parents(r), r)]
    missing = [r for r in roots if r not in g]
    if missing:
        raise ValueError(f"code key: no project module {missing} under {root}")
    seen: set[str] = set()
    while todo:
        m = todo.pop()
        if m in seen or m not in g:
            continue
        seen.add(m)
        for d in g[m]:
            todo.extend((*_parents(d), d))
    return seen


def dependency_versions() -> dict[str, str]:
    """Installed versions of :data:`DEPENDENCIES` (``"absent"`` when not installed)."""
    out = {}
    for d in DEPENDENCIES:
        try:
            out[d] = metadata.version(d)
        except metadata.PackageNotFoundError:
            out[d] = "absent"
    return out


_KEYS: dict[tuple, str] = {}


def code_key(roots: Iterable[str], root: Path = REPO) -> str:
    """Hash of the source of every project module ``roots`` reach (:func:`reached`) and of
    :func:`dependency_versions`: 16 hex digits, cached per process.

    Args:
        roots: the entry-point modules of the cached computation (dotted names).
        root: the tree to read (the installed one by default; a copy in tests).
    """
    roots = tuple(sorted(set(roots)))
    ck = (roots, str(Path(root).resolve()))
    if ck not in _KEYS:
        from freescale_core import __version__

        files = module_files(root)
        h = hashlib.sha256(__version__.encode())
        for m in sorted(reached(roots, root)):
            h.update(m.encode() + b"\0")
            h.update(files[m].read_bytes())
        for d, v in sorted(dependency_versions().items()):
            h.update(f"{d}={v}\0".encode())
        _KEYS[ck] = h.hexdigest()[:16]
    return _KEYS[ck]


def clear_cache() -> None:
    """Forget the import graphs and keys read so far (a process that edits a tree: tests)."""
    _GRAPHS.clear()
    _KEYS.clear()
