"""The layout of docs/design.md ("Layout"): ``hw/`` (numpy only) <- ``jaxcart/`` (the simulator)
<- ``tuning/`` (built on it, and the top floor: the command line and the benchmark).

Imports are read from the source with ``ast``, so a violation is found without running it;
the command line is run in a fresh interpreter, where ``sys.modules`` tells what it imported.
"""

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: Command modules whose top still imports jaxcart (hence jax) when the parser is built; the
#: owners move those imports into the functions. Empty this set then: the xfails are strict.
WAITING: set[str] = set()


def _modules(package: str):
    return sorted((ROOT / package).rglob("*.py"))


def _imports(path: Path, root: Path = ROOT):
    """(line, module name) of every import in the file: statements, and ``importlib`` /
    ``__import__`` calls whose module is a string constant."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = ".".join(path.relative_to(root).with_suffix("").parts[:-1])
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: inside the file's own package
                yield node.lineno, package
            else:
                yield node.lineno, node.module
        elif isinstance(node, ast.Call) and node.args:
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            first = node.args[0]
            if name in ("import_module", "__import__") and isinstance(first, ast.Constant):
                if isinstance(first.value, str):
                    yield node.lineno, first.value


def _top(name: str) -> str:
    return name.split(".")[0]


def test_the_scan_sees_every_kind_of_import(tmp_path):
    (tmp_path / "pkg").mkdir()
    probe = tmp_path / "pkg" / "probe.py"
    probe.write_text(
        "import tuning.commands.main\nfrom tuning import fit\nimport importlib\n"
        "from . import sibling\n"
        "importlib.import_module('tuning.design.grid')\n__import__('tuning')\n"
    )
    names = [name for _, name in _imports(probe, tmp_path)]
    assert names == [
        "tuning.commands.main",
        "tuning",
        "importlib",
        "pkg",
        "tuning.design.grid",
        "tuning",
    ]


@pytest.mark.parametrize("path", _modules("jaxcart"), ids=lambda p: str(p.relative_to(ROOT)))
def test_jaxcart_never_imports_tuning(path):
    upward = [(line, name) for line, name in _imports(path) if _top(name) == "tuning"]
    assert not upward, f"{path.relative_to(ROOT)} imports the tuning floor: {upward}"


def test_no_library_module_uses_pyplot():
    """Figures are drawn with matplotlib's object API (``matplotlib.figure.Figure``): pyplot
    keeps open figures and a backend for the process, and a library that draws a report must
    not switch a notebook's backend or leave figures behind."""
    found = [
        f"{path.relative_to(ROOT)}:{line}"
        for package in ("jaxcart", "tuning", "hw")
        for path in _modules(package)
        for line, name in _imports(path)
        if name == "matplotlib.pyplot"
    ]
    found += [
        str(path.relative_to(ROOT))
        for package in ("jaxcart", "tuning", "hw")
        for path in _modules(package)
        if re.search(r"matplotlib\.use\(|from matplotlib import [^\n]*\bpyplot\b", path.read_text())
    ]
    assert not found, found


#: A vendor's board API that one hw module may import, lazily (inside a function), so that hw/
#: imports without it: {top-level name: the module allowed to import it}.
VENDOR_APIS = {"quanser": "hw/devices/quanser.py"}


def _module_level_lines(path: Path) -> set[int]:
    tree = ast.parse(path.read_text(), filename=str(path))
    return {n.lineno for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)}


@pytest.mark.parametrize("path", _modules("hw"), ids=lambda p: str(p.relative_to(ROOT)))
def test_hw_imports_only_numpy_and_the_standard_library(path):
    allowed = set(sys.stdlib_module_names) | {"numpy", "hw"}
    where = str(path.relative_to(ROOT))
    top_level = _module_level_lines(path)
    other = [
        (line, name)
        for line, name in _imports(path)
        if _top(name) not in allowed
        and not (VENDOR_APIS.get(_top(name)) == where and line not in top_level)
    ]
    assert not other, f"{where} imports beyond numpy and the stdlib: {other}"


def _fresh(code: str, **env) -> str:
    """stdout of ``code`` in a new interpreter run from the repository root."""
    environ = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"} | env
    done = subprocess.run(
        [sys.executable, "-c", code],
        cwd=ROOT,
        env=environ,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def _commands():
    import tuning.commands.main

    return [
        pytest.param(
            name,
            marks=pytest.mark.xfail(
                name in WAITING, strict=True, reason="imports jaxcart at the top"
            ),
        )
        for name in tuning.commands.main.COMMANDS
    ]


@pytest.mark.parametrize("name", _commands())
def test_registering_a_command_imports_no_jax(name):
    code = (
        "import argparse, importlib, sys\n"
        "try:\n"
        f"    module = importlib.import_module({name!r})\n"
        "except ModuleNotFoundError as exc:\n"
        f"    if exc.name != {name!r}: raise\n"
        "    print('absent'); raise SystemExit\n"
        "module.register(argparse.ArgumentParser().add_subparsers())\n"
        "print(sorted({'jax', 'jaxlib'} & set(sys.modules)))\n"
    )
    assert _fresh(code) in ("absent", "[]")


@pytest.mark.xfail(bool(WAITING), strict=True, reason=f"waiting for {sorted(WAITING)}")
def test_help_imports_no_jax():
    """``jaxcart --help`` (and so every argument error) answers without starting jax."""
    code = (
        "import sys\n"
        "from tuning.commands.main import main\n"
        "try:\n"
        "    main(['--help'])\n"
        "except SystemExit as exc:\n"
        "    assert exc.code == 0, exc.code\n"
        "print('jax' in sys.modules)\n"
    )
    assert _fresh(code).splitlines()[-1] == "False"


def test_python_m_tuning_lists_every_command():
    done = subprocess.run(
        [sys.executable, "-m", "tuning", "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout.startswith("usage: jaxcart")
    for command in ("simulate", "tune", "grid", "fit", "lab", "bench"):
        assert f"    {command} " in done.stdout


def test_a_command_gets_one_xla_device_per_core():
    """``main`` asks for the devices after parsing, before the command starts jax's backend."""
    code = (
        "import sys, types\n"
        "import tuning.commands.main as cli\n"
        "probe = types.ModuleType('probe')\n"
        "def count(args):\n"
        "    import jax\n"
        "    print(jax.device_count())\n"
        "probe.register = lambda sub: sub.add_parser('count').set_defaults(func=count)\n"
        "sys.modules['probe'] = probe\n"
        "cli.COMMANDS = ('probe',)\n"
        "raise SystemExit(cli.main(['count']))\n"
    )
    assert _fresh(code, JAX_PLATFORMS="cpu") == str(os.cpu_count())


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph(root: Path, packages) -> dict[str, set[str]]:
    """{module: the project modules it imports}, for every ``.py`` under ``packages`` of
    ``root``, counting imports inside functions too (a circle hidden by a function-level import
    is still a circle). ``from a import b`` counts ``a`` and, where it is a module, ``a.b``;
    a module's own parent packages are left out (every submodule runs them)."""
    files = {
        p: _module_name(p, root) for pkg in packages for p in sorted((root / pkg).rglob("*.py"))
    }
    known = set(files.values())
    graph: dict[str, set[str]] = {}
    for path, me in files.items():
        package = me if path.name == "__init__.py" else me.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    parts = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base = ".".join(parts + ([node.module] if node.module else []))
                targets |= {base} | {f"{base}.{alias.name}" for alias in node.names}
        graph[me] = {t for t in targets if t in known and t != me and not me.startswith(t + ".")}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The import circles: strongly connected sets of two or more modules (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            members = set()
            while True:
                w = stack.pop()
                members.add(w)
                if w == v:
                    break
            if len(members) > 1:
                found.append(members)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_the_circle_finder_sees_function_level_imports(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from pkg import b\n")
    (pkg / "b.py").write_text("def f():\n    from pkg.c import g\n")
    (pkg / "c.py").write_text("import pkg.a\n")
    (pkg / "d.py").write_text("from . import a\n")
    assert _circles(_import_graph(tmp_path, ["pkg"])) == [{"pkg.a", "pkg.b", "pkg.c"}]
    (pkg / "c.py").write_text("import os\n")  # the circle broken: d -> a -> b -> c only
    assert _circles(_import_graph(tmp_path, ["pkg"])) == []


def test_jaxcart_and_tuning_have_no_import_circle():
    circles = [sorted(c) for c in _circles(_import_graph(ROOT, ["jaxcart", "tuning"]))]
    assert not circles, f"import circles (imports inside functions count): {circles}"
