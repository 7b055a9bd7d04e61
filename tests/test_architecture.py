"""The house rules of docs/architecture.md, checked on the source itself (an AST reading independent of import-linter).

* the layers of ``pyproject.toml``'s import-linter contract: a module imports only its own layer and the layers below;
* its forbidden contracts between internal packages (the TD3 family: ``td3`` knows no child, ``cig_td3`` and ``traco``
  import only ``td3`` among algorithm packages), directly or through other modules;
* no import cycle among the modules of coin_app, tuning and cluster (imports inside functions included);
* an import inside a function body names its reason (``# optional: ...``);
* the simulator and inference import without Ray, and inference without torch;
* nothing but ``python -m coin_app`` imports the CLI (benchmarks and cluster scripts included).
"""

from __future__ import annotations

import ast
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ROOTS = ("coin_app", "tuning", "cluster")


def _modules() -> dict[str, Path]:
    """Every module of the root packages: dotted name -> file."""
    out = {}
    for root in ROOTS:
        for path in (REPO / root).rglob("*.py"):
            parts = path.relative_to(REPO).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """(imported name, line, inside a function) of every import statement in ``path``."""
    tree = ast.parse(path.read_text())
    found: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            inside = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if isinstance(child, ast.Import):
                found.extend((a.name, child.lineno, in_function) for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.module:
                found.extend((f"{child.module}.{a.name}", child.lineno, in_function) for a in child.names)
            visit(child, inside)

    visit(tree, False)
    return found


def _resolve(name: str, modules: dict[str, Path]) -> str | None:
    """The internal module an imported name refers to (``pkg.mod.Symbol`` -> ``pkg.mod``), or None if external."""
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def _graph() -> dict[str, set[str]]:
    """Internal import graph: module -> modules it imports (anywhere in its body)."""
    modules = _modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        for name, _, _ in _imports(path):
            target = _resolve(name, modules)
            if target is not None and target != mod:
                graph[mod].add(target)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                strong(w)
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
                out.append(sorted(comp))

    sys.setrecursionlimit(10_000)
    for v in sorted(graph):
        if v not in index:
            strong(v)
    return out


def test_cycle_finder_finds_a_planted_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert _cycles(graph) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles():
    assert _cycles(_graph()) == []


def _layers() -> list[list[str]]:
    """The layers of the import-linter contract in pyproject.toml, top first; siblings split on '|'."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]
    (contract,) = [c for c in config["contracts"] if c["type"] == "layers"]
    return [[m.strip() for m in layer.split("|")] for layer in contract["layers"]]


def _layer_of(module: str, layers: list[list[str]]) -> tuple[int, str] | None:
    """(layer index, the layer member) that contains ``module``; None if it is in no layer."""
    for i, members in enumerate(layers):
        for m in members:
            if module == m or module.startswith(m + "."):
                return i, m
    return None


def test_layers_import_only_downward():
    layers = _layers()
    assert [m for layer in layers for m in layer][-1] == "coin_app.sim"  # the simulator is the bottom
    bad = []
    for mod, targets in _graph().items():
        here = _layer_of(mod, layers)
        for target in targets:
            there = _layer_of(target, layers)
            if here is None or there is None:
                continue
            if there[0] < here[0] or (there[0] == here[0] and there[1] != here[1]):  # higher, or an independent sibling
                bad.append(f"{mod} -> {target}")
    assert bad == []


def _forbidden_internal() -> list[tuple[str, list[str], list[str]]]:
    """(name, sources, forbidden) of every forbidden contract in pyproject.toml whose forbidden modules are internal."""
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]
    out = []
    for c in config["contracts"]:
        if c["type"] == "forbidden" and all(m.split(".")[0] in ROOTS for m in c["forbidden_modules"]):
            out.append((c["name"], c["source_modules"], c["forbidden_modules"]))
    return out


def _under(module: str, packages: list[str]) -> bool:
    """Whether ``module`` is one of ``packages`` or inside one."""
    return any(module == p or module.startswith(p + ".") for p in packages)


def test_forbidden_internal_imports_are_absent_directly_and_through_other_modules():
    contracts = _forbidden_internal()
    assert any("coin_app.algorithms.td3" in sources for _, sources, _ in contracts)  # the TD3 family's contracts are read
    graph = _graph()
    bad = []
    for name, sources, forbidden in contracts:
        for start in (m for m in graph if _under(m, sources)):
            seen, todo = {start}, [start]
            while todo:  # every module reachable from start
                for target in graph[todo.pop()] - seen:
                    seen.add(target)
                    todo.append(target)
            bad += [f"{name}: {start} -> {m}" for m in sorted(seen) if _under(m, forbidden)]
    assert bad == []


def test_function_level_imports_name_their_reason():
    modules = _modules()
    unexplained = []
    for path in modules.values():
        lines = path.read_text().splitlines()
        for name, line, in_function in _imports(path):
            text = lines[line - 1] + (lines[line - 2] if line > 1 else "")
            if in_function and "# optional:" not in text:
                unexplained.append(f"{path.relative_to(REPO)}:{line} {name}")
    assert unexplained == []


def test_nothing_but_main_imports_the_cli():
    modules = _modules()
    importers = []
    for path in [*modules.values(), *(REPO / "benchmarks").glob("*.py")]:
        if path == REPO / "coin_app" / "__main__.py" or (REPO / "coin_app" / "cli") in path.parents:  # the CLI's own modules
            continue
        if any(name == "coin_app.cli" or name.startswith("coin_app.cli.") for name, _, _ in _imports(path)):
            importers.append(str(path.relative_to(REPO)))
    assert importers == []


def _loaded_after(imports: list[str]) -> set[str]:
    """Top-level packages loaded in a fresh interpreter after importing ``imports``."""
    code = "import sys\n" + "".join(f"import {m}\n" for m in imports) + "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))"
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    return set(out.stdout.split())


def test_sim_and_inference_import_without_ray_and_inference_without_torch():
    sim = sorted(m for m in _modules() if m.startswith("coin_app.sim"))
    loaded = _loaded_after(sim)
    assert "numpy" in loaded  # the probe sees what was imported
    assert "ray" not in loaded and "torch" not in loaded
    loaded = _loaded_after(["coin_app.inference", "coin_app.inference.switching"])
    assert "ray" not in loaded and "torch" not in loaded
