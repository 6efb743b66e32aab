"""Command-line conventions (tuning/commands/options.py, main.py): --version, one gain order
(kp, ki, kd, as the handout writes the PID) in every option that takes gains, the distributed
options defined once in an advanced help group of their own, and a settling time that never
comes said in words."""

import math
import re
from pathlib import Path

import pytest

from tuning.commands import options
from tuning.commands.main import build_parser, main

COMMANDS = Path(__file__).resolve().parents[1] / "tuning" / "commands"


def _help(capsys, *argv) -> str:
    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--help"])
    assert exit_.value.code == 0
    return capsys.readouterr().out


def test_version(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxcart {version('jaxcart')}"


def test_every_help_says_percent_once(capsys):
    """argparse %-formats options' help but prints a description as written: a "%%" there is
    printed as "%%" (class said "overshoot < 5 %%")."""
    commands = build_parser()._subparsers._group_actions[0].choices
    for command in commands:
        text = _help(capsys, command)
        assert "%%" not in text, (command, text[text.index("%%") - 60 : text.index("%%") + 5])


@pytest.mark.parametrize("command", ["tune", "grid", "fit", "diagnose"])
def test_distributed_options_are_listed_last_under_advanced(capsys, command):
    text = _help(capsys, command)
    body = text[text.index("\noptions:") :]  # past the usage line
    heading = body.index(options.ADVANCED.split("(")[0])
    for flag in ("--coordinator HOST:PORT", "--num-processes N", "--process-id I"):
        assert body.index(flag) > heading, (command, flag)
    assert not re.search(r"\n\S.*:\n", body[heading + len(options.ADVANCED) :])  # the last group


def test_student_commands_show_no_distributed_options(capsys):
    for command in ("lab", "simulate", "class"):
        assert "--coordinator" not in _help(capsys, command)


def test_the_distributed_options_are_defined_once():
    defined = [p.name for p in COMMANDS.glob("*.py") if '"--coordinator"' in p.read_text()]
    assert defined == ["options.py"]
    # The commands import shared options from options.py, not from one another.
    for path in COMMANDS.glob("*.py"):
        assert "from tuning.commands.tune import" not in path.read_text(), path.name


def test_tune_start_is_kp_ki_kd():
    """--start 60,1,4 is kp = 60, ki = 1, kd = 4, as the design library receives it."""
    from tuning.commands.tune import _start
    from tuning.design.losses import PARAM_NAMES
    from tuning.design.problem import start_and_template

    start = _start("60,1,4")
    assert start == {"kp": 60.0, "ki": 1.0, "kd": 4.0}
    params, _ = start_and_template(start, None, ("kp", "ki", "kd"))
    got = dict(zip(PARAM_NAMES, params, strict=True))
    assert (got["kp"], got["ki"], got["kd"]) == (60.0, 1.0, 4.0)
    args = build_parser().parse_args(["tune", "--start", "60,1,4"])
    assert args.start == "60,1,4" and args.free == "kp,ki,kd"


def test_tune_start_errors_name_the_order():
    from jaxcart.errors import UserError

    with pytest.raises(UserError, match=r"kp,ki,kd >= 0 in the handout's order"):
        options.parse_gains("40,5", "--start")


def test_grid_gains_file_without_header_is_kp_ki_kd(tmp_path):
    from tuning.commands.grid import read_gains_file

    path = tmp_path / "list.csv"
    path.write_text("60,1,4\n")
    assert read_gains_file(path) == [(60.0, 4.0, 1.0)]  # the library's rows: kp, kd, ki
    path.write_text("ki,kd,kp\n1,4,60\n")
    assert read_gains_file(path) == [(60.0, 4.0, 1.0)]


def test_gain_options_are_listed_in_the_handout_order(capsys):
    for command in ("grid", "simulate"):
        text = _help(capsys, command)
        body = text[text.index("\noptions:") :]
        assert body.index("--kp") < body.index("--ki") < body.index("--kd"), command


def test_a_time_never_reached_is_said_in_words():
    assert options.seconds_text(math.inf) == "does not settle within the horizon"
    assert options.seconds_text(0.7091) == "0.709 s"
    assert options.timed("settling", math.inf) == options.NOT_SETTLED
    assert options.timed("settling", 0.5) == "settling 0.500 s"


def test_simulate_prints_a_run_that_never_settles_in_words(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    argv = ["simulate", "--kp", "2", "--ki", "0", "--kd", "0", "--horizon", "0.5"]
    assert main([*argv, "--out", "slow.csv", "--plot", "slow.png"]) == 0
    out = capsys.readouterr().out
    assert "does not settle within the horizon" in out and " inf" not in out


def test_library_messages_with_inf_are_said_in_words():
    """tune prints the design library's message through in_words, grid its comparison table
    through _not_settled_in_words."""
    from tuning.commands.grid import _not_settled_in_words

    message = (
        "cannot meet the specification (exact simulator): settling time inf s is not under "
        "1 s. Best found: settling inf s, overshoot 0.00 %"
    )
    said = options.in_words(message)
    assert " inf" not in said and said.count(options.NOT_SETTLED) == 2
    assert options.in_words("settling 0.709 s") == "settling 0.709 s"
    table = "  settling time [s]              inf            0.709\n  overshoot [%]   1   2"
    lines = _not_settled_in_words(table).splitlines()
    assert options.NOT_SETTLED in lines[0] and "0.709" in lines[0] and lines[1].endswith("2")


def test_a_failed_command_ends_at_once_beside_work_it_abandons(tmp_path):
    """The process's own command line (main() with no argv): a command that fails while
    background work is inside XLA (a failed lab's diagnosis) ends with its status and one
    error line; the interpreter's shutdown on that thread aborted it (status 134, "terminate
    called after throwing ...") before."""
    import subprocess
    import sys

    code = (
        "import sys, threading\n"
        "import jax, jax.numpy as jnp\n"
        "from jaxcart.background import Background\n"
        "from tuning.commands.main import main\n"
        "started = threading.Event()\n"
        "def busy():  # many short calls into XLA, each leaving and taking the GIL\n"
        "    f = jax.jit(lambda x: jnp.sin(x) + 1.0)\n"
        "    x = jnp.ones(1000)\n"
        "    while True:\n"
        "        x = f(x)\n"
        "        x.block_until_ready()\n"
        "        started.set()\n"
        "work = Background(busy)\n"
        "started.wait()\n"
        "sys.argv = ['jaxcart', 'simulate', 'nowhere.toml']\n"
        "sys.exit(main())\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines()[-1].startswith("jaxcart simulate: error: "), done.stderr
    assert "terminate" not in done.stderr
