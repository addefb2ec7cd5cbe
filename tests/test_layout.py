"""The package's layout: subpackages by purpose, imports only downward, no cycle."""
import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "so_transients"

#: each subpackage's layer: a module may import only from lower layers or its own subpackage
LAYERS = {"common": 0, "io": 1, "detect": 1, "sources": 1, "score": 1, "sim": 2, "coherent": 2,
          "significance": 3, "preprocess": 4, "site": 5, "events": 6, "database": 7,
          "alerts": 8, "report": 9,
          "campaign": 9}   # the validation studies: above every product, none reaches into them
#: the only modules outside the subpackages, above them all
TOP = {"__init__", "cli", "demo"}


def _imports(path):
    """The so_transients modules ``path`` imports, lazy imports included."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.level:
                raise AssertionError(f"{path}: relative import of {node.module}")
            if node.module.split(".")[0] == "so_transients":
                yield node.module, node.lineno
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.split(".")[0] == "so_transients":
                    yield alias.name, node.lineno


def _part(module):
    """The subpackage (or top-level module) a dotted module name lives in."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def test_every_module_lives_in_a_subpackage_but_the_entry_points():
    loose = {p.stem for p in PKG.glob("*.py")}
    assert loose <= TOP, f"modules outside the subpackages: {sorted(loose - TOP)}"
    subpackages = {p.parent.name for p in PKG.glob("*/__init__.py")}
    assert subpackages == set(LAYERS), subpackages ^ set(LAYERS)


def test_each_subpackage_says_what_lives_there():
    for name in LAYERS:
        doc = ast.get_docstring(ast.parse((PKG / name / "__init__.py").read_text()))
        assert doc and len(doc) > 40, f"so_transients/{name}/__init__.py has no docstring"


def test_imports_run_only_downward():
    wrong = []
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(PKG)
        here = rel.parts[0] if len(rel.parts) > 1 else rel.stem
        if here in TOP:
            continue
        for module, line in _imports(path):
            there = _part(module)
            if there == here:
                continue
            # the steps register themselves when the package is imported: the site pipeline's
            # entry point imports the package for that
            if module == "so_transients" and rel.as_posix() == "site/run.py":
                continue
            if there not in LAYERS or LAYERS[there] >= LAYERS[here]:
                wrong.append(f"{rel}:{line} imports {module}")
    assert not wrong, "imports that climb up or sideways:\n" + "\n".join(wrong)


def test_no_import_cycle_between_modules():
    graph = {}
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(PKG).with_suffix("")
        name = ".".join(("so_transients", *rel.parts)).removesuffix(".__init__")
        graph[name] = {m for m, _ in _imports(path)}
    state = {}

    def visit(node, stack):
        state[node] = "open"
        for nxt in graph.get(node, ()):
            if nxt not in graph or nxt == node:
                continue
            if state.get(nxt) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(nxt):]
                                                                     + [nxt]))
            if nxt not in state:
                visit(nxt, stack + [nxt])
        state[node] = "done"

    for node in graph:
        if node not in state:
            visit(node, [node])
