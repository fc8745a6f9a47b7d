"""The rules of the house (docs/design.md, "Layers"), checked on the source: each layer imports
only from the layers below it, no package-internal import hides inside a function (except the
CLI's per-command imports and a package's lazy ``__getattr__``), and no private name crosses a
module boundary."""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "octomerge_jax"

# lowest first; a module may import its own layer and the ones below
LAYERS = [
    ("core", ["_ops", "_sort", "_fileutil", "types", "se3", "morton", "map", "tree", "leaf_index", "hostmem",
              "budget", "kernel_store"]),
    ("kernels", ["updates", "insert", "resample", "fusion"]),
    ("side", ["io", "sim", "examples"]),
    ("solvers", ["registration"]),
    ("pipeline", ["pipeline"]),
    ("apps", ["cli", "viewer", "__init__", "__main__"]),
]
LAYER_OF = {name: i for i, (_, names) in enumerate(LAYERS) for name in names}


def _modules():
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE.parent).with_suffix("")
        yield path, list(rel.parts)


def _top(parts):
    """The first component below the package: the concept a module belongs to."""
    return parts[1] if len(parts) > 1 else "__init__"


def _resolve(parts, node: ast.ImportFrom):
    """Absolute module path of a relative (or absolute) import inside the package, or None."""
    if node.level == 0:
        mod = (node.module or "").split(".")
        return mod if mod[0] == PACKAGE.name else None
    base = parts[:-1] if parts[-1] != "__init__" else parts[:-1]
    base = base[: len(base) - (node.level - 1)]
    return base + (node.module.split(".") if node.module else [])


def _imports(tree):
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            yield node


def _functions(tree):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node


def test_layers_import_only_downwards():
    bad = []
    for path, parts in _modules():
        here = LAYER_OF.get(_top(parts))
        assert here is not None, f"{path}: module not assigned to a layer in tests/test_house.py"
        for node in _imports(ast.parse(path.read_text())):
            target = _resolve(parts, node)
            if target is None or len(target) < 2:
                continue
            names = [target[1]] if len(target) > 1 else [a.name for a in node.names]
            for name in names:
                there = LAYER_OF.get(name)
                if there is not None and there > here:
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} imports {'.'.join(target)}")
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_no_package_imports_inside_functions():
    bad = []
    for path, parts in _modules():
        tree = ast.parse(path.read_text())
        for fn in _functions(tree):
            if parts[1] == "cli" or (parts[-1] == "__init__" and fn.name == "__getattr__"):
                continue  # per-command lazy imports keep `octomerge --help` fast
            for node in ast.walk(fn):
                if isinstance(node, ast.ImportFrom) and _resolve(parts, node) is not None:
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} in {fn.name}()")
                elif isinstance(node, ast.Import) and any(a.name.startswith(PACKAGE.name) for a in node.names):
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} in {fn.name}()")
    assert not bad, "function-level package imports:\n" + "\n".join(bad)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_private_name_crosses_a_module_boundary():
    """``from .x import _y`` and ``x._y`` are refused. A private module ``pkg/_m.py`` may be
    imported by the modules of ``pkg`` and below it (``fuse/_pair.py`` by ``fuse/__init__.py``;
    ``_ops.py`` by the whole package)."""
    bad = []
    for path, parts in _modules():
        where = path.relative_to(PACKAGE.parent)
        tree = ast.parse(path.read_text())
        modules = set()
        for node in _imports(tree):
            target = _resolve(parts, node)
            if target is None:
                continue
            for a in node.names:
                full = target + [a.name] if _private(a.name) and not node.module else target
                for i, part in enumerate(full):
                    if i and _private(part) and full[:i] != parts[:i]:
                        bad.append(f"{where}:{node.lineno} imports {'.'.join(full)}")
                if _private(a.name) and node.module:
                    bad.append(f"{where}:{node.lineno} imports {a.name} from {'.'.join(target)}")
                modules.add(a.asname or a.name)
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and _private(node.attr) and isinstance(node.value, ast.Name)
                    and node.value.id in modules):
                bad.append(f"{where}:{node.lineno} reads {node.value.id}.{node.attr}")
    assert not bad, "private names across modules:\n" + "\n".join(sorted(set(bad)))


@pytest.mark.parametrize("module", ["octomerge_jax", "octomerge_jax.registration", "octomerge_jax.sim",
                                    "octomerge_jax.io"])
def test_all_names_resolve(module):
    import importlib

    m = importlib.import_module(module)
    missing = [n for n in m.__all__ if not hasattr(m, n)]
    assert not missing, f"{module}.__all__ names that do not resolve: {missing}"


def test_no_module_is_hidden_by_a_name_of_its_package():
    """docs/design.md, "Modules not named after their functions": ``package.name`` is the module
    ``package/name.py`` itself, not a function the package re-exports under the module's name (which
    left the module reachable only through ``importlib``)."""
    import importlib

    hidden = []
    for _, parts in _modules():
        if parts[-1] in ("__init__", "__main__") or len(parts) < 2:
            continue
        package = importlib.import_module(".".join(parts[:-1]))
        module = importlib.import_module(".".join(parts))
        if getattr(package, parts[-1], module) is not module:
            hidden.append(".".join(parts))
    assert not hidden, f"modules hidden by a name of their package: {hidden}"
