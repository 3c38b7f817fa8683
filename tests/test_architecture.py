"""The architecture, read from the source (no import is executed): no import cycle in
``oga``, ``feedplan`` and ``api``; no web or plotting package on the engine's module-level
import path; compiled kernels with few parameters; functions a reader can hold in mind.

An import edge is any ``import``/``from ... import`` statement, at module level or inside a
function (a function-level import hides a cycle, it does not break it), plus the lazy ones:
``importlib.import_module("<literal>")`` and, in a package ``__init__``, the module names of
its lazy maps (``_EXPORTS``). Imports under ``if TYPE_CHECKING:`` are annotations only and
do not count. ``from a import b`` is an edge to ``a.b`` where that is a module, else to ``a``; an import of
the module's own ancestor package (``from oga import __version__`` in ``oga.report``) is none:
Python has initialised it before the module runs.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("oga", "feedplan", "api")
#: The engine: what ``oga optimize`` and the library import.
ENGINE = ("oga", "feedplan")
#: Packages the engine must not import at module level (web servers, plotting, clusters).
FORBIDDEN = ("fastapi", "uvicorn", "starlette", "httpx", "matplotlib", "plotly", "bokeh",
             "dask.distributed", "distributed")
#: Most parameters of a compiled kernel (pack the rest: a parameter array with named offsets,
#: a namedtuple of arrays).
MAX_KERNEL_PARAMS = 10
#: Most lines of a function (def line to last line, decorators not counted).
MAX_FUNCTION_LINES = 80
JIT_DECORATORS = {"njit", "jit", "generated_jit", "vectorize", "guvectorize", "cfunc"}


def _modules() -> dict[str, Path]:
    """Module name -> file, for every ``.py`` file of :data:`PACKAGES`."""
    found = {}
    for package in PACKAGES:
        for f in sorted((ROOT / package).rglob("*.py")):
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = f
    return found


MODULES = _modules()
TREES = {name: ast.parse(f.read_text(), str(f)) for name, f in MODULES.items()}


def _is_type_checking(node: ast.AST) -> bool:
    test = node.test if isinstance(node, ast.If) else None
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _walk(node: ast.AST, in_function: bool = False):
    """(node, inside a function) for every node, leaving out ``if TYPE_CHECKING:`` bodies."""
    for child in ast.iter_child_nodes(node):
        if _is_type_checking(child):
            for sub in child.orelse:
                yield sub, in_function
                yield from _walk(sub, in_function)
            continue
        yield child, in_function
        yield from _walk(child, in_function or isinstance(
            child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)))


def _imported(node: ast.AST, module: str) -> list[str]:
    """The modules (dotted names) an import node or a lazy-import literal names."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    if isinstance(node, ast.ImportFrom):
        if node.level:  # relative: resolve against this module's package
            is_package = MODULES[module].name == "__init__.py"
            base = module.split(".")
            base = base[:len(base) - node.level + (1 if is_package else 0)]
            source = ".".join(base + ([node.module] if node.module else []))
        else:
            source = node.module
        return [f"{source}.{a.name}" if f"{source}.{a.name}" in MODULES else source
                for a in node.names]
    if (isinstance(node, ast.Call) and isinstance(node.func, (ast.Attribute, ast.Name))
            and getattr(node.func, "attr", getattr(node.func, "id", "")) == "import_module"
            and node.args and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)):
        return [node.args[0].value]
    return []


def _lazy_map_targets(module: str) -> list[tuple[int, str]]:
    """(line, module) of the module names in a package ``__init__``'s lazy maps."""
    if MODULES[module].name != "__init__.py":
        return []
    out = []
    for node in TREES[module].body:
        if isinstance(node, (ast.Assign, ast.AnnAssign)) and isinstance(node.value, ast.Dict):
            out += [(v.lineno, v.value) for v in node.value.values
                    if isinstance(v, ast.Constant) and v.value in MODULES]
    return out


def import_graph() -> dict[str, dict[str, int]]:
    """module -> {imported module of the three packages: line of the first such import}."""
    graph: dict[str, dict[str, int]] = {}
    for module, tree in TREES.items():
        edges = graph.setdefault(module, {})
        found = [(node.lineno, name) for node, _ in _walk(tree)
                 for name in _imported(node, module)]
        for line, name in found + _lazy_map_targets(module):
            # the deepest known module the name is (``oga.verify.verify`` -> ``oga.verify``)
            while name and name not in MODULES:
                name = name.rpartition(".")[0]
            # an ancestor package is initialised before the module runs: no edge
            if name and name != module and not module.startswith(name + "."):
                edges.setdefault(name, line)
    return graph


def _cycles(graph: dict[str, dict[str, int]]) -> list[list[str]]:
    """One cycle through every strongly connected component of more than one module."""
    index, low, stack, on_stack, sccs = {}, {}, [], set(), []

    def strongconnect(v):  # Tarjan, iterative over each node's edges
        work = [(v, iter(sorted(graph[v])))]
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        while work:
            node, edges = work[-1]
            for w in edges:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on_stack:
                    low[node] = min(low[node], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    scc = []
                    while True:
                        w = stack.pop()
                        on_stack.discard(w)
                        scc.append(w)
                        if w == node:
                            break
                    if len(scc) > 1:
                        sccs.append(set(scc))

    for v in sorted(graph):
        if v not in index:
            strongconnect(v)
    cycles = []
    for scc in sccs:  # the shortest cycle from the component's first module (BFS)
        start = min(scc)
        parent, frontier = {start: None}, [start]
        while frontier and start not in [w for v in frontier for w in graph[v]]:
            nxt = []
            for v in frontier:
                for w in sorted(graph[v]):
                    if w in scc and w not in parent:
                        parent[w] = v
                        nxt.append(w)
            frontier = nxt
        last = next(v for v in frontier if start in graph[v])
        path = [last]
        while parent[path[-1]] is not None:
            path.append(parent[path[-1]])
        cycles.append(path[::-1] + [start])
    return cycles


def _where(module: str) -> str:
    return MODULES[module].relative_to(ROOT).as_posix()


def test_no_import_cycle():
    graph = import_graph()
    assert "oga.model.machine" in graph["oga.optimize"]  # the walk sees imports
    messages = []
    for cycle in _cycles(graph):
        steps = [f"{_where(a)}:{graph[a][b]} imports {b}" for a, b in zip(cycle, cycle[1:])]
        messages.append("import cycle " + " -> ".join(cycle) + "\n    " + "\n    ".join(steps))
    assert not messages, "\n".join(messages)


def test_the_cycle_finder_finds_a_cycle():
    graph = {"a": {"b": 1}, "b": {"c": 2}, "c": {"a": 3, "d": 4}, "d": {}}
    assert _cycles(graph) == [["a", "b", "c", "a"]]
    assert _cycles({"a": {"b": 1}, "b": {}}) == []


def test_engine_imports_no_web_or_plotting_package_at_module_level():
    bad = []
    for module, tree in TREES.items():
        if module.split(".")[0] not in ENGINE:
            continue
        for node, in_function in _walk(tree):
            if in_function or not isinstance(node, (ast.Import, ast.ImportFrom)):
                continue
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] + [f"{node.module}.{a.name}" for a in node.names])
            hits = sorted({f for f in FORBIDDEN for n in names if n == f or n.startswith(f + ".")})
            bad += [f"{_where(module)}:{node.lineno} imports {h} at module level" for h in hits]
    assert not bad, "\n".join(bad)


def _decorator_name(d: ast.expr) -> str:
    d = d.func if isinstance(d, ast.Call) else d
    return d.attr if isinstance(d, ast.Attribute) else getattr(d, "id", "")


def _functions(packages):
    for module, tree in TREES.items():
        if module.split(".")[0] in packages:
            for node in ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    yield module, node


def _parameters(f: ast.FunctionDef) -> int:
    a = f.args
    return (len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
            + (a.vararg is not None) + (a.kwarg is not None))


def test_compiled_kernels_take_few_parameters():
    bad = [f"{_where(m)}:{f.lineno}:{f.name} takes {_parameters(f)} parameters"
           for m, f in _functions(ENGINE)
           if any(_decorator_name(d) in JIT_DECORATORS for d in f.decorator_list)
           and _parameters(f) > MAX_KERNEL_PARAMS]
    assert not bad, (f"{len(bad)} compiled kernel(s) over {MAX_KERNEL_PARAMS} parameters "
                     "(pack them):\n" + "\n".join(bad))


def test_functions_are_short():
    bad = [f"{_where(m)}:{f.lineno}:{f.name} is {f.end_lineno - f.lineno + 1} lines"
           for m, f in _functions(PACKAGES) if f.end_lineno - f.lineno + 1 > MAX_FUNCTION_LINES]
    assert not bad, (f"{len(bad)} function(s) over {MAX_FUNCTION_LINES} lines (split them):\n"
                     + "\n".join(bad))


def test_the_layout_pictures_name_every_package():
    """The README's layout and the architecture page show the tree as it is: every package
    of ``oga`` (a folder with an ``__init__.py``) is named in both pictures."""
    packages = sorted(p.parent.relative_to(ROOT).as_posix() + "/"
                      for p in (ROOT / "oga").glob("*/__init__.py"))
    readme = (ROOT / "README.md").read_text().split("## Layout", 1)[1].split("```", 2)[1]
    page = (ROOT / "docs" / "explanation" / "architecture.md").read_text()
    for name, text in (("README.md", readme), ("architecture.md", page)):
        short = [p for p in packages if p not in text and p.split("/", 1)[1] not in text]
        assert not short, f"{name}'s layout picture does not name {short}"
