"""The package's shape: imports run one way, at the top, and modules stay small.

Pure source checks (no JAX): they read every module of ``jaxsync`` (and of
``jaxsync.optimize``, installed from ``optimize/``) with ``ast``.
"""

from __future__ import annotations

import ast
import pathlib
import re

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
# the packages from the bottom of the data's way to the top: a module imports
# from its own layer or the ones below it, never from one above
LAYERS = ("_errors", "runtime", "physics", "control", "sim", "io", "calibrate", "optimize", "cli")
MAX_LINES = 500


def _modules() -> dict[str, pathlib.Path]:
    mods = {}
    for base, prefix in ((ROOT / "jaxsync", "jaxsync"), (ROOT / "optimize", "jaxsync.optimize")):
        for path in base.rglob("*.py"):
            parts = list(path.relative_to(base).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join([prefix, *parts])] = path
    return mods


MODULES = _modules()


def _imports(path: pathlib.Path):
    """(imported module, line, at the top?) for every import of a jaxsync module in ``path``."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            if name in MODULES:
                yield name, node.lineno, id(node) in top


def _layer(module: str) -> int:
    part = module.split(".")[1] if "." in module else ""
    return LAYERS.index(part) if part in LAYERS else -1  # jaxsync/__init__.py: the public face, above all


def test_modules_are_found():
    assert {"jaxsync.physics.step", "jaxsync.control.controller", "jaxsync.optimize.tuning.tune"} <= set(MODULES)


def test_no_import_loop_counting_imports_inside_functions():
    graph = {m: {n for n, _, _ in _imports(p) if n != m} for m, p in MODULES.items()}
    # a package's __init__ is not a dependency of its own modules' imports of siblings
    state: dict[str, int] = {}
    loops = []

    def visit(m, stack):
        state[m] = 1
        for n in sorted(graph[m]):
            if n in MODULES and not m.startswith(n + ".") and not n.startswith(m + "."):
                if state.get(n) == 1:
                    loops.append(stack[stack.index(n) :] + [n] if n in stack else [m, n])
                elif n not in state:
                    visit(n, [*stack, n])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not loops, f"import loops: {loops}"


@pytest.mark.parametrize("module", sorted(m for m in MODULES if m != "jaxsync"))
def test_imports_run_down_the_layers(module):
    here = _layer(module)
    upward = [(n, line) for n, line, _ in _imports(MODULES[module]) if _layer(n) > here and n != "jaxsync"]
    assert not upward, f"{module} imports from a layer above it ({LAYERS[here]}): {upward}"


def test_library_modules_import_jaxsync_at_the_top_only():
    """Only the command line defers jaxsync's own modules (its start-up time): in the library
    every dependency between modules is at the top, where the layer test and a reader see it."""
    hidden = [
        f"{MODULES[m].relative_to(ROOT)}:{line}: {n}"
        for m in sorted(MODULES)
        if not m.startswith("jaxsync.cli")
        for n, line, top in _imports(MODULES[m])
        if not top
    ]
    assert not hidden, f"imports of jaxsync modules inside library functions: {hidden}"


def test_command_line_text_is_parsed_by_the_commands():
    """Text a user typed ("0:3", "0.05:1") is read in jaxsync.cli; the library takes numbers."""
    found = [
        f"{MODULES[m].relative_to(ROOT)}: {name}"
        for m in sorted(MODULES)
        if not m.startswith("jaxsync.cli")
        for name in re.findall(r"^def (parse_delay|parse_ft_filter|delay_text)\b", MODULES[m].read_text(), re.M)
    ]
    assert not found, found


def test_imports_inside_functions_say_why():
    """An import inside a function is there only for an optional dependency, a
    private module another version may lack, or the command line's start-up
    time, and a comment on its line or the line before says which."""
    silent = []
    for path in sorted({*MODULES.values()}):
        lines = path.read_text().split("\n")
        tree = ast.parse("\n".join(lines))
        top = {id(n) for n in tree.body}
        imports = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
        in_import = {i for n in imports for i in range(n.lineno, n.end_lineno + 1)}
        for node in imports:
            if id(node) in top:
                continue
            # its own line, or the comment above the block of imports it is in
            reason = "#" in lines[node.lineno - 1]
            i = node.lineno - 1
            while not reason and i >= 1 and (i in in_import or not lines[i - 1].strip()):
                reason = "#" in lines[i - 1]
                i -= 1
            if not reason and i >= 1:
                reason = lines[i - 1].strip().startswith("#")
            if not reason:
                silent.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert not silent, f"imports inside functions without a reason: {silent}"


@pytest.mark.parametrize("module", sorted(MODULES))
def test_no_module_over_500_lines(module):
    n = len(MODULES[module].read_text().split("\n"))
    assert n <= MAX_LINES, f"{module}: {n} lines"


def test_the_project_speaks_of_itself_as_it_is():
    """No tracker or session numbers, and no "new/old path" names, in the code,
    tests or docs: names say what a thing is, not when or why it came."""
    pattern = re.compile(r"\b(issue #?\d+|session \d+|(new|old) path)\b", re.IGNORECASE)
    files = [*ROOT.glob("*.md"), *ROOT.glob("docs/*.md"), *ROOT.glob("experiments/*.py"), *ROOT.glob("tests/*.py")]
    files += sorted(set(MODULES.values()))
    found = []
    for path in files:
        for i, line in enumerate(path.read_text().split("\n"), 1):
            if pattern.search(line) and path.name != "test_layout.py":
                found.append(f"{path.relative_to(ROOT)}:{i}: {line.strip()[:80]}")
    assert not found, found


# each command that only parses: the jaxsync names it may import besides jaxsync.cli._common, its
# job's module (whole) or single names it prints ("module:name")
PARSE_ONLY = {
    "jaxsync.cli.compare": (
        "jaxsync.optimize.studies.compare",
        "jaxsync.sim.crosscheck:sim_to_sim_table",
        "jaxsync.sim.metrics:CHATTER_THRESHOLD_N",
    ),
    "jaxsync.cli.export": (
        "jaxsync.io.export_gains:export_gains",
        "jaxsync.io.golden:golden_job",
        "jaxsync.io.export:COMMAND_INTERFACES",
        "jaxsync.io.export:COMPLIANCE_FRAMES",
        "jaxsync.io.export:DISTROS",
        "jaxsync.io.export:FORMATS",
    ),
    "jaxsync.cli.sensitivity": ("jaxsync.optimize.studies.sensitivity",),
}


def _jaxsync_names(path: pathlib.Path):
    """Each jaxsync import of ``path``: a module's name, or "module:name" for a name from a module."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name.startswith("jaxsync"))
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("jaxsync"):
            for a in node.names:
                whole = f"{node.module}.{a.name}"
                yield whole if whole in MODULES else f"{node.module}:{a.name}"


@pytest.mark.parametrize("command", sorted(PARSE_ONLY))
def test_a_command_parses_calls_one_job_and_prints(command):
    """The command imports its job and what it prints, nothing that computes
    (no model loading, no gains files): a Python user gets the job whole."""
    beyond = [
        name
        for name in _jaxsync_names(MODULES[command])
        if name not in PARSE_ONLY[command] and not name.startswith(("jaxsync.cli._common", "jaxsync.cli._stack"))
    ]
    assert not beyond, f"{command} imports more than its job and what it prints: {beyond}"
    text = MODULES[command].read_text()
    assert "load_model" not in text and "gains_file" not in text and "default_gains" not in text
