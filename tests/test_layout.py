"""The layout of ``daemon/`` (issue 13): one subpackage per part, imports that run one
way, parsed from every module's source (nothing is imported).

Layers, highest first; a module may import its own subpackage and any lower layer,
never a higher one nor another subpackage of its own layer::

    cli                                  the command line
    live, synth                          the live daemon; the synthetic performer
    retarget, face, validate, post, console, props
    body                                 rigs, calibration, the body solve
    shared leaves (daemon/*.py)          rotations, errors, version, compiled primitives
    replay, protocols                    outside daemon/ (tests/test_packaging.py)

Also: no import cycle between modules; no import of a ``retargetd`` module inside a
function (the one way to hide a cycle) except in ``cli/``, whose commands load heavy
modules lazily so that ``retargetd --help`` stays fast; no runtime module imports
``cli``; no command imports another command; no shipped module over 500 lines of code.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
DAEMON = REPO_ROOT / "daemon"
PREFIX = "retargetd.daemon"

#: Subpackage -> layer (higher imports lower). Leaves (daemon/*.py) are layer 1.
LAYERS: dict[str, int] = {
    "body": 2,
    "retarget": 3,
    "face": 3,
    "validate": 3,
    "post": 3,
    "console": 3,
    "props": 3,
    "live": 4,
    "synth": 4,
    "cli": 5,
}
LEAF_LAYER = 1
#: Data-only packages (shipped files, no code of their own).
DATA_PACKAGES = {"body.rigs", "face.faces", "synth.markersets"}


def _modules() -> Iterator[tuple[str, Path]]:
    for path in sorted(DAEMON.rglob("*.py")):
        rel = path.relative_to(DAEMON).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join([PREFIX, *parts]) if parts else PREFIX, path


def _imports(path: Path) -> Iterator[tuple[str, bool, int]]:
    """(imported module, inside a function, line) for every retargetd import."""
    tree = ast.parse(path.read_text(), filename=str(path))
    func_lines: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
            for sub in ast.walk(node):
                if isinstance(sub, ast.Import | ast.ImportFrom):
                    func_lines.add(sub.lineno)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("retargetd."):
                    yield alias.name, node.lineno in func_lines, node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module:
            if not node.module.startswith("retargetd."):
                continue
            for alias in node.names:
                # ``from pkg import module`` names a module: resolve to it.
                candidate = f"{node.module}.{alias.name}"
                target = candidate if _is_module(candidate) else node.module
                yield target, node.lineno in func_lines, node.lineno


def _is_module(name: str) -> bool:
    if not name.startswith(PREFIX + "."):
        return False
    rel = Path(*name[len(PREFIX) + 1 :].split("."))
    return (DAEMON / rel).with_suffix(".py").is_file() or (
        DAEMON / rel / "__init__.py"
    ).is_file()


def _part(module: str) -> str | None:
    """The subpackage of a daemon module (None: a shared leaf or the root)."""
    if not module.startswith(PREFIX + "."):
        return None
    first = module[len(PREFIX) + 1 :].split(".")[0]
    return first if (DAEMON / first / "__init__.py").is_file() else None


def _layer(module: str) -> int:
    part = _part(module)
    return LEAF_LAYER if part is None else LAYERS[part]


def test_every_subpackage_has_a_layer_and_a_docstring() -> None:
    for init in sorted(DAEMON.rglob("__init__.py")):
        rel = ".".join(init.parent.relative_to(DAEMON).parts)
        if not rel or rel in DATA_PACKAGES:
            continue
        assert rel in LAYERS, f"daemon/{rel}: give it a layer in LAYERS"
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc and len(doc) > 40, (
            f"daemon/{rel}/__init__.py: a docstring saying what it owns"
        )


def test_imports_run_one_way() -> None:
    bad = []
    for module, path in _modules():
        if module == f"{PREFIX}.__main__":
            continue  # ``python -m retargetd.daemon``: the entry point itself
        src_part, src_layer = _part(module), _layer(module)
        for target, _in_func, line in _imports(path):
            if not target.startswith(PREFIX + "."):
                continue
            dst_part, dst_layer = _part(target), _layer(target)
            where = f"{path.relative_to(REPO_ROOT)}:{line} imports {target}"
            if dst_part == src_part and dst_part is not None:
                continue
            if dst_layer > src_layer:
                bad.append(f"{where} (a higher layer)")
            elif dst_layer == src_layer and dst_part != src_part:
                bad.append(f"{where} (another part of the same layer)")
    assert not bad, "\n".join(bad)


def test_no_function_level_imports_outside_cli() -> None:
    bad = [
        f"{path.relative_to(REPO_ROOT)}:{line} imports {target} inside a function"
        for module, path in _modules()
        if _part(module) != "cli"
        for target, in_func, line in _imports(path)
        if in_func
    ]
    assert not bad, "\n".join(bad)


def test_no_runtime_module_imports_cli_and_commands_stand_alone() -> None:
    main = (DAEMON / "cli" / "main.py").read_text()
    commands = set(re.findall(r'"(retargetd\.daemon\.cli\.\w+)"', main))
    assert f"{PREFIX}.cli.run" in commands and len(commands) >= 13
    bad = []
    for module, path in _modules():
        for target, _in_func, line in _imports(path):
            where = f"{path.relative_to(REPO_ROOT)}:{line} imports {target}"
            runtime = _part(module) != "cli" and module != f"{PREFIX}.__main__"
            if runtime and _part(target) == "cli":
                bad.append(f"{where} (a runtime module importing the CLI)")
            if module in commands and target in commands and target != module:
                bad.append(f"{where} (a command importing another command)")
    assert not bad, "\n".join(bad)


def test_no_import_cycles() -> None:
    graph: dict[str, set[str]] = {}
    for module, path in _modules():
        graph[module] = {
            t
            for t, in_func, _ in _imports(path)
            if t.startswith(PREFIX) and t != module
        }
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                cycle = [*stack[stack.index(nxt) :], nxt]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if nxt in graph and not state.get(nxt):
                visit(nxt)
        stack.pop()
        state[node] = 2

    for module in sorted(graph):
        if not state.get(module):
            visit(module)


def test_imports_are_absolute() -> None:
    bad = []
    for _module, path in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                bad.append(f"{path.relative_to(REPO_ROOT)}:{node.lineno}")
    assert not bad, "relative imports: " + ", ".join(bad)


#: The most lines of code a shipped module may hold (issue 13: "none over ~500 lines
#: of code"); blank lines, comments and docstrings do not count.
MAX_CODE_LINES = 500


def code_lines(source: str) -> int:
    """Lines of ``source`` that hold code: not blank, not only a comment, not part of
    a module, class or function docstring."""
    docstring_lines: set[int] = set()
    for node in ast.walk(ast.parse(source)):
        if not isinstance(
            node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef
        ):
            continue
        first = node.body[0] if node.body else None
        if (
            isinstance(first, ast.Expr)
            and isinstance(first.value, ast.Constant)
            and isinstance(first.value.value, str)
        ):
            docstring_lines.update(range(first.lineno, (first.end_lineno or 0) + 1))
    return sum(
        1
        for number, line in enumerate(source.splitlines(), 1)
        if line.strip()
        and not line.strip().startswith("#")
        and number not in docstring_lines
    )


def test_code_lines_counts_only_code() -> None:
    source = (
        '"""Doc\n\nmore doc."""\n\n# comment\nx = 1\n\n\n'
        'def f():\n    """Doc."""\n    return x  # trailing\n'
    )
    assert code_lines(source) == 3


def test_no_shipped_module_is_over_the_size_limit() -> None:
    over = []
    for package in ("daemon", "protocols", "replay"):
        for path in sorted((REPO_ROOT / package).rglob("*.py")):
            n = code_lines(path.read_text(encoding="utf-8"))
            if n > MAX_CODE_LINES:
                over.append(f"{path.relative_to(REPO_ROOT)}: {n}")
    assert not over, f"modules over {MAX_CODE_LINES} lines of code: {over}"


LIVE = DAEMON / "live"


def live_inheritance(sources: dict[str, str]) -> list[str]:
    """``module.Class(Base)`` for every class of the live daemon (``sources``: module
    name -> source) whose base is a class of another of its modules: a part mixed
    into another instead of passed in (issue 33: parts own their state; the loop
    composes them). A module's own classes (a config table and its named variant)
    and bases from elsewhere (``Protocol``, ``Generic``, stdlib) are fine."""
    trees = {name: ast.parse(src) for name, src in sources.items()}
    home = {
        node.name: name
        for name, tree in trees.items()
        for node in ast.walk(tree)
        if isinstance(node, ast.ClassDef)
    }
    bad = []
    for name, tree in sorted(trees.items()):
        for node in ast.walk(tree):
            if not isinstance(node, ast.ClassDef):
                continue
            for base in node.bases:
                base_name = (
                    base.id
                    if isinstance(base, ast.Name)
                    else base.attr
                    if isinstance(base, ast.Attribute)
                    else ""
                )
                if home.get(base_name, name) != name:
                    bad.append(f"{name}.{node.name}({base_name})")
    return bad


def test_live_inheritance_finds_a_mixin() -> None:
    sources = {
        "inputs": "class InputsMixin:\n    pass\n",
        "loop": "from typing import Protocol\n\nclass P(Protocol):\n    pass\n\n"
        "class Q(P):\n    pass\n\nclass Daemon(InputsMixin):\n    pass\n",
    }
    assert live_inheritance(sources) == ["loop.Daemon(InputsMixin)"]


def test_no_class_of_the_live_daemon_inherits_from_another_part() -> None:
    sources = {p.stem: p.read_text(encoding="utf-8") for p in LIVE.glob("*.py")}
    assert len(sources) > 20  # the live daemon's modules were read
    bad = live_inheritance(sources)
    assert not bad, (
        f"classes of daemon/live/ built on another of its classes (compose parts, "
        f"pass them in): {bad}"
    )
