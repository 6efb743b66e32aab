"""Serve the design page: a local Bokeh server (``jaxcart app``) or a Jupyter notebook cell.

Bokeh's server serves BokehJS from the installed package, so the page works offline; each
browser tab gets a session of its own (its own sliders) over one :class:`DesignProblem`, whose
feasible regions are shared through its memo.

    jaxcart app                                  # the handout's plant
    jaxcart app --data pid.toml --plant P.toml   # a recording and a fitted plant overlaid

In a Jupyter notebook (Notebook 7 and JupyterLab render Bokeh through the jupyter_bokeh
extension: ``pip install -e '.[notebook]'``), with the notebook's own address::

    from tuning.app.server import show_in_notebook
    show_in_notebook(data="pid.toml", plant="P.toml", notebook_url="localhost:8888")

The kernel runs a Bokeh server of its own for the page (its callbacks run the simulator); the
notebook gets BokehJS inline from the installed package, not from a CDN.
"""

from __future__ import annotations

import sys
import webbrowser

from bokeh.application import Application
from bokeh.application.handlers.function import FunctionHandler
from bokeh.io import output_notebook, show
from bokeh.resources import INLINE
from bokeh.server.server import Server

from jaxcart.errors import UserError
from tuning.app.design import DesignProblem, Settings, problem_from_files
from tuning.app.port import free_port, port_problem
from tuning.app.view import build

#: The port ``jaxcart app`` asks for first (Bokeh's own default).
DEFAULT_PORT = 5006


def warm(problem: DesignProblem) -> None:
    """Compute the first slider position once, so that the first page opens at once (the
    region's batched program compiles here, about a second)."""
    start = problem.start
    problem.design(start)
    problem.region_at(start)
    # The setpoint slider's other sign compiles nothing new but fills the experiment memo.
    problem.region_at(Settings(ki=start.ki, tau=start.tau, setpoint=-start.setpoint))


def make_server(problem: DesignProblem, *, port: int = DEFAULT_PORT, address="127.0.0.1"):
    """A started-to-be :class:`bokeh.server.server.Server` of the page on ``address:port``
    (port 0: a free one), accepting pages opened from that address or localhost."""
    port = port or free_port(address)
    app = Application(FunctionHandler(lambda doc: build(doc, problem)))
    origins = [f"{address}:{port}", f"localhost:{port}"]
    return Server({"/": app}, port=port, address=address, allow_websocket_origin=origins)


def serve(problem: DesignProblem, *, port=DEFAULT_PORT, address="127.0.0.1", browser=True):
    """Serve the page until Ctrl-C (or SIGTERM); prints its address first. Returns 0. The
    port is taken before the page's first position is computed, so a busy one is said at
    once."""
    try:
        server = make_server(problem, port=port, address=address)
    except OSError as exc:
        raise UserError(port_problem(address, port, exc)) from None
    print("jaxcart app: preparing the page (the region's batch compiles once)...", flush=True)
    warm(problem)
    url = f"http://{address}:{server.port}/"
    server.start()
    print(f"jaxcart app: the design page is at {url} (Ctrl-C to stop)", flush=True)
    if browser:
        server.io_loop.add_callback(webbrowser.open, url)
    try:
        server.io_loop.start()
    except KeyboardInterrupt:
        print("jaxcart app: stopped", file=sys.stderr)
    finally:
        server.stop()
    return 0


def show_in_notebook(data=None, plant=None, *, notebook_url="localhost:8888"):
    """Show the page in the running Jupyter notebook (a Bokeh server inside the kernel);
    ``notebook_url``: the host:port the notebook's page was opened at. The page computes in
    float64 (:class:`tuning.app.design.DesignProblem`), whatever the kernel has set."""
    problem = problem_from_files(data, plant)
    warm(problem)
    # INLINE: BokehJS from the installed package into the notebook (the default is a CDN).
    output_notebook(resources=INLINE, hide_banner=True)
    show(lambda doc: build(doc, problem, narrow=True), notebook_url=notebook_url)
