"""The package's layout rules (issue 29), checked on the source with `ast`:

* no module uses another module's underscore name (``from .m import _x`` or ``m._x`` on
  an imported module): a helper shared across files gets a public name;
* a subpackage's private modules (``arith._tape``) are imported only inside it; other
  subpackages take what its ``__init__`` exports (the root's private modules, ``_core``,
  ``_lanes``, are the package's shared floor);
* no import circle among jaxiso's modules (imports inside functions count);
* no function longer than MAX_LINES lines.

The allow-lists name what is left, each with its owner; they only shrink.
"""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "jaxiso"
MAX_LINES = 60

# (file, name): private names still crossing files
ALLOWED_PRIVATE: set = set()

# functions longer than MAX_LINES, left to shorten (file, name)
ALLOWED_LONG: set = set()


def _modules():
    return {p: ast.parse(p.read_text()) for p in sorted(ROOT.rglob("*.py"))}


def _name(path: pathlib.Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _target(path, node):
    """The dotted jaxiso module an ImportFrom names (relative imports resolved)."""
    package = list(path.relative_to(ROOT.parent).with_suffix("").parts)[:-1]
    if path.name == "__init__.py":
        package = list(path.relative_to(ROOT.parent).parts)[:-1]
    base = package[:len(package) - node.level + 1] if node.level else []
    return ".".join(base + (node.module.split(".") if node.module else []))


def _private_uses(path, tree):
    """(name, line) of every underscore name this file takes from another module."""
    modules = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            for a in node.names:
                if _is_private(a.name) and not _is_module(path, node, a.name):
                    yield a.name, node.lineno
                modules.add(a.asname or a.name)
        elif isinstance(node, ast.Import):
            modules.update((a.asname or a.name).split(".")[0] for a in node.names)
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and _is_private(node.attr)
                and isinstance(node.value, ast.Name) and node.value.id in modules
                and not _is_module_path(path, node.value.id, node.attr)):
            yield node.attr, node.lineno


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _is_module(path, node, name) -> bool:
    """Whether ``from X import name`` imports a submodule (private modules are fine)."""
    module = _target(path, node).split(".")
    return (ROOT.parent.joinpath(*module, name + ".py").exists()
            or ROOT.parent.joinpath(*module, name, "__init__.py").exists())


def _is_module_path(path, alias, attr) -> bool:
    """``jaxiso._lanes``, ``arith._tape`` and the like: a package's module."""
    package = ROOT if alias == "jaxiso" else ROOT / alias
    return (package / "__init__.py").exists() and (package / (attr + ".py")).exists()


def _graph(modules):
    """module -> the jaxiso modules it imports (anywhere in the file)."""
    graph = {}
    for path, tree in modules.items():
        me = ".".join(path.relative_to(ROOT.parent).with_suffix("").parts)
        me = me.removesuffix(".__init__")
        deps = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.level or (
                    node.module or "").startswith("jaxiso")):
                target = _target(path, node)
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    deps.add(sub if _is_module(path, node, a.name) else target)
        graph[me] = {d for d in deps if d != me}
    return graph


def _cycle(graph):
    """One import circle as a list of modules, or None."""
    state = {}

    def visit(m, stack):
        state[m] = "open"
        for d in sorted(graph.get(m, ())):
            if d not in graph or _is_package_of(d, m):
                continue
            if state.get(d) == "open":
                return stack[stack.index(d):] + [d] if d in stack else [m, d]
            if d not in state:
                found = visit(d, stack + [d])
                if found:
                    return found
        state[m] = "done"
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m, [m])
            if found:
                return found
    return None


def _is_package_of(package, module) -> bool:
    """A package's __init__ imports its modules, which import their siblings through
    the package: not a circle between modules."""
    return module.startswith(package + ".")


@pytest.fixture(scope="module")
def modules():
    return _modules()


def test_no_private_name_crosses_files(modules):
    found = sorted({(_name(p), n, line) for p, t in modules.items()
                    for n, line in _private_uses(p, t) if (_name(p), n) not in ALLOWED_PRIVATE})
    assert not found, f"private names used across files: {found}"


def _foreign_private_modules(path, tree):
    """(module, line) of every private module of another subpackage this file imports."""
    mine = path.relative_to(ROOT).parts[:-1]
    for node in ast.walk(tree):
        if not isinstance(node, ast.ImportFrom) or not (node.level or (
                node.module or "").startswith("jaxiso")):
            continue
        target = _target(path, node).split(".")
        dotted = [target + [a.name] for a in node.names if _is_module(path, node, a.name)]
        for parts in dotted + [target]:
            inner = parts[1:]  # under jaxiso
            for k, part in enumerate(inner):
                if k >= 1 and _is_private(part) and tuple(inner[:k]) != mine[:k]:
                    yield ".".join(parts), node.lineno


def test_no_subpackage_reaches_into_anothers_private_modules(modules):
    found = sorted({(_name(p), m, line) for p, t in modules.items()
                    for m, line in _foreign_private_modules(p, t)})
    assert not found, f"private modules of another subpackage imported: {found}"


def test_no_import_circle(modules):
    assert _cycle(_graph(modules)) is None, _cycle(_graph(modules))


def test_functions_are_short(modules):
    long = sorted((_name(p), n.name, n.end_lineno - n.lineno + 1)
                  for p, t in modules.items() for n in ast.walk(t)
                  if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)
                  and n.end_lineno - n.lineno + 1 > MAX_LINES
                  and (_name(p), n.name) not in ALLOWED_LONG)
    assert not long, f"functions over {MAX_LINES} lines: {long}"


def test_allow_lists_hold_only_what_is_still_there(modules):
    """An entry fixed must leave its allow-list (so the lists only shrink)."""
    private = {(_name(p), n) for p, t in modules.items() for n, _ in _private_uses(p, t)}
    long = {(_name(p), n.name) for p, t in modules.items() for n in ast.walk(t)
            if isinstance(n, ast.FunctionDef) and n.end_lineno - n.lineno + 1 > MAX_LINES}
    assert not ALLOWED_PRIVATE - private, sorted(ALLOWED_PRIVATE - private)
    assert not ALLOWED_LONG - long, sorted(ALLOWED_LONG - long)
