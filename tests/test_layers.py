"""The package's layers, read from the source: no import cycle, and each layer imports only
the layers below it (numerics never the stream, nodes, views or paper code)."""

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "bttsim_stream"

#: Third-party packages each layer must not import.
TRANSPORT = {"zenoh", "google", "mcap", "mcap_protobuf", "rerun"}
NUMERICS = ("bttsim_stream.model", "bttsim_stream.sim", "bttsim_stream.process")
#: Internal modules each group must not import (prefix match).
FORBIDDEN = {
    NUMERICS: ("bttsim_stream.bus", "bttsim_stream.runtime", "bttsim_stream.nodes", "bttsim_stream.views",
               "bttsim_stream.paper", "bttsim_stream.acquisition", "bttsim_stream.offline",
               "bttsim_stream.orchestrate", "bttsim_stream.cli", "bttsim_stream.testing"),
    ("bttsim_stream.bus",): ("bttsim_stream.runtime", "bttsim_stream.nodes", "bttsim_stream.views",
                             "bttsim_stream.paper", "bttsim_stream.acquisition", "bttsim_stream.offline",
                             "bttsim_stream.orchestrate", "bttsim_stream.cli"),
    ("bttsim_stream.views",): ("bttsim_stream.runtime", "bttsim_stream.nodes", "bttsim_stream.paper",
                               "bttsim_stream.orchestrate", "bttsim_stream.cli", "bttsim_stream.model",
                               "bttsim_stream.sim", "bttsim_stream.scenario"),
    ("bttsim_stream.runtime", "bttsim_stream.nodes", "bttsim_stream.acquisition", "bttsim_stream.offline",
     "bttsim_stream.export", "bttsim_stream.processor", "bttsim_stream.orchestrate",
     "bttsim_stream.testing"): ("bttsim_stream.paper",),
    # studies on Dask: above the simulation and processing, beside the live system
    ("bttsim_stream.campaign",): ("bttsim_stream.nodes", "bttsim_stream.views", "bttsim_stream.orchestrate",
                                  "bttsim_stream.runtime", "bttsim_stream.cli", "bttsim_stream.paper"),
}

#: Exact modules each group must not import: the bus decodes processing results (the result
#: dataclasses of ``process.results``, ``process.resonance``, ...) but never runs the
#: processing (the pipeline, the streaming processor, or the package that re-exports them).
FORBIDDEN_EXACT = {
    ("bttsim_stream.bus",): ("bttsim_stream.process", "bttsim_stream.process.pipeline",
                             "bttsim_stream.process.streaming"),
}


def _modules() -> dict[str, Path]:
    mods = {}
    for root, name in ((PKG, "bttsim_stream"), (REPO / "nodes", "bttsim_stream.nodes")):
        for path in root.rglob("*.py"):
            if "_gen" in path.parts:
                continue
            rel = path.relative_to(root).with_suffix("").parts
            parts = (name,) + (rel[:-1] if rel[-1] == "__init__" else rel)
            mods[".".join(parts)] = path
    return mods


def _within(module: str, packages) -> bool:
    """``module`` is one of ``packages`` or inside one (by dotted components, not by prefix)."""
    return any(module == p or module.startswith(p + ".") for p in packages)


def _imports(name: str, path: Path, mods: dict) -> list[tuple[str, int, bool]]:
    """``(imported module, line, at module level)`` for every import of ``path``."""
    tree = ast.parse(path.read_text())
    is_pkg = path.name == "__init__.py"
    top = set(map(id, tree.body))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno, id(node) in top) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base[:len(base) - node.level + (1 if is_pkg else 0)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module
            for a in node.names:
                sub = f"{mod}.{a.name}"
                out.append((sub if sub in mods else mod, node.lineno, id(node) in top))
    return out


@pytest.fixture(scope="module")
def graph():
    mods = _modules()
    return mods, {m: _imports(m, p, mods) for m, p in mods.items()}


def test_no_import_cycle(graph):
    mods, imports = graph
    edges = {m: sorted({t for t, _, _ in imp if t in mods and t != m}) for m, imp in imports.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for t in edges[m]:
            if state.get(t) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(t):] + [t]))
            if t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(edges):
        if m not in state:
            visit(m)


def test_layers_import_only_what_is_below_them(graph):
    _, imports = graph
    bad = []
    for m, imp in imports.items():
        for group, forbidden in FORBIDDEN.items():
            if _within(m, group):
                bad += [f"{m}:{line} imports {t}" for t, line, _ in imp if _within(t, forbidden)]
        for group, forbidden in FORBIDDEN_EXACT.items():
            if _within(m, group):
                bad += [f"{m}:{line} imports {t}" for t, line, _ in imp if t in forbidden]
        if _within(m, NUMERICS):
            bad += [f"{m}:{line} imports {t}" for t, line, _ in imp if t.split(".")[0] in TRANSPORT]
        if _within(m, ("bttsim_stream.views",)):
            bad += [f"{m}:{line} imports {t}" for t, line, _ in imp if t.split(".")[0] == "zenoh"]
    assert not bad, "\n".join(bad)


def test_only_the_cli_imports_the_campaign_and_dask(graph):
    _, imports = graph
    users = {m for m, imp in imports.items() for t, _, _ in imp
             if (_within(t, ("bttsim_stream.campaign",)) or t.split(".")[0] in ("dask", "distributed"))
             and not _within(m, ("bttsim_stream.campaign",))}
    assert users <= {"bttsim_stream.cli"}


def test_the_runtime_imports_paper_code_only_from_the_cli_commands(graph):
    _, imports = graph
    paper = ("bttsim_stream.paper",)
    users = {m for m, imp in imports.items() for t, _, _ in imp if _within(t, paper) and not _within(m, paper)}
    assert users <= {"bttsim_stream.cli"}
    assert all(not top for m in users for t, _, top in imports[m] if _within(t, paper))


def test_every_command_line_option_has_help_and_nodes_show_the_same_flags_everywhere():
    import argparse

    from bttsim_stream.cli import build_parser
    from bttsim_stream.nodes import programs
    from bttsim_stream.runtime import node_parser

    missing, node_flags = [], {}

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    walk(sub, path + (name,))
            elif not isinstance(action, argparse._HelpAction):
                if not action.help:
                    missing.append(" ".join(path) + f" {action.option_strings or action.dest}")
                if path[:2] == ("bttsim", "node"):
                    node_flags.setdefault(path[2], []).append((tuple(action.option_strings), action.help))

    walk(build_parser(), ("bttsim",))
    assert not missing, missing
    for prog in programs():  # `bttsim node NAME` and the node's own script: one definition
        own = [(tuple(a.option_strings), a.help) for a in node_parser(prog)._actions
               if not isinstance(a, argparse._HelpAction)]
        assert node_flags[prog.name] == own, prog.name


#: The house's limits: a module a reader can hold, a function that fits a screen or two.
MAX_MODULE_LINES, MAX_FUNCTION_LINES = 1000, 120


def test_no_module_over_1000_lines_and_no_function_over_120():
    big = []
    for path in PKG.rglob("*.py"):
        if "_gen" in path.parts:
            continue
        text = path.read_text()
        if text.count("\n") > MAX_MODULE_LINES:
            big.append(f"{path.relative_to(REPO)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    big.append(f"{path.relative_to(REPO)}:{node.lineno} {node.name}: {n} lines")
    assert not big, "\n".join(big)


def test_no_private_name_is_imported_from_another_module(graph):
    """A name another module needs is public where it is defined (no ``_name`` imports)."""
    bad = []
    mods, _ = graph
    for path in mods.values():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("bttsim_stream")):
                bad += [f"{path.relative_to(REPO)}:{node.lineno} imports {a.name}" for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, "\n".join(bad)
