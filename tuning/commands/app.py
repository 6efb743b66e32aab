"""``jaxcart app``: the interactive design page in the browser (tuning/app), served from this
machine until Ctrl-C.

    jaxcart app                                   # the handout's plant, its gains to start
    jaxcart app --data pid.toml --plant P.toml    # your recording and your fitted plant
"""

from __future__ import annotations

from jaxcart.errors import UserError
from tuning.app.port import check_port

# What imports jax (jaxcart's simulator, tuning's engines) is imported inside the functions that
# run the command: building the parser must start no jax (importing jax takes 2.4 s against
# 0.65 s for all of ``jaxcart --help``, measured on 2 cores; tests/test_layout.py checks it).


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "app",
        help="interactive design page: move kp, ki, kd and see the step, metrics, region, poles",
        description=(
            "Serve a local web page where sliders move kp, ki, kd, the derivative filter tau "
            "and the setpoint, and the page shows at once the step response on the exact "
            "simulator with the 6 V limit, the voltage, rise/settling/overshoot/steady-state "
            "error against the handout's spec (0.5 m, settling < 1 s, overshoot < 5 %), the "
            "feasible region of the (kp, kd) plane at the current ki and the closed-loop "
            "poles. Works offline. In Jupyter: tuning.app.server.show_in_notebook()."
        ),
    )
    p.add_argument(
        "--data",
        metavar="REC.toml",
        help="a closed-loop step recording to overlay (the sliders start at its gains)",
    )
    p.add_argument(
        "--plant",
        metavar="PLANT.toml",
        help="design on this plant: a plant file (from fit or diagnose), or an experiment "
        "file's own [plant] table; the handout's plant is drawn beside it",
    )
    p.add_argument(
        "--port", type=int, default=5006, help="port to serve on (5006; 0: any free port)"
    )
    p.add_argument(
        "--address", default="127.0.0.1", help="address to serve on (127.0.0.1: this machine)"
    )
    p.add_argument(
        "--no-browser", action="store_true", help="do not open the page in the web browser"
    )
    p.set_defaults(func=run)


def run(args) -> int:
    if not 0 <= args.port <= 65535:
        raise UserError(f"--port {args.port}: give a port from 1 to 65535 (0: any free port)")
    check_port(args.address, args.port)  # before seconds of reading and compiling
    # lazy: imports jax, bokeh, scipy and matplotlib, 3.4 s at start-up (python -X importtime)
    from tuning.app.design import problem_from_files
    from tuning.app.server import serve

    problem = problem_from_files(args.data, args.plant)
    return serve(problem, port=args.port, address=args.address, browser=not args.no_browser)
