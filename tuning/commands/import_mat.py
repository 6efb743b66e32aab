"""``jaxcart import``: raw QUARC/Simulink .mat files (and CSV files of named columns without
an experiment file) to experiment files, nothing else.

    jaxcart import part1.1.mat 2.1pos.mat 2.1volt.mat          # -> part1.1.toml, 2.1pos.toml
    jaxcart import run7.mat --as pi --out lab/                 # name the experiment yourself
    jaxcart import mux.mat:scope[1]                            # the position is column 1
    jaxcart import other_sim.csv                               # time,position,voltage

Each run (a file, or files whose names differ only by the signal: 2.1pos.mat + 2.1volt.mat)
is recognised from its content and names (jaxcart.recognition); the guess and its evidence are
printed, and the experiment file it implies is written (its [data] maps the .mat variables,
nothing is copied). Weak evidence writes nothing for that run and asks, in one line, to name
the experiment with --as; nor does a run that every command would refuse (positions in mm,
say), which is told what to convert. Existing files are never replaced without --force.
"""

from __future__ import annotations

import sys
from pathlib import Path

from jaxcart.errors import UserError
from jaxcart.recognition import EXPERIMENTS

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "import",
        help="turn raw QUARC/Simulink .mat files (or CSV files of named columns) into "
        "experiment files (no TOML to write)",
        description="Read .mat files as the lab's scopes saved them (structure with or "
        "without time, N x 2 arrays, muxed scopes, MATLAB v7.3), recognise each run's "
        "experiment from its content and names, print the guess with its evidence and write "
        "the experiment file (TOML) that maps its signals. A CSV file of named columns "
        "(time,position,voltage) is read the same way.",
    )
    p.add_argument(
        "files",
        nargs="+",
        metavar="FILE",
        help='.mat (or .csv) files; "FILE.mat:var[k]" or "FILE.mat:var[label]" chooses the '
        "position among a muxed scope's signals (k counted from 1, as MATLAB does)",
    )
    p.add_argument(
        "--as",
        dest="experiment",
        choices=tuple(EXPERIMENTS),
        help="the experiment, when you know it (for every run given): "
        + ", ".join(f"{k} (Part ({s.part}))" for k, s in EXPERIMENTS.items()),
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        type=Path,
        help="folder for the experiment files (default: beside the .mat files)",
    )
    p.add_argument("--force", action="store_true", help="replace existing experiment files")
    p.set_defaults(func=run)


def run(args) -> int:
    # lazy: imports jax, 0.45 s at start-up (python -X importtime)
    from jaxcart.files import read_imported
    from jaxcart.matimport import scan, siblings, split_source, write_imported

    paths, named, chosen = [], {}, {}
    for text in args.files:
        found = split_source(text)
        if found is None:
            raise UserError(
                f"{text}: not a .mat file nor a text table (.csv, .tsv, .txt); give FILE.mat, "
                "FILE.mat:variable or FILE.csv"
            )
        path, variable = found
        if not path.is_file():
            raise UserError(f"{path}: no such file; give the path of a .mat or .csv file")
        paths.append(path)
        if variable:
            chosen[path.name] = variable
        if args.experiment:
            named[path.name] = args.experiment
    # A file's siblings (2.1pos.mat brings 2.1volt.mat), as every other command reads it.
    paths += [s for s in dict.fromkeys(x for p in paths for x in siblings(p)) if s not in paths]
    weak = 0
    for imported in scan(paths, named=named, chosen=chosen):
        print("\n".join(imported.lines()))
        if imported.problem:
            weak += 1
            continue
        if not imported.usable():
            weak += 1
            how = f"with jaxcart import {imported.files[0].name} --as PART"
            print(imported.guess.question(imported.label, how), file=sys.stderr)
            continue
        try:  # what every command would refuse is not written (positions in mm, say)
            read_imported(imported, quiet=True)
        except UserError as exc:
            weak += 1
            print(f"  not written: {exc}; convert it and import again", file=sys.stderr)
            continue
        folder = args.out if args.out is not None else imported.files[0].parent
        toml = write_imported(imported, folder / f"{imported.stem}.toml", force=args.force)
        print(f"  wrote {toml}")
    return 2 if weak else 0
