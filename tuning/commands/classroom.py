"""``jaxcart class``: the lab over every student's (or group's) folder of a class, one table.

    jaxcart class CLASS_DIR                       # -> ./jaxcart-class/class.html, class.csv
    jaxcart class CLASS_DIR --out REPORT --workers 4 --diagnosis

CLASS_DIR holds one sub-folder per student or group, each what ``jaxcart lab --data`` reads.
The logic is :func:`tuning.lab.classroom.run_class`; this module parses and prints.
"""

from __future__ import annotations

from pathlib import Path

from jaxcart.errors import UserError

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "class",
        help="run the lab for every student folder of a class: one table, flags, figures",
        description="Run the lab report (jaxcart lab) on every sub-folder of CLASS_DIR, in "
        "parallel processes, and write one table of every handout number per student "
        "(class.csv, a self-contained class.html, class.json) with Part (v)'s step checked "
        "against the spec (settling < 1 s, overshoot < 5 %), flags (a failed lab, a part "
        "lost to a file that cannot be used, a missing part, a file the lab did not use, an "
        "estimate of B_eq or f_c ten times off the class's median), the class's "
        "distributions and overlays of everyone's recordings, and a link to each student's "
        "report. A broken or missing file costs its part, not the student's lab; a folder the "
        "lab refuses as a whole is one failed row; the others complete. With the compilation "
        "cache on, one student's lab runs alone first and compiles the class's programs once.",
    )
    p.add_argument(
        "folder",
        metavar="CLASS_DIR",
        type=Path,
        help="the class folder: one sub-folder of recordings per student or group",
    )
    p.add_argument(
        "--out",
        metavar="REPORT_DIR",
        type=Path,
        help="output folder (default ./jaxcart-class, or ./jaxcart-class-N if it exists)",
    )
    p.add_argument(
        "--force", action="store_true", help="write into an existing, non-empty --out folder"
    )
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="labs run at once, each in a process of its own (default: one per core)",
    )
    p.add_argument(
        "--diagnosis",
        action="store_true",
        help="add each lab's diagnosis section (off by default: it is most of a lab's time, "
        "about a minute per student)",
    )
    p.set_defaults(func=run)


def run(args) -> int:
    # lazy: imports jax, scipy and matplotlib, 1.9 s at start-up (python -X importtime)
    from tuning.lab.classroom import run_class

    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers {args.workers}: give at least 1 process")
    result = run_class(
        args.folder,
        args.out,
        workers=args.workers,
        diagnosis=args.diagnosis,
        force=args.force,
        cache=not args.no_cache,
    )
    counts = result.counts()
    verdicts = [s.verdict for s in result.students]
    print(
        f"{counts['students']} students: {counts['complete']} complete, {counts['failed']} "
        f"failed; spec: {verdicts.count('pass')} pass, {verdicts.count('fail')} fail, "
        f"{verdicts.count('n/a')} not measured; {result.seconds:.1f} s with {result.workers} "
        f"processes"
    )
    for s in result.students:
        for note in s.flags:
            print(f"  {s.name}: {note}")
    for name in ("class.html", "class.csv", "class.json"):
        print(f"wrote {result.out / name}")
    return 0
