"""Import structure of a coin_app tree: import cycles, imports inside functions, the largest files.

Usage: python benchmarks/import_structure.py [TREE]   (default: this repository; e.g. a git worktree of an older commit)

Reads the source of ``coin_app``, ``tuning`` and ``cluster`` with ``ast`` (nothing is imported), so
an old checkout can be measured beside the current one. Prints the strongly connected components
of the internal import graph (imports inside functions included: they hide cycles), the number of
imports inside function bodies (internal / external), and the ten largest files by line count.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOTS = ("coin_app", "tuning", "cluster")


def modules(tree: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every module of the root packages."""
    out = {}
    for root in ROOTS:
        for path in (tree / root).rglob("*.py"):
            parts = path.relative_to(tree).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


def imports(path: Path) -> list[tuple[str, bool]]:
    """(imported name, inside a function body) of every import in ``path``."""
    found: list[tuple[str, bool]] = []

    def visit(node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                found.extend((a.name, in_function) for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.module:
                found.extend((f"{child.module}.{a.name}", in_function) for a in child.names)
            visit(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

    visit(ast.parse(path.read_text()), False)
    return found


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (iterative Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out = []
    for start in sorted(graph):
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
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
    return out


def main() -> None:
    """Print the cycles, the function-level import counts and the largest files of the tree."""
    tree = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parent.parent)
    mods = modules(tree)
    graph: dict[str, set[str]] = {m: set() for m in mods}
    in_function = {"internal": 0, "external": 0}
    for mod, path in mods.items():
        for name, inside in imports(path):
            target = name
            while target and target not in mods:
                target = target.rpartition(".")[0]
            if inside:
                in_function["internal" if name.startswith(ROOTS) else "external"] += 1
            if target and target != mod:
                graph[mod].add(target)
    found = cycles(graph)
    print(f"{tree}: {len(mods)} modules")
    print(f"import cycles: {len(found)}")
    for comp in found:
        print("  " + " <-> ".join(comp))
    print(f"imports inside functions: {sum(in_function.values())} ({in_function['internal']} internal, {in_function['external']} external)")
    print("largest files:")
    for path in sorted(mods.values(), key=lambda p: -len(p.read_text().splitlines()))[:10]:
        print(f"  {len(path.read_text().splitlines()):>5}  {path.relative_to(tree)}")


if __name__ == "__main__":
    main()
