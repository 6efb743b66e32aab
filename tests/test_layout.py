"""The layout of docs/design.md ("Layout"): ``hw/`` (numpy only) <- ``jaxcart/`` (the simulator)
<- ``tuning/`` (built on it, and the top floor: the command line and the benchmark).

Imports are read from the source with ``ast``, so a violation is found without running it;
the command line is run in a fresh interpreter, where ``sys.modules`` tells what it imported.
"""

import ast
import os
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
