"""The import graph of msps_render: rooms (top-level modules and subpackages), floors, cycles.

    python scripts/import_graph.py        # prints rooms by floor and the counts

Every `import` / `from ... import` of an msps_render module counts, at module level or
inside a function (those are counted apart).  A cycle is a set of modules (or of rooms)
that import each other; with none, each room stands one floor above everything it imports.
"""
from __future__ import annotations

import ast
import sys
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "msps_render"


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def room(module: str) -> str:
    parts = module.split(".")
    if len(parts) == 1:
        return "msps_render/__init__.py"
    sub = PKG / parts[1]
    return f"msps_render/{parts[1]}/" if sub.is_dir() else f"msps_render/{parts[1]}.py"


def imports(path: Path) -> tuple[list[str], int]:
    """(msps_render modules imported, number of imports inside functions)."""
    tree = ast.parse(path.read_text())
    local = {id(n) for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
             for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
    out = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Import):
            out += [a.name for a in n.names if a.name.startswith("msps_render")]
        elif isinstance(n, ast.ImportFrom) and n.module and n.module.startswith("msps_render"):
            out += [f"{n.module}.{a.name}" if (PKG.parent / (n.module.replace(".", "/") + "/" + a.name)).exists()
                    or (PKG.parent / (n.module.replace(".", "/") + "/" + a.name + ".py")).exists() else n.module
                    for a in n.names]
    return out, len(local)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one node (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in list(graph):
        if v not in index:
            visit(v)
    return out


def measure() -> dict:
    modules, rooms, n_local = {}, {}, 0
    for path in sorted(PKG.rglob("*.py")):
        name = module_name(path)
        deps, local = imports(path)
        n_local += local
        modules[name] = {d for d in deps if d != name}
    for m, deps in modules.items():
        rooms.setdefault(room(m), set()).update(room(d) for d in deps if room(d) != room(m))
    floors: dict[str, int] = {}

    def floor(r, seen=()):
        if r not in floors:
            floors[r] = 1 + max((floor(d, seen + (r,)) for d in rooms.get(r, ()) if d not in seen), default=0)
        return floors[r]

    for r in rooms:
        floor(r)
    return {"modules": modules, "rooms": rooms, "floors": floors, "module_cycles": cycles(modules),
            "room_cycles": cycles(rooms), "function_local_imports": n_local,
            "room_imports": sum(len(v) for v in rooms.values())}


def main() -> None:
    m = measure()
    for f in sorted(set(m["floors"].values()), reverse=True):
        print(f"floor {f}: " + ", ".join(sorted(r for r, x in m["floors"].items() if x == f)))
    print(f"rooms {len(m['rooms'])}, floors {max(m['floors'].values())}, imports between rooms "
          f"{m['room_imports']}, module cycles {len(m['module_cycles'])}, room cycles {len(m['room_cycles'])}, "
          f"function-local imports {m['function_local_imports']}")
    for c in m["module_cycles"] + m["room_cycles"]:
        print("cycle:", " <-> ".join(c))


if __name__ == "__main__":
    main()
