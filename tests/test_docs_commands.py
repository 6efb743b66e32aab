"""Every command README.md and docs/*.md show runs here as written, from the folder the text
says, and does what the text says it does.

What a command is (:func:`shown`): each line of a code block that starts with ``jaxcart``,
``python -m``, ``python3``, ``tools/`` or ``.venv/bin/`` (a ``$`` prompt and a trailing
``# comment`` dropped), and each inline code span that starts with ``jaxcart`` or ``python -m``
and something to run, naming no placeholder (an upper-case name such as DIR or FILE.mat, ``[``,
``|``, ``...``): ``jaxcart fit EXP.toml [more.toml]`` is a usage, not a command, and a bare
command name in prose (``jaxcart fit``'s floor) is a name, except in the README's handout
table, whose command column is run as it stands.

Where each runs (:data:`SHOWN`): ``examples``, the folder that ``jaxcart examples && cd
jaxcart-examples`` makes; ``repository``, a folder with ``../shared`` beside it (the README's
``../shared/realdata`` paths); ``realdata``, a copy of ``../shared/realdata``; ``hw``, a folder
holding the gains file docs/hardware.md runs (kp=120.9 ki=1.67 kd=4.1, 6 V), and ``hw-print``,
another, for the run whose output it prints. Each folder's
commands run once, in-process, in the order the text gives them (a later one reads what an
earlier one wrote: ``fitted.toml``, ``gains.json``, ``p5.toml``). ``jaxcart lab``, the README's
main job, runs once in the whole suite, in tests/test_lab.py, as does its caption's run on the
real recordings: here it is checked that they run there as written. The set-up and test
commands (venv, pip, pytest) are what CI runs (.ci/run, checked to be the README's).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shlex
import shutil
import webbrowser
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
REALDATA = ROOT.parent / "shared" / "realdata"
PLACEHOLDER = re.compile(r"\[|\||\.\.\.|(?<![\w-])[A-Z][A-Z0-9_]*(\.[a-z]+)?(?![\w-])")
STARTS = ("jaxcart ", "python -m ", "python3 ", "tools/", ".venv/bin/")


@dataclass(frozen=True)
class Shown:
    """A command as shown, where it runs and what the text says of it: its exit status and
    what its output (stdout and stderr) says (regular expressions), the files it writes."""

    text: str
    folder: str
    status: int = 0
    says: tuple = ()
    writes: tuple = ()
    elsewhere: str = ""  # run as written by that test file instead (once in the suite)
    when: str = ""  # a condition that skips it ("realdata": ../shared/realdata beside the tree)


def _ss_error(mm: str) -> str:
    return rf"simulated: .*steady-state error {mm} mm"


#: Every command shown, by folder, in the order it runs there.
SHOWN = [
    # README: set up and run, test (CI runs them; the lab once, in tests/test_lab.py)
    Shown(
        "python3 -m venv .venv && .venv/bin/pip install -q -e . && .venv/bin/jaxcart lab",
        "ci",
        elsewhere="tests/test_lab.py",
    ),
    Shown(
        "tools/provide-browser && python3 -m venv .venv && .venv/bin/pip install -q -e "
        "'.[test]' && .venv/bin/python -m pytest -q -n 2 --dist loadfile",
        "ci",
    ),
    Shown(
        "jaxcart lab --data ../shared/realdata --no-diagnosis",
        "repository",
        elsewhere="tests/test_lab.py",
    ),
    Shown("jaxcart --version", "repository", says=(r"^jaxcart \d+\.\d+",)),
    Shown("jaxcart --help", "repository", says=(r"usage: jaxcart", r"examples")),
    # README: the handout, item by item (in jaxcart-examples/)
    Shown(
        "jaxcart examples && cd jaxcart-examples",
        "start",
        says=(r"copied the built-in recordings \(p10, p50, pi, pid, ramp, tap, each",),
    ),
    Shown("jaxcart lab", "examples", elsewhere="tests/test_lab.py"),
    Shown(
        "jaxcart tune --out gains.json",
        "examples",
        says=(r"tuned gains: kp = ", r"meets the specification \(exact simulator\)"),
        writes=("gains.json", "gains.png"),
    ),
    Shown("jaxcart app", "examples", says=(r"the design page is at http://127\.0\.0\.1:5006/",)),
    Shown(
        "jaxcart grid --kp 10:150:24 --ki 0:30:6 --kd 0:15:24",
        "examples",
        says=(r"3456 points", r"meets specification +yes +yes"),
        writes=("jaxcart-out/grid.npz", "jaxcart-out/grid.png"),
    ),
    Shown(
        "jaxcart fit tap.toml --params B_eq,f_c --classic --out tap_fit.toml",
        "examples",
        says=(
            r"\nB_eq +4\.60\d* ",
            r"\nf_c +0\.4[45]\d* ",
            r"tap\.toml: B_eq = 5\.\d+ .*log-linear",
            r"fitted plant: tap_fit\.toml",
        ),
        writes=("tap_fit.toml",),
    ),
    Shown(
        "jaxcart simulate tap.toml --plant tap_fit.toml",
        "examples",
        # The coast from where the hand let go, on the tap's own fit: 0.13 mm from it.
        says=(
            r"tap from where the hand let go, t = 0\.6\d+ s",
            r"position minus recording \(exact simulator\): rms 0\.\d+ mm",
        ),
        writes=("jaxcart-out/tap-sim.csv", "jaxcart-out/tap-sim.toml", "jaxcart-out/tap-sim.png"),
    ),
    Shown(
        "jaxcart simulate p50.toml",
        "examples",
        says=(r"exact simulator", r"recorded: .*steady-state error 4\.97 mm"),
        writes=("jaxcart-out/p50-sim.csv", "jaxcart-out/p50-sim.toml", "jaxcart-out/p50-sim.png"),
    ),
    Shown("jaxcart fit p50.toml --params B_eq", "examples", says=(r"\nB_eq +5\.\d+ ",)),
    Shown(
        "jaxcart fit ramp.toml --params f_c --classic",
        "examples",
        says=(r"\nf_c +0\.4\d+ ", r"ramp\.toml: f_c = 0\.4\d+ N .*ramp breakaway"),
    ),
    Shown(
        "jaxcart fit tap.toml ramp.toml --params B_eq,f_c --out fitted.toml",
        "examples",
        says=(r"\nB_eq +4\.(59|60)\d* ", r"\nf_c +0\.(449|450)\d* ", r"fitted plant: fitted\.toml"),
        writes=("fitted.toml",),
    ),
    Shown(
        "jaxcart tune --plant fitted.toml --robust --out robust.json",
        "examples",
        says=(
            r"meets the specification \(on all 12 plants",
            r"what limits the gains: ",
            r"margins: gain margin .* phase margin .* peak sensitivity",
            r"on 63 carts drawn from the plant file's uncertainty: settling .* meets the spec",
        ),
        writes=("robust.json", "robust.png"),
    ),
    Shown(
        "jaxcart simulate p10.toml --plant fitted.toml",
        "examples",
        # The README: the dead band, 26.1 mm as recorded (issue 34: 15.65 mm on the smooth
        # simulator, the old default).
        says=(_ss_error("26.1[0-9]"), r"recorded: .*steady-state error 26.1[0-9] mm"),
    ),
    Shown(
        "jaxcart simulate pi.toml --plant fitted.toml",
        "examples",
        says=(_ss_error("3.1[0-9]"), r"position minus recording \(exact simulator\): rms 0\.0"),
    ),
    Shown(
        "jaxcart run gains.json --device q2_usb --step 0.5",
        "examples",
        status=1,
        says=(r"quanser\.hardware\) is not installed", r"nothing was driven"),
        when="no-sdk",
    ),
    Shown(
        "jaxcart run gains.json --device sim --step 0.5",
        "examples",
        says=(r"hw run: completed, 3001 samples", r"meets the spec"),
    ),
    Shown("jaxcart simulate pid.toml", "examples", says=(r"recorded: .*settling 0\.70\d s",)),
    Shown(
        "jaxcart fit tap.toml p50.toml --json fit.mat",
        "examples",
        says=(r"report: fit\.mat",),
        writes=("fit.mat",),
    ),
    # README and docs/interop.md: .mat in, .mat out
    Shown(
        "jaxcart simulate ../shared/realdata/p50.toml --out p50-sim.mat",
        "repository",
        says=(r"wrote p50-sim\.mat",),
        writes=("p50-sim.mat", "p50-sim.toml"),
        when="realdata",
    ),
    Shown(
        "jaxcart simulate ../shared/realdata/p50.toml",
        "repository",
        says=(r"jaxcart-out/p50-sim\.mat",),
        writes=("jaxcart-out/p50-sim.mat",),
        when="realdata",
    ),
    Shown("jaxcart simulate p50.toml --out run.mat", "examples", writes=("run.mat", "run.toml")),
    Shown(
        "jaxcart simulate p50.toml --out run-array.mat --mat-layout array",
        "examples",
        writes=("run-array.mat",),
    ),
    # docs/experiment-files.md: raw scope files, in ../shared/realdata
    Shown(
        "jaxcart fit part1.1.mat",
        "realdata",
        says=(r"recognised|tap", r"\nB_eq +1\.5"),
        when="realdata",
    ),
    Shown("jaxcart simulate 2.1pos.mat", "realdata", says=(r"exact simulator",), when="realdata"),
    # docs/hardware.md (in a folder with its gains file)
    Shown(
        "python -m hw run gains.json --device sim --step 0.5",
        "hw",
        says=(r"hw run: completed, 3001 samples",),
    ),
    Shown(
        "python -m hw run gains.json --device sim --step 0.5 --real-time",
        "hw",
        says=(r"real time on the computer's clock", r"hw run: completed, 3001 samples"),
    ),
    Shown(
        "python -m hw run gains.json --device q2_usb --step 0.5 --out p5.toml",
        "hw",
        status=1,
        says=(r"quanser\.hardware\) is not installed",),
        when="no-sdk",
    ),
    Shown(
        "python -m hw run gains.json --device q2_usb --slider 0.2,0,-0.2,0.2 --hold 2",
        "hw",
        status=1,
        says=(r"quanser\.hardware\) is not installed",),
        when="no-sdk",
    ),
    Shown(
        "python -m hw run gains.json --device replay --replay p5.toml",
        "hw",
        says=(r"hw run: replay in virtual time", r"hw run: completed, 3001 samples"),
    ),
    Shown(
        "python -m hw bench --samples 2000",
        "hw",
        says=(r"2000 samples each", r"naive time\.sleep"),
    ),
    # Its output, as printed in a folder of its own: the docs' block (a test below).
    Shown("python -m hw run gains.json --step 0.5", "hw-print", says=()),
    Shown(
        "python -m hw run gains.json --device q2_usb --step 0.5 --out run1.toml",
        "hw",
        status=1,
        says=(r"quanser\.hardware\) is not installed",),
        when="no-sdk",
    ),
]
#: The gains of docs/hardware.md's printed run.
HW_GAINS = {"kp": 120.9, "ki": 1.67, "kd": 4.1, "v_limit": 6.0}


# ---------------------------------------------------------------- what the text shows


def _commands_in(text: str, *, table_column: bool) -> list[str]:
    out = []
    fenced = False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            continue
        block = line.startswith("    ") and not line.startswith("     ")
        if block:
            cmd = re.sub(r"^\$ ", "", line.strip())
            cmd = re.sub(r"\s+#.*$", "", cmd)
            if cmd.startswith(STARTS) and not PLACEHOLDER.search(cmd.replace("'.[test]'", "")):
                out.append(cmd)
                continue
        cells = line.split(" | ") if table_column and line.startswith("| ") else []
        in_command_column = (
            len(cells) > 2
            and cells[0].startswith("| Part")
            or (len(cells) > 2 and cells[0].startswith("| pre-lab"))
        )
        for span in re.findall(r"`([^`]+)`", line):
            if not span.startswith(("jaxcart ", "python -m ")) or PLACEHOLDER.search(span):
                continue
            handout = in_command_column and span in cells[1]
            if handout or len(span.split()) > (3 if span.startswith("python") else 2):
                out.append(span)
            elif span.split()[1].startswith("--"):  # an option of jaxcart itself
                out.append(span)
    return out


def shown() -> dict[str, list[str]]:
    """{command: [files that show it]} of README.md and docs/*.md."""
    out: dict[str, list[str]] = {}
    for path in DOCS:
        text = path.read_text(encoding="utf-8")
        for cmd in _commands_in(text, table_column=path.name == "README.md"):
            out.setdefault(cmd, []).append(path.name)
    return out


def test_every_command_shown_is_run_here():
    listed = {s.text for s in SHOWN}
    found = shown()
    assert set(found) - listed == set(), "shown but not run: add them to SHOWN"
    assert listed - set(found) == set(), "in SHOWN but no longer shown: remove them"


def test_the_set_up_and_test_commands_are_what_ci_runs():
    run = (ROOT / ".ci" / "run").read_text().strip().splitlines()[-1]
    test_command = next(s.text for s in SHOWN if "pytest" in s.text)
    assert run == test_command


@pytest.mark.parametrize("shown_cmd", [s for s in SHOWN if s.elsewhere], ids=lambda s: s.text)
def test_the_lab_runs_as_written_once_in_the_suite(shown_cmd):
    source = (ROOT / shown_cmd.elsewhere).read_text()
    argv = shlex.split(shown_cmd.text.split("&&")[-1].strip())[1:]  # after jaxcart
    assert (
        f"in_folder(folder, {json.dumps(argv)})" in source or f"argv = {json.dumps(argv)}" in source
    )


# ---------------------------------------------------------------- running them


@dataclass
class Ran:
    status: int
    out: str
    folder: Path
    files: list = field(default_factory=list)


def _argv(cmd: str) -> tuple[str, list[str]]:
    tokens = shlex.split(cmd)
    if tokens[0] == "jaxcart":
        return "jaxcart", tokens[1:]
    if tokens[:3] == ["python", "-m", "hw"]:
        return "hw", tokens[3:]
    raise AssertionError(f"no way to run {cmd!r} here")


def _run(cmd: str, folder: Path) -> Ran:
    import hw.cli
    from tuning.commands.main import main

    program, argv = _argv(cmd)
    buffer = io.StringIO()
    here = os.getcwd()
    os.chdir(folder)
    try:
        with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(buffer):
            try:
                status = (main if program == "jaxcart" else hw.cli.main)(argv)
            except SystemExit as exc:
                status = exc.code
    finally:
        os.chdir(here)
    return Ran(int(status or 0), buffer.getvalue(), folder)


def _port_5006():
    """The port `jaxcart app` serves on as shown, one run at a time: each xdist worker runs
    every shown command (and another checkout's suite may too), so the runs take a lock."""
    import fcntl
    import tempfile

    lock = open(Path(tempfile.gettempdir()) / "jaxcart-docs-app-5006.lock", "w")  # noqa: SIM115
    fcntl.flock(lock, fcntl.LOCK_EX)
    return contextlib.closing(lock)  # (closing the file releases the lock)


@contextlib.contextmanager
def _app_opens_and_closes():
    """`jaxcart app` serves until Ctrl-C and opens the browser: here the browser fetches the
    page, and the server stops once it has answered."""
    import threading
    import urllib.request

    from tornado.ioloop import IOLoop

    pages = []
    real = webbrowser.open

    def fetch_then_stop(url, *args, **kwargs):
        loop = IOLoop.current()

        def get():
            with urllib.request.urlopen(url, timeout=600) as response:
                pages.append((response.status, response.read().decode()))
            loop.add_callback(loop.stop)

        threading.Thread(target=get, daemon=True).start()
        return True

    webbrowser.open = fetch_then_stop
    try:
        yield pages
    finally:
        webbrowser.open = real


def _folders(tmp: Path) -> dict[str, Path]:
    from hw.control_law import PID
    from hw.gains import write_gains

    start = tmp / "start"
    repository = tmp / "repository"
    hw_folder, hw_print = tmp / "hw", tmp / "hw-print"
    for f in (start, repository, hw_folder, hw_print):
        f.mkdir()
    if REALDATA.is_dir():
        (tmp / "shared").symlink_to(REALDATA.parent)
        shutil.copytree(REALDATA, tmp / "realdata")
    for f in (hw_folder, hw_print):
        write_gains(f / "gains.json", PID(**HW_GAINS), note="docs/hardware.md")
    return {
        "start": start,
        "examples": start / "jaxcart-examples",
        "repository": repository,
        "realdata": tmp / "realdata",
        "hw": hw_folder,
        "hw-print": hw_print,
    }


def _skip(s: Shown) -> str | None:
    if s.when == "realdata" and not REALDATA.is_dir():
        return "../shared/realdata is not beside this checkout"
    if s.when == "no-sdk":
        import importlib.util

        if importlib.util.find_spec("quanser") is not None:
            return "the Quanser SDK is installed here: this would drive a board"
    return None


@pytest.fixture(scope="module")
def ran(tmp_path_factory) -> dict[str, Ran]:
    """Every command of SHOWN run once in its folder, in order: {text: Ran}."""
    from fakeclock import FakeClock

    import hw.pacing

    folders = _folders(tmp_path_factory.mktemp("docs"))
    out = {}
    for s in SHOWN:
        if s.elsewhere or s.folder == "ci" or _skip(s):
            continue
        if s.folder == "start":  # jaxcart examples && cd jaxcart-examples
            out[s.text] = _run(s.text.split("&&")[0], folders["start"])
            continue
        if "--replay p5.toml" in s.text:
            # p5.toml: on a PC without a board, the simulated cart's run of the same gains
            # (docs/hardware.md says so).
            made = _run(
                "python -m hw run gains.json --device sim --step 0.5 --out p5.toml", folders["hw"]
            )
            assert made.status == 0, made.out
        real = hw.pacing.SYSTEM_TIMER
        if "--real-time" in s.text:  # paced on a clock the test drives (not the load's)
            hw.pacing.SYSTEM_TIMER = FakeClock().timer
        try:
            if s.text == "jaxcart app":
                with _port_5006(), _app_opens_and_closes() as pages:
                    out[s.text] = _run(s.text, folders[s.folder])
                assert pages and pages[0][0] == 200 and "<html" in pages[0][1].lower()
            else:
                out[s.text] = _run(s.text, folders[s.folder])
        finally:
            hw.pacing.SYSTEM_TIMER = real
    return out


@pytest.mark.parametrize(
    "s", [s for s in SHOWN if not s.elsewhere and s.folder != "ci"], ids=lambda s: s.text
)
def test_a_command_shown_runs_as_written_and_says_what_the_text_says(s, ran):
    reason = _skip(s)
    if reason:
        pytest.skip(reason)
    r = ran[s.text]
    assert r.status == s.status, r.out
    assert "Traceback" not in r.out
    for pattern in s.says:
        assert re.search(pattern, r.out, flags=re.M), (pattern, r.out)
    for name in s.writes:
        assert (r.folder / name).is_file(), (name, r.out)


def test_the_run_docs_hardware_prints_is_what_it_prints(ran):
    """docs/hardware.md's block "What a run prints", line by line; the compute time is the
    machine's (a measurement), every other number the run's own."""
    text = (ROOT / "docs" / "hardware.md").read_text()
    block = text.split("    $ python -m hw run gains.json --step 0.5")[1].split("\n\n")[0]
    expected = [line[4:] for line in block.splitlines()[1:]]
    got = ran["python -m hw run gains.json --step 0.5"].out.strip().splitlines()
    assert len(got) == len(expected), got
    for want, line in zip(expected, got, strict=True):
        pattern = re.escape(want).replace(
            r"compute\ median\ 1\.8\ us", r"compute\ median\ [0-9.]+\ us"
        )
        pattern = pattern.replace(r"3001\ samples\ \.\.\.", r"3001\ samples\ .*")
        assert re.fullmatch(pattern, line), (want, line)


def test_a_missing_recording_named_like_a_built_in_one_says_where_that_is(tmp_path, capsys):
    from tuning.commands.main import main

    os.chdir(tmp_path)
    try:
        assert main(["fit", "tap.toml", "--params", "B_eq,f_c", "--classic"]) == 2
    finally:
        os.chdir(ROOT)
    err = capsys.readouterr().err
    (line,) = err.splitlines()
    assert line.startswith("jaxcart fit: error: experiment file tap.toml not found; the built-in")
    assert "jaxcart/data/tap.toml: jaxcart examples copies the built-in recordings into " in line
    assert main(["fit", str(tmp_path / "mine.toml")]) == 2
    assert "the built-in" not in capsys.readouterr().err  # no such built-in name
