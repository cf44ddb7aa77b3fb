"""House rules over the source tree (read as text, nothing imported): no private name imported
across modules, no import cycle (lazy imports inside functions included), and no helper defined
twice across the experiment scripts (shared ones live in experiments/common.py)."""
from __future__ import annotations

import ast
import collections
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("jaxdenoise", "data_gen")
# the verbs of the experiment scripts' command lines: every script has its own
SCRIPT_VERBS = {"main", "run", "prepare", "page"}  # page(res): the page an experiment writes from its JSON


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in (ROOT / pkg).rglob("*.py"):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def _imported(module: str, path: Path, node: ast.AST, known: dict) -> list[str]:
    """The project modules an import statement names (``from . import x`` names the submodule)."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    base = base[:len(base) - (node.level - 1)] if node.level else []
    mod = ".".join(base + ([node.module] if node.module else []))
    subs = [f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in known]
    return subs or [mod]


def _private_imports(path: Path, module: str | None, known: dict) -> list[str]:
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ImportFrom) or node.module == "__future__":
            continue
        names = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
        if names:
            found.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {names}")
        targets = _imported(module, path, node, known) if module else [node.module or ""]
        for t in targets:
            parts = t.split(".")
            for i, part in enumerate(parts):  # a private module, imported from outside its package
                if part.startswith("_") and not part.startswith("__"):
                    owner = ".".join(parts[:i])
                    if module is None or not (module == owner or module.startswith(owner + ".")):
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno} imports private module {t}")
    return found


def test_no_private_name_is_imported_across_modules():
    known = _modules()
    found = [f for m, p in known.items() for f in _private_imports(p, m, known)]
    found += [f for p in sorted((ROOT / "experiments").glob("*.py")) for f in _private_imports(p, None, known)]
    assert not found, "\n".join(found)


def test_no_import_cycle():
    """Module-level and lazy (function-level) imports alike; a submodule's import of its own
    package does not count (Python runs the package first either way)."""
    known = _modules()
    graph = {m: set() for m in known}
    for m, p in known.items():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for t in _imported(m, p, node, known):
                    if t in known and t != m and not m.startswith(t + "."):
                        graph[m].add(t)
    cycles = []

    def reach(start):  # depth-first: the first path back to ``start``
        stack, seen = [(start, [start])], set()
        while stack:
            node, path = stack.pop()
            for nxt in graph[node]:
                if nxt == start:
                    return path + [start]
                if nxt not in seen:
                    seen.add(nxt)
                    stack.append((nxt, path + [nxt]))
        return None

    for m in sorted(graph):
        loop = reach(m)
        if loop and not any(set(loop) == set(c) for c in cycles):
            cycles.append(loop)
    assert not cycles, "\n".join(" -> ".join(c) for c in cycles)


def test_no_helper_is_defined_twice_across_experiments():
    defined = collections.defaultdict(list)
    for p in sorted((ROOT / "experiments").glob("*.py")):
        for node in ast.parse(p.read_text()).body:
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name not in SCRIPT_VERBS:
                defined[node.name].append(p.name)
    twice = {k: v for k, v in defined.items() if len(v) > 1}
    assert not twice, f"define these once in experiments/common.py: {twice}"
