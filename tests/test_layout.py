"""The package layout: subpackages import downwards only, no module import cycles, files of a
size one can hold in one's head, and a small public top level."""
import ast
from pathlib import Path

import ams_torch as at

ROOT = Path(__file__).resolve().parents[1] / "ams_torch"

#: what each subpackage may import (besides itself)
ALLOWED = {
    "geometry": set(),
    "native": set(),
    "solver": {"native"},
    "stages": {"geometry", "solver", "native"},
    "grooms": {"geometry"},
    "sim": {"stages", "solver", "native", "geometry"},
    "apps": {"sim", "stages", "solver", "native", "geometry", "grooms", "top"},
}


def _modules():
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT.parent).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path


def _imports(name: str, path: Path) -> set:
    """Every ams_torch module a file imports, at any level (module or function scope)."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):  # imports only for type checkers do not run
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            node.body = []
    out = set()
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("ams_torch")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.startswith("ams_torch"):
                out.add(mod)
                out |= {f"{mod}.{a.name}" for a in node.names}
    return out


def _group(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in ALLOWED else "top"


def test_subpackages_import_downwards_only():
    known = {m for m, _ in _modules()}
    bad = []
    for name, path in _modules():
        src = _group(name)
        if src == "top":
            continue
        for target in _imports(name, path):
            if target not in known:
                continue  # a name imported from a module, not a module
            dst = _group(target)
            if dst != src and dst not in ALLOWED[src]:
                bad.append(f"{name} -> {target}")
    assert not bad, "imports against the layering:\n" + "\n".join(bad)


def test_no_module_import_cycles():
    known = {m for m, _ in _modules()}
    graph = {name: {t for t in _imports(name, path) if t in known and t != name
                    and not name.startswith(t + ".")}  # a module may import its own package's __init__
             for name, path in _modules()}
    index, low, stack, on_stack, cycles, counter = {}, {}, [], set(), [], [0]

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                cycles.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    assert not cycles, f"import cycles: {cycles}"


def test_no_file_is_too_long():
    long = [f"{p.relative_to(ROOT.parent)} ({n} lines)" for p in ROOT.rglob("*.py")
            if (n := len(p.read_text().splitlines())) > 560]
    assert not long, long


def test_the_top_level_is_small():
    names = [n for n in at.__all__ if n not in ("apps", "geometry", "grooms", "sim", "solver", "stages",
                                                "__version__")]
    assert len(names) <= 13, names
    assert callable(at.native_status) and "cpu" in at.native_status()


def _private_calls(path: Path) -> set:
    """Private names a file calls as an attribute of another object (``obj._name(...)``, not
    ``self``/``cls``/``super()``): a call into another module that no import shows."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            name, owner = node.func.attr, node.func.value
            if not name.startswith("_") or name.startswith("__"):
                continue
            if isinstance(owner, ast.Name) and owner.id in ("self", "cls"):
                continue
            if isinstance(owner, ast.Call) and isinstance(owner.func, ast.Name) and owner.func.id == "super":
                continue
            out.add(name)
    return out


def _defined(path: Path) -> set:
    return {n.name for n in ast.walk(ast.parse(path.read_text()))
            if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}


def test_no_call_cycles_between_modules_of_one_package():
    """Within one package, the dependency graph has no cycle when it counts, besides imports
    (any scope), calls of another module's private functions or methods
    (``recipe._concrete_motion(...)`` from a module that the recipe's module imports): the
    cycles that an import graph alone does not show."""
    modules = dict(_modules())
    defined = {name: _defined(path) for name, path in modules.items()}
    graph = {}
    for name, path in modules.items():
        package = name.rpartition(".")[0] if path.name != "__init__.py" else name
        edges = set(_imports(name, path))
        own = defined[name]
        for called in _private_calls(path) - own:
            edges |= {m for m in modules if m.rpartition(".")[0] == package and called in defined[m]}
        graph[name] = {t for t in edges if t in modules and t != name and t.rpartition(".")[0] == package
                       and not modules[t].name == "__init__.py"}
    cycles = []
    for start in graph:  # a short DFS per module: the packages are small
        stack = [(start, [start])]
        while stack:
            node, trail = stack.pop()
            for nxt in graph[node]:
                if nxt == start:
                    cycles.append(" -> ".join(trail + [start]))
                elif nxt not in trail and len(trail) < 8:
                    stack.append((nxt, trail + [nxt]))
    assert not cycles, "call/import cycles within a package:\n" + "\n".join(sorted(set(cycles))[:20])


def test_library_code_never_imports_the_test_helpers():
    bad = [name for name, path in _modules() if name != "ams_torch.testing"
           and any(t == "ams_torch.testing" or t.startswith("ams_torch.testing.") for t in _imports(name, path))]
    assert not bad, f"library modules importing ams_torch.testing: {bad}"
