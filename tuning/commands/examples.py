"""``jaxcart examples``: the built-in recordings, copied into a folder of yours.

    jaxcart examples                 # -> ./jaxcart-examples/ (tap.toml, p50.toml, ..., lab.toml)
    jaxcart examples mydata          # -> ./mydata/

The README's handout commands (``jaxcart fit tap.toml --params B_eq,f_c --classic``, ...) run
in that folder as written. Nothing of yours is replaced without --force.
"""

from __future__ import annotations


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "examples",
        help="copy the built-in example recordings into a folder (./jaxcart-examples)",
        description="Copy the built-in recordings (synthetic, one per handout item: tap, P 50, "
        "ramp, P 10, PI and PID, with lab.toml, the index the lab reads) into FOLDER, where "
        "the README's commands run as written (cd FOLDER first). Existing files are never "
        "replaced without --force.",
    )
    p.add_argument(
        "folder",
        nargs="?",
        default=None,
        metavar="FOLDER",
        help="where to copy them (default ./jaxcart-examples)",
    )
    p.add_argument("--force", action="store_true", help="replace files of the same names")
    p.set_defaults(func=run)


def run(args) -> int:
    # lazy: imports jax, scipy and matplotlib, 2.3 s at start-up (python -X importtime)
    from jaxcart.files import EXAMPLES_DIR
    from tuning.lab.data import copy_examples

    folder = args.folder or EXAMPLES_DIR
    written = copy_examples(folder, force=args.force)
    stems = [p.stem for p in written if p.suffix == ".toml" and p.stem != "lab"]
    print(
        f"copied the built-in recordings ({', '.join(stems)}, each .toml + .csv, and lab.toml) "
        f"into {folder}/"
    )
    print(
        f"  cd {folder}, then e.g.: jaxcart fit tap.toml --params B_eq,f_c --classic "
        "(the README's handout table runs there as written)"
    )
    return 0
