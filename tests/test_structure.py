"""The code's structure holds: no import cycle between the package's modules (imports inside
functions included: a cycle hidden in a function is still a cycle), no module importing another
module's private name, no module over 600 lines, no module of ``sfm/`` reading the whole
configuration (each component takes its own sections)."""
import ast
from pathlib import Path

import stereoseed

PACKAGE = Path(stereoseed.__file__).parent
MAX_LINES = 600


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _imports(path: Path, name: str, modules: dict[str, Path]) -> list[tuple[str, str, int]]:
    """(module imported, name imported or "", line) for every import of the package's own
    modules in ``path`` (module ``name``), wherever it stands."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found += [(a.name, "", node.lineno) for a in node.names if a.name.startswith("stereoseed")]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1] + ([base] if base else []))
            if not base.startswith("stereoseed"):
                continue
            for a in node.names:
                sub = f"{base}.{a.name}"
                found.append((sub, "", node.lineno) if sub in modules else (base, a.name, node.lineno))
    return found


def test_no_import_cycle_even_inside_functions():
    modules = _modules()
    graph = {m: {target for target, _, _ in _imports(p, m, modules) if target in modules and target != m}
             for m, p in modules.items()}
    state, stack, cycles = {}, [], []

    def visit(m):
        state[m] = "open"
        stack.append(m)
        for t in sorted(graph[m]):
            if state.get(t) == "open":
                cycles.append(stack[stack.index(t):] + [t])
            elif t not in state:
                visit(t)
        stack.pop()
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m)
    assert not cycles, "import cycles: " + "; ".join(" -> ".join(c) for c in cycles)


def test_no_module_imports_another_modules_private_name():
    modules = _modules()
    private = [f"{p.relative_to(PACKAGE.parent)}:{line} imports {name} from {target}"
               for m, p in modules.items() for target, name, line in _imports(p, m, modules)
               if name.startswith("_") and target != m]
    assert not private, "\n".join(private)


def test_no_module_over_600_lines():
    long = {str(p.relative_to(PACKAGE.parent)): n for p in PACKAGE.rglob("*.py")
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > MAX_LINES}
    assert not long, long


def test_no_sfm_module_reads_the_whole_config():
    # the mapper's components take their own sections, resolved once at the top (sfm/options.py):
    # none imports stereoseed.config (wherever the import stands) or resolves a configuration
    modules = _modules()
    found = []
    for m, p in modules.items():
        if not m.startswith("stereoseed.sfm"):
            continue
        where = p.relative_to(PACKAGE.parent)
        found += [f"{where}:{line} imports {target}" for target, _, line in _imports(p, m, modules)
                  if target == "stereoseed.config"]
        tree = ast.parse(p.read_text(encoding="utf-8"))
        found += [f"{where}:{node.lineno} calls .resolve()" for node in ast.walk(tree)
                  if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                  and node.func.attr == "resolve"]
    assert not found, "\n".join(found)
