"""The layout of ../shared/ARCHITECTURE.md, checked by parsing the source (nothing is imported).

Layers, lowest first; a module may import its own layer and the layers below it:

    base (errors.py, atomic.py) <- geometry <- networks <- robot <- data <- method / perception
    <- estimator.py / tracking.py <- training / report <- apps (with api.py, __init__.py, __main__.py beside it)

The two pipelines, method/ (the paper's diffusion) and perception/ (the geometric fit), share a
layer and never import each other; no module imports itself back through others (no cycle).

Within apps/, a command module (an ``apps/*.py`` with a ``run_<name>`` function) never imports
another command module; ``apps/arguments.py`` and ``apps/cli.py`` are the shared shell that
commands may import. Private names (a leading underscore, not dunder) never cross a module
boundary in src/, benchmarks/ or tools/. Every module stays at most MAX_LINES lines, and the
pinhole projection formula is written once, in geometry/camera.py.
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
PACKAGE = SRC / "monose3"
MAX_LINES = 400
SHELL = ("arguments", "cli")  # apps/ modules shared by every command

# Layer rank of each top-level name under monose3/ (a subpackage or a module).
LAYERS = (
    ("errors", "atomic"),
    ("geometry",),
    ("networks",),
    ("robot",),
    ("data",),
    ("method", "perception"),
    ("estimator", "tracking"),
    ("training", "report"),
    ("apps", "api", "calibration", "adaptation", "__init__", "__main__"),
)
RANK = {name: rank for rank, names in enumerate(LAYERS) for name in names}
LAYER_NAME = {name: "/".join(names) for names in LAYERS for name in names}


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def python_files(*roots: str) -> list[Path]:
    return sorted(p for root in roots for p in (ROOT / root).rglob("*.py") if "__pycache__" not in p.parts)


@cache
def parse(path: Path) -> ast.Module:
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def module_name(path: Path) -> str:
    """``src/monose3/geometry/camera.py`` -> ``monose3.geometry.camera`` (packages keep ``__init__``)."""
    return ".".join(path.relative_to(SRC).with_suffix("").parts)


def is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _exists(dotted: str) -> bool:
    base = SRC.joinpath(*dotted.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def imports(path: Path) -> list[tuple[int, str, list[str]]]:
    """Every import in the file, top level or inside a function: ``(line, module, names)``.

    Relative imports are resolved; ``from pkg import sub`` where ``sub`` is a module yields
    ``pkg.sub`` so that a submodule counts as its own target."""
    out = []
    own = module_name(path).split(".") if path.is_relative_to(SRC) else []
    for node in ast.walk(parse(path)):
        if isinstance(node, ast.Import):
            out.extend((node.lineno, alias.name, []) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                package = own[: len(own) - node.level]  # own[-1] is the module (or __init__)
                module = ".".join(package + ([module] if module else []))
            names = [alias.name for alias in node.names]
            subs = [n for n in names if _exists(f"{module}.{n}")]
            out.extend((node.lineno, f"{module}.{n}", []) for n in subs)
            rest = [n for n in names if n not in subs]
            if rest or not subs:
                out.append((node.lineno, module, rest))
    return out


def top_name(dotted: str) -> str | None:
    """The layer key of a ``monose3...`` module (None for other packages)."""
    parts = dotted.split(".")
    if parts[0] != "monose3":
        return None
    return parts[1] if len(parts) > 1 else "__init__"


def command_modules() -> set[str]:
    """``monose3.apps.<name>`` for every apps/*.py that defines a top-level ``run_<name>``."""
    found = set()
    for path in sorted((PACKAGE / "apps").glob("*.py")):
        if any(isinstance(node, ast.FunctionDef) and node.name.startswith("run_") for node in parse(path).body):
            found.add(module_name(path))
    return found


def _report(violations: list[str]) -> str:
    return f"{len(violations)} violation(s):\n  " + "\n  ".join(violations)


# --- (a) import direction -------------------------------------------------------------------------


def test_every_module_has_a_layer():
    unknown = sorted({_rel(p) for p in python_files("src/monose3") if top_name(module_name(p)) not in RANK})
    assert not unknown, f"modules outside every layer (add them to LAYERS): {unknown}"


def layering_violations() -> list[str]:
    violations = []
    for path in python_files("src/monose3"):
        me = top_name(module_name(path))
        if me not in RANK:
            continue
        for line, target, _ in imports(path):
            other = top_name(target)
            if other is None or other not in RANK or RANK[other] <= RANK[me]:
                continue
            violations.append(f"{_rel(path)}:{line} ({LAYER_NAME[me]}) imports {target} ({LAYER_NAME[other]})")
    return violations


def test_imports_follow_the_layers():
    violations = layering_violations()
    assert not violations, _report(violations)


def test_the_two_pipelines_never_import_each_other():
    violations = [
        f"{_rel(path)}:{line} imports {target}"
        for me, other in (("method", "perception"), ("perception", "method"))
        for path in python_files(f"src/monose3/{me}")
        for line, target, _ in imports(path)
        if top_name(target) == other
    ]
    assert not violations, _report(violations)


def import_graph() -> dict[str, set[str]]:
    """Every monose3 module's monose3 imports (those under ``if TYPE_CHECKING:`` too: a cycle
    hidden from the interpreter is still two ideas that lean on each other)."""
    graph = {}
    for path in python_files("src/monose3"):
        me = module_name(path)
        graph[me] = {t for _, t, _ in imports(path) if top_name(t) is not None and t != me}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index, low, on_stack, stack, found = {}, {}, set(), [], []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for nxt in graph.get(node, ()):
            if nxt not in graph:
                continue
            if nxt not in index:
                visit(nxt)
                low[node] = min(low[node], low[nxt])
            elif nxt in on_stack:
                low[node] = min(low[node], index[nxt])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_import_cycles_are_found():
    """Guards the next test against a search that finds nothing."""
    assert import_cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycle():
    cycles = import_cycles(import_graph())
    assert not cycles, _report([" <-> ".join(c) for c in cycles])


def test_geometry_imports_only_the_base():
    violations = [
        f"{_rel(path)}:{line} imports {target}"
        for path in python_files("src/monose3/geometry")
        for line, target, _ in imports(path)
        if top_name(target) not in (None, "geometry", *LAYERS[0])
    ]
    assert not violations, _report(violations)


def test_command_modules_exist():
    """Guards the next two tests against a definition of 'command module' that matches nothing."""
    assert len(command_modules()) >= 3, command_modules()


def test_no_command_imports_another_command():
    commands = command_modules()
    violations = [
        f"{_rel(path)}:{line} imports {target}"
        for path in python_files("src/monose3/apps")
        if module_name(path) in commands
        for line, target, _ in imports(path)
        if target in commands and target != module_name(path)
    ]
    assert not violations, _report(violations)


def test_the_shared_shell_imports_no_command():
    """arguments.py and cli.py sit below the commands (cli reaches them only by name, at run time)."""
    commands = command_modules()
    violations = [
        f"{_rel(path)}:{line} imports {target}"
        for name in SHELL
        for path in [PACKAGE / "apps" / f"{name}.py"]
        if path.is_file()
        for line, target, _ in imports(path)
        if target in commands
    ]
    assert not violations, _report(violations)


def registered_commands() -> dict[str, str]:
    """The ``COMMANDS = {name: (module, help)}`` table, read from whichever module defines it."""
    for path in python_files("src/monose3"):
        for node in parse(path).body:
            if (
                isinstance(node, ast.Assign)
                and any(isinstance(t, ast.Name) and t.id == "COMMANDS" for t in node.targets)
                and isinstance(node.value, ast.Dict)
            ):
                return {
                    ast.literal_eval(k): ast.literal_eval(v)[0]
                    for k, v in zip(node.value.keys, node.value.values, strict=True)
                }
    return {}


def test_every_command_lives_in_apps():
    commands = registered_commands()
    assert commands, "no COMMANDS table found in src/monose3"
    outside = [f"{name}: {module}" for name, module in commands.items() if not module.startswith("monose3.apps.")]
    assert not outside, _report(outside)


# --- (b) private names ----------------------------------------------------------------------------


def private_imports(*roots: str) -> list[str]:
    violations = []
    for path in python_files(*roots):
        for line, target, names in imports(path):
            if any(is_private(part) for part in target.split(".")):
                violations.append(f"{_rel(path)}:{line} imports {target}")
            violations.extend(f"{_rel(path)}:{line} imports {name} from {target}" for name in names if is_private(name))
    return violations


def test_no_private_name_is_imported():
    violations = private_imports("src", "benchmarks", "tools")
    assert not violations, _report(violations)


def private_attributes(*roots: str) -> list[str]:
    """``obj._name`` where obj is not ``self`` / ``cls``, and ``getattr(obj, "_name")`` and kin: a
    private attribute read or written from outside the object's own methods."""
    violations = []
    for path in python_files(*roots):
        for node in ast.walk(parse(path)):
            own_attribute = isinstance(node, ast.Attribute) and (
                isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")
            )
            by_dot = isinstance(node, ast.Attribute) and is_private(node.attr) and not own_attribute
            by_name = (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in ("getattr", "setattr", "hasattr", "delattr")
                and len(node.args) >= 2
                and isinstance(node.args[1], ast.Constant)
                and isinstance(node.args[1].value, str)
                and is_private(node.args[1].value)
            )
            if by_dot or by_name:
                violations.append(f"{_rel(path)}:{node.lineno} {ast.unparse(node)}")
    return violations


def test_no_private_attribute_of_another_object_is_used():
    violations = private_attributes("src", "benchmarks", "tools")
    assert not violations, _report(violations)


# --- (c) module size ------------------------------------------------------------------------------


def test_every_module_is_at_most_400_lines():
    sizes = {_rel(p): len(p.read_text(encoding="utf-8").splitlines()) for p in python_files("src")}
    over = [f"{path}: {n} lines" for path, n in sorted(sizes.items(), key=lambda kv: -kv[1]) if n > MAX_LINES]
    assert not over, f"modules over {MAX_LINES} lines:\n  " + "\n  ".join(over)


# --- (d) one pinhole projection -------------------------------------------------------------------

CAMERA = PACKAGE / "geometry" / "camera.py"
_XY = r"\[\s*(?:\.\.\.|:)\s*,\s*:2\s*\]"  # [:, :2] or [..., :2]
PROJECTION = (
    # xy / z * focal, with K (or a focal vector) on the line: x[:, :2] / x[:, 2:] * np.diag(K)[:2] + K[:2, 2]
    re.compile(_XY + r"\s*/\s*[\w.]+(?:\[[^\]]*\])?\s*\*.*(?:\bK\b|focal)"),
    # anything divided by z then scaled: ... / z * f
    re.compile(r"/\s*z\s*\*"),
    # one component at a time: K[0, 0] * x[:, 0] / z + K[0, 2]
    re.compile(r"\bK\w*\[[^\]]*\]\s*\*\s*[\w.]+\[[^\]]*\]\s*/\s*[\w.]+(?:\[[^\]]*\])?\s*\+\s*K\w*\["),
)


def projection_lines(path: Path) -> list[str]:
    found = []
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        code = line.split("#", 1)[0]
        if any(p.search(code) for p in PROJECTION):
            found.append(f"{_rel(path)}:{number}: {line.strip()}")
    return found


def test_the_projection_pattern_finds_camera_py():
    """Guards the next test against patterns that no longer match the one real definition."""
    assert projection_lines(CAMERA), f"no projection formula found in {_rel(CAMERA)}: update PROJECTION"


def test_projection_is_written_only_in_geometry_camera():
    copies = [line for path in python_files("src") if path != CAMERA for line in projection_lines(path)]
    assert not copies, _report(copies)


# --- (e) one home per concept ---------------------------------------------------------------------

# The modules that drive every denoiser design alike (the designs live in method/designs/).
DESIGN_DRIVERS = (
    PACKAGE / "estimator.py",
    PACKAGE / "method" / "reverse.py",
    PACKAGE / "training" / "loop.py",
    PACKAGE / "training" / "objective.py",
)
APPEARANCE = PACKAGE / "data" / "scenes" / "appearance.py"
ATOMIC = PACKAGE / "atomic.py"
# Calls that write a file by renaming a temporary one: atomic.py's job alone.
ATOMIC_CALLS = {("os", "replace"), ("os", "rename"), ("tempfile", "mkstemp"), ("tempfile", "NamedTemporaryFile")}


def design_names() -> set[str]:
    """``DESIGNS`` as method/config.py writes it (parsed, not imported)."""
    for node in parse(PACKAGE / "method" / "config.py").body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "DESIGNS" for t in node.targets):
            return set(ast.literal_eval(node.value))
    return set()


def test_no_design_is_named_where_every_design_is_driven_alike():
    names = design_names()
    assert "flow-solve" in names, "DESIGNS not found in method/config.py"
    violations = [
        f"{_rel(path)}:{node.lineno} {node.value!r}"
        for path in DESIGN_DRIVERS
        for node in ast.walk(parse(path))
        if isinstance(node, ast.Constant) and node.value in names
    ]
    violations += [
        f"{_rel(path)}:{node.lineno} .{node.attr}"
        for path in DESIGN_DRIVERS
        for node in ast.walk(parse(path))
        if isinstance(node, ast.Attribute) and node.attr in ("design", "needs_surface", "predicts_flow")
    ]
    assert not violations, _report(violations)


def top_level_functions(path: Path) -> set[str]:
    return {node.name for node in parse(path).body if isinstance(node, ast.FunctionDef)}


def test_scene_appearance_is_written_once():
    """No other module defines a function of appearance.py's (a second set of backgrounds,
    shapes, augmentations), and only it blurs, adds noise or JPEG-compresses a scene."""
    own = top_level_functions(APPEARANCE)
    assert {"backgrounds", "augment", "compose", "jpeg_like"} <= own
    violations = [
        f"{_rel(path)}: defines {sorted(top_level_functions(path) & own)}"
        for path in python_files("src/monose3")
        if path != APPEARANCE and top_level_functions(path) & own
    ]
    assert not violations, _report(violations)


def test_atomic_writes_go_through_atomic_py():
    violations = [
        f"{_rel(path)}:{node.lineno} {ast.unparse(node.func)}"
        for path in python_files("src/monose3")
        if path != ATOMIC
        for node in ast.walk(parse(path))
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and isinstance(node.func.value, ast.Name)
        and (node.func.value.id, node.func.attr) in ATOMIC_CALLS
    ]
    assert not violations, _report(violations)
