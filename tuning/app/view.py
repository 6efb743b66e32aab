"""The design page drawn with Bokeh: sliders on the left, the step response and the voltage in
the middle, the feasible region and the poles on the right, the metric table under the sliders.
The three columns fit a 1280 x 720 screen (:data:`PAGE_WIDTH`) and wrap onto the next line on a
narrower one.

The numbers come from :mod:`tuning.app.design`; this module only turns them into Bokeh models.
:func:`build` fills a :class:`bokeh.document.Document` (a server session's or a notebook's), so
the same page runs under ``jaxcart app`` and in Jupyter. Models the browser test and the latency
benchmark look up carry names: the sliders ``kp``, ``ki``, ``kd``, ``tau``, ``setpoint``; the data
sources ``response``, ``region``, ``poles``; the metric table ``metrics``.
"""

from __future__ import annotations

import html
import math

import numpy as np
from bokeh.events import Tap
from bokeh.layouts import column, row
from bokeh.models import (
    BoxAnnotation,
    ColumnDataSource,
    Div,
    Legend,
    LegendItem,
    LinearColorMapper,
    Range1d,
    SingleIntervalTicker,
    Slider,
    Span,
)
from bokeh.plotting import figure

from tuning.app.design import (
    EXCURSION,
    RANGES,
    STATUS_NAMES,
    TRAVEL,
    V_LIMIT,
    Design,
    DesignProblem,
    Region,
    Settings,
    checks_of,
    snap,
)

#: Slider order and titles: the handout writes the PID as kp, ki, kd. tau is shown in ms.
SLIDERS = ("kp", "ki", "kd", "tau", "setpoint")
TITLES = {
    "kp": "kp [V/m]",
    "ki": "ki [V/(m s)]",
    "kd": "kd [V s/m]",
    "tau": "derivative filter tau [ms]",
    "setpoint": "setpoint [m]",
}
#: Slider value = SI value x this (tau in ms on the page).
SCALE = {"tau": 1e3}
#: Region colours by status code (design.STATUS_NAMES): green feasible, orange/purple one
#: bound missed, grey both, black diverged.
REGION_COLOURS = ("#4daf4a", "#ff7f00", "#984ea3", "#bdbdbd", "#252525")
#: The poles plot's window [1/s]: the dominant poles of the lab's gains; faster ones are counted.
POLE_WINDOW = (-150.0, 20.0, -100.0, 100.0)
#: Widths [px] of the three columns: sliders and metrics, the response and the voltage, the
#: region and the poles. With Bokeh's 5 px margins they fill a 1280 px wide window
#: (:data:`PAGE_WIDTH`) without a scroll bar; a narrower one wraps the right column under.
CONTROLS_WIDTH, MIDDLE_WIDTH, RIGHT_WIDTH = 300, 550, 400
PAGE_WIDTH = 1280
SIM_COLOUR, REC_COLOUR, NOMINAL_COLOUR = "#1f77b4", "#d62728", "#7f7f7f"


def build(doc, problem: DesignProblem, *, narrow: bool = False) -> DesignPage:
    """Fill ``doc`` with the design page of ``problem``; returns the page (its models and
    :meth:`DesignPage.update`). ``narrow``: the region and the poles under the response
    instead of beside it (a notebook cell is about 1000 px wide)."""
    page = DesignPage(problem, narrow=narrow)
    doc.add_root(page.layout)
    doc.title = "jaxcart design page"
    page.doc = doc
    return page


class DesignPage:
    """The page's models and the one update that redraws them from the sliders."""

    def __init__(self, problem: DesignProblem, *, narrow: bool = False):
        self.problem = problem
        self.doc = None
        self._pending = False
        self._setpoint = None
        start = problem.start
        self.sliders = {name: _slider(name, getattr(start, name)) for name in SLIDERS}
        self.response = ColumnDataSource(_empty("t", "y", "r", "v"), name="response")
        self.nominal = ColumnDataSource(_empty("t", "y", "v"), name="nominal")
        self.region = ColumnDataSource(
            dict(image=[np.zeros((1, 1), np.int8)], x=[0.0], y=[0.0], dw=[1.0], dh=[1.0]),
            name="region",
        )
        self.point = ColumnDataSource(dict(kp=[start.kp], kd=[start.kd]), name="point")
        self.poles = ColumnDataSource(_empty("re", "im"), name="poles")
        self.spec = ColumnDataSource(_empty("t", "lo", "hi"), name="spec")
        self.bounds = ColumnDataSource(dict(xs=[], ys=[]), name="bounds")
        self.metrics = Div(name="metrics", width=CONTROLS_WIDTH - 10)
        self.pole_list = Div(name="pole_list", width=RIGHT_WIDTH)
        self.figures = _Figures(self)
        for slider in self.sliders.values():
            slider.on_change("value", self._moved)
        self.figures.region.on_event(Tap, self._tapped)
        note = Div(text=_note(problem), width=CONTROLS_WIDTH - 10)
        controls = column(*self.sliders.values(), self.metrics, note, width=CONTROLS_WIDTH)
        middle = column(self.figures.position, self.figures.voltage)
        if narrow:
            poles = column(self.figures.poles, self.pole_list)
            self.layout = column(row(controls, middle), row(self.figures.region, poles))
        else:
            right = column(self.figures.region, self.figures.poles, self.pole_list)
            # A flex row that wraps: on a window narrower than the three columns the right one
            # goes under the others instead of off the screen.
            self.layout = row(controls, middle, right, styles={"flex-wrap": "wrap"})
        self.update()

    def settings(self) -> Settings:
        """The sliders' position in SI units."""
        values = {n: float(s.value) / SCALE.get(n, 1.0) for n, s in self.sliders.items()}
        return Settings(**values)

    def _moved(self, attr, old, new):
        # A drag sends many values; while the page computes, the later ones queue. Coalesce:
        # one update per tick, reading the sliders as they are when it runs.
        served = self.doc is not None and self.doc.session_context is not None
        if not served:
            self.update()
        elif not self._pending:
            self._pending = True
            self.doc.add_next_tick_callback(self._tick)

    def _tick(self):
        self._pending = False
        self.update()

    def _tapped(self, event):
        """A click on the region moves kp and kd there, to the sliders' nearest steps."""
        for name, value in (("kp", event.x), ("kd", event.y)):
            if value is not None and math.isfinite(value):
                self.sliders[name].value = snap(name, value) * SCALE.get(name, 1.0)

    def update(self) -> Design:
        """Recompute at the sliders' position and push every changed number to the page.

        Served, Bokeh sends one message per changed property, in order, and the page applies
        each as it arrives; the response goes last, so that when the page sees it change (what
        a person watches, and what :func:`browser.timed_moves` times) the rest has arrived."""
        if self.doc is not None:
            self.doc.hold("combine")
        try:
            return self._update()
        finally:
            if self.doc is not None:
                self.doc.unhold()

    def _update(self) -> Design:
        settings = self.settings()
        design = self.problem.design(settings)
        region = self.problem.region_at(settings)
        if design.nominal is not None:
            nom = design.nominal
            self.nominal.data = dict(
                t=np.asarray(nom.time), y=np.asarray(nom.position), v=np.asarray(nom.voltage)
            )
        self.point.data = dict(kp=[settings.kp], kd=[settings.kd])
        self.poles.data = dict(re=design.poles.real, im=design.poles.imag)
        self.figures.show(design, region)
        self.metrics.text = metrics_html(design, self.problem)
        res = design.response
        runs = dict(y=np.asarray(res.position), v=np.asarray(res.voltage))
        if len(self.response.data["t"]) == len(res.time) and settings.setpoint == self._setpoint:
            self.response.data.update(runs)  # time and reference as they were: send half
        else:
            self.response.data = dict(t=np.asarray(res.time), r=np.asarray(res.reference), **runs)
        self._setpoint = settings.setpoint
        return design


class _Figures:
    """The four plots and the annotations that move with the settings."""

    def __init__(self, page: DesignPage):
        self.page = page
        problem = page.problem
        tools = "pan,wheel_zoom,box_zoom,reset,save"
        horizon = float(problem.spec.horizon)
        self.position = figure(
            title="Step response (exact simulator, 6 V limit)",
            x_axis_label="time [s]",
            y_axis_label="position [m]",
            width=MIDDLE_WIDTH,
            height=340,
            tools=tools,
            x_range=Range1d(0.0, horizon),
            name="position_figure",
        )
        p = self.position
        # The spec drawn as glyphs (not annotations) so that the legend names them: the 2 %
        # band shaded, the overshoot bound and the settling bound dotted red.
        p.varea(
            "t",
            "lo",
            "hi",
            source=page.spec,
            fill_color="#2ca02c",
            fill_alpha=0.15,
            legend_label="2 % band",
        )
        p.multi_line(
            "xs",
            "ys",
            source=page.bounds,
            line_color="#d62728",
            line_dash="dotted",
            line_width=1.5,
            legend_label="spec: overshoot, settling",
        )
        p.line(
            "t",
            "r",
            source=page.response,
            color="black",
            line_dash="dashed",
            legend_label="reference",
        )
        p.line(
            "t",
            "y",
            source=page.response,
            color=SIM_COLOUR,
            line_width=2,
            legend_label=problem.plant_label or "simulated",
        )
        if problem.plant_label is not None:
            p.line(
                "t",
                "y",
                source=page.nominal,
                color=NOMINAL_COLOUR,
                line_dash="dashed",
                line_width=1.5,
                legend_label="handout plant",
            )
        _recording(page, p, "position")
        _legend_above(p)
        self.voltage = self._voltage_figure(page, tools, horizon)
        self.region = self._region_figure(page)
        self.poles = self._poles_figure(page)

    def _voltage_figure(self, page, tools, horizon):
        v = figure(
            title="Voltage",
            x_axis_label="time [s]",
            y_axis_label="voltage [V]",
            width=MIDDLE_WIDTH,
            height=260,
            tools=tools,
            x_range=self.position.x_range,
            y_range=Range1d(-1.25 * V_LIMIT, 1.25 * V_LIMIT),
        )
        for sign in (1, -1):
            v.add_layout(
                Span(
                    location=sign * V_LIMIT,
                    dimension="width",
                    line_color="black",
                    line_dash="dotted",
                )
            )
        v.line(
            "t",
            "v",
            source=page.response,
            color=SIM_COLOUR,
            line_width=1.5,
            legend_label="simulated",
        )
        _recording(page, v, "command")
        _legend_above(v)
        return v

    def _region_figure(self, page):
        lo_kp, hi_kp, _ = RANGES["kp"]
        lo_kd, hi_kd, _ = RANGES["kd"]
        f = figure(
            title="Feasible region",
            x_axis_label="kp [V/m]",
            y_axis_label="kd [V s/m]",
            width=RIGHT_WIDTH,
            height=390,
            tools="tap,reset,save",
            x_range=Range1d(lo_kp, hi_kp),
            y_range=Range1d(lo_kd, hi_kd),
            name="region_figure",
        )
        mapper = LinearColorMapper(palette=list(REGION_COLOURS), low=-0.5, high=4.5)
        f.image("image", x="x", y="y", dw="dw", dh="dh", source=page.region, color_mapper=mapper)
        f.scatter(
            "kp",
            "kd",
            source=page.point,
            size=12,
            marker="circle",
            fill_color="white",
            line_color="black",
            line_width=2,
        )
        # The statuses as a legend under the plot (a colour bar's labels beside it took a
        # third of the column): one square per status, at NaN so that only its entry shows (a
        # glyph without data draws no entry).
        items = []
        for colour, name in zip(REGION_COLOURS, STATUS_NAMES, strict=True):
            swatch = f.scatter(x=[math.nan], y=[math.nan], marker="square", size=10, color=colour)
            items.append(LegendItem(label=name, renderers=[swatch]))
        legend = Legend(items=items, orientation="horizontal", ncols=2, name="region_legend")
        _legend_style(legend)
        f.add_layout(legend, "below")
        return f

    def _poles_figure(self, page):
        x0, x1, y0, y1 = POLE_WINDOW
        f = figure(
            title="Closed-loop poles",
            x_axis_label="Re s [1/s]",
            y_axis_label="Im s [rad/s]",
            width=RIGHT_WIDTH,
            height=250,
            tools="pan,wheel_zoom,reset,save",
            x_range=Range1d(x0, x1),
            y_range=Range1d(y0, y1),
            name="poles_figure",
        )
        # Bokeh's default ticker put a label every 10 1/s, run together; every 50 reads.
        f.xaxis.ticker = SingleIntervalTicker(interval=50, num_minor_ticks=5)
        f.yaxis.ticker = SingleIntervalTicker(interval=50, num_minor_ticks=5)
        f.add_layout(BoxAnnotation(left=0, fill_color="#d62728", fill_alpha=0.08))
        f.add_layout(Span(location=0, dimension="height", line_color="black"))
        f.scatter(
            "re", "im", source=page.poles, marker="x", size=12, line_width=2, color=SIM_COLOUR
        )
        return f

    _setpoint = None
    _region = None

    def show_region(self, region: Region) -> None:
        kp, kd = region.kp, region.kd
        dkp, dkd = kp[1] - kp[0], kd[1] - kd[0]
        self.page.region.data = dict(
            image=[region.status],
            x=[kp[0] - dkp / 2],
            y=[kd[0] - dkd / 2],
            dw=[kp[-1] - kp[0] + dkp],
            dh=[kd[-1] - kd[0] + dkd],
        )
        self.region.title.text = (
            f"Feasible at ki = {region.ki:g}, tau = {1e3 * region.tau:g} ms: "
            f"{region.n_feasible}/{region.status.size}"
        )

    def show(self, design: Design, region: Region) -> None:
        """Move the annotations and titles to ``design`` and ``region``."""
        s = design.settings
        page = self.page
        if s.setpoint != self._setpoint:
            self._setpoint = s.setpoint
            page.spec.data, page.bounds.data = spec_lines(page.problem.spec, s.setpoint)
        if region is not self._region:  # moving kp or kd keeps the region: send nothing
            self._region = region
            self.show_region(region)
        x0, x1, y0, y1 = POLE_WINDOW
        p = design.poles
        outside = int(np.count_nonzero((p.real < x0) | (p.real > x1) | (abs(p.imag) > y1)))
        verdict = "stable" if design.stable else "UNSTABLE"
        beyond = f", {outside} off the plot" if outside else ""
        self.poles.title.text = f"Closed-loop poles: {verdict}{beyond}"
        page.pole_list.text = pole_text(p)


def pole_text(poles: np.ndarray) -> str:
    """The poles [1/s] as a line of text, slowest first (a pole near 0 is the slow creep the
    plot cannot show apart from the others)."""
    order = np.argsort(np.abs(poles))
    parts = []
    for s in poles[order]:
        if abs(s.imag) < 1e-9 * max(1.0, abs(s.real)):
            parts.append(f"{s.real:.3g}")
        elif s.imag > 0:
            parts.append(f"{s.real:.3g} &plusmn; {s.imag:.3g}j")
    return "<p style='font-size:90%'>poles [1/s], slowest first: " + ", ".join(parts) + "</p>"


def _legend_above(fig) -> None:
    """The legend in a row above the plot, off the data and inside the column's width (beside
    the plot it took a third of the width); a click on an entry hides its line."""
    legend = fig.legend[0]
    legend.click_policy = "hide"
    legend.orientation = "horizontal"
    legend.ncols = 4 if len(legend.items) <= 4 else 3
    _legend_style(legend)
    fig.add_layout(legend, "above")


def _legend_style(legend) -> None:
    legend.label_text_font_size = "9pt"
    legend.padding = 2
    legend.spacing = 8
    legend.margin = 2
    legend.border_line_alpha = 0.0


def spec_lines(spec, setpoint: float) -> tuple[dict, dict]:
    """The spec on the position plot for a step to ``setpoint`` [m] from 0: the settling band
    (t, lo, hi) and the bounds as polylines: the overshoot limit over the run, the settling
    time as a vertical line."""
    horizon = float(spec.horizon)
    half = spec.band * abs(setpoint)
    band = dict(t=[0.0, horizon], lo=[setpoint - half] * 2, hi=[setpoint + half] * 2)
    over = setpoint * (1 + spec.overshoot / 100.0)
    lo, hi = sorted((0.0, over))
    t_s = float(spec.settling_time)
    bounds = dict(xs=[[0.0, horizon], [t_s, t_s]], ys=[[over, over], [lo, hi]])
    return band, bounds


def _slider(name: str, value: float) -> Slider:
    lo, hi, step = RANGES[name]
    scale = SCALE.get(name, 1.0)
    fmt = "0.00" if step * scale < 0.1 else "0.0" if step * scale < 1 else "0"
    return Slider(
        start=lo * scale,
        end=hi * scale,
        step=step * scale,
        value=value * scale,
        title=TITLES[name],
        name=name,
        css_classes=[f"slider-{name}"],
        format=fmt,
        width=CONTROLS_WIDTH - 20,
    )


def _empty(*names) -> dict:
    return {n: np.zeros(0) for n in names}


def _recording(page: DesignPage, fig, what: str) -> None:
    rec = page.problem.overlay
    if rec is None:
        return
    values = rec.position if what == "position" else rec.command
    if values is None:
        return
    source = ColumnDataSource(dict(t=rec.time, y=values), name=f"recording_{what}")
    fig.line(
        "t",
        "y",
        source=source,
        color=REC_COLOUR,
        line_width=1.2,
        alpha=0.8,
        legend_label=f"recorded ({rec.name})",
    )


#: What an infinite metric means, by row (step_info's inf).
NOT_REACHED = {"settling time": "not settled", "rise time": "never at 90 %"}


def _number(value: float, unit: str, name: str = "") -> str:
    if not math.isfinite(value):
        return NOT_REACHED.get(name, "diverged") if value > 0 else "-"
    if unit == "m":
        return f"{1e3 * value:.2f} mm"
    if unit == "s":
        return f"{value:.3f} s"
    return f"{value:.2f} {unit}"


def metrics_html(design: Design, problem: DesignProblem) -> str:
    """The metric table: each metric, its bound, simulated (green: meets, red: misses) and,
    with a recording, recorded."""
    if design.info is None:
        return "<p>setpoint 0 m: no step to measure; move the setpoint.</p>"
    overlay = problem.overlay
    rec = overlay.info if overlay is not None else None
    # The bound beside the metric's name (a column of its own made the table wider than the
    # sliders' column); rows and cells named for the browser test.
    head = "<tr><th>metric, spec</th><th>simulated</th>"
    head += "<th>recorded</th></tr>" if rec is not None else "</tr>"
    rows = [head]
    recorded = {}
    if rec is not None:
        excursion = float(np.max(np.abs(overlay.position)))  # from its start y0
        recorded = {c.name: c for c in checks_of(rec, problem.spec, excursion)}
    for check in design.checks:
        name = html.escape(check.name)
        bound = ""
        if check.bound is not None:
            shown, unit = (
                (1e3 * check.bound, "mm") if check.unit == "m" else (check.bound, check.unit)
            )
            bound = f' <span style="color:#555;white-space:nowrap">&lt; {shown:g} {unit}</span>'
        colour = {True: "#1a7f37", False: "#cf222e", None: "inherit"}[check.ok]
        cell = html.escape(_number(check.value, check.unit, check.name))
        line = f'<tr data-metric="{name}"><td style="white-space:normal">{name}{bound}</td>'
        line += f'<td class="sim" style="color:{colour};font-weight:bold">{cell}</td>'
        if rec is not None:
            mine = html.escape(_number(recorded[check.name].value, check.unit, check.name))
            line += f'<td class="rec">{mine}</td>'
        rows.append(line + "</tr>")
    missing = [c.name for c in design.checks if c.ok is False and c.name != EXCURSION]
    if design.meets:
        verdict = '<b style="color:#1a7f37">meets the spec</b>'
    elif not missing and design.on_track:
        verdict = '<b style="color:#cf222e">misses: the run diverged</b>'
    elif not missing:
        verdict = '<b style="color:#cf222e">meets the spec but leaves the track</b>'
    else:
        verdict = f'<b style="color:#cf222e">misses: {", ".join(missing)}</b>'
    spec = problem.spec
    step = design.settings.setpoint
    other = "" if step == spec.step else f"; the handout's step is {spec.step:g} m"
    title = (
        f"<p>{verdict} (step {step:.2f} m, settling &lt; {spec.settling_time:g} s, "
        f"overshoot &lt; {spec.overshoot:g} %, {V_LIMIT:g} V{other})</p>"
    )
    if not design.on_track:
        title += (
            f'<p style="color:#cf222e">leaves the track: the cart would move '
            f"{_number(design.excursion, 'm')} from its start, beyond the {1e3 * TRAVEL:g} mm "
            "travel (it would hit the end stop)</p>"
        )
    table = '<table style="border-spacing:6px 2px;font-size:90%;white-space:nowrap">'
    return title + table + "".join(rows) + "</table>" + margins_html(design.margins)


def margins_html(m) -> str:
    """The design's margins on the design plant in one line (and the hunting warning in red):
    gain and phase margins, peak sensitivity, the encoder's ripple."""
    if m is None:
        return ""
    gm = (
        "∞"
        if not math.isfinite(m.gain_margin)
        else f"{m.gain_margin:.3g} ({m.gain_margin_db:.1f} dB)"
    )
    delay = f", its {1e3 * m.delay:.3g} ms delay" if m.delay else ""
    text = (
        f"<p data-metric='margins' style='font-size:90%'>margins (linear loop{delay}): gain "
        f"{gm}, phase {m.phase_margin:.1f}°, peak sensitivity {m.peak_sensitivity:.2f}; "
        f"one encoder count moves the command by {m.ripple:.3g} V</p>"
    )
    if m.hunting:
        text += f"<p style='font-size:90%;color:#cf222e'>{html.escape(m.hunting)}</p>"
    return text


def _note(problem: DesignProblem) -> str:
    lines = [
        "Exact simulator (event-exact friction, hard 6 V clip) over "
        f"{problem.spec.horizon:g} s, its run checked against the track's "
        f"{1e3 * TRAVEL:g} mm travel; region: {problem.region_points}x{problem.region_points} "
        "hard-clip runs at the current ki, settling and overshoot (click it to move kp, kd "
        "there); poles: the linear digital loop (no limit, no friction) as s = ln(z)/Ts."
    ]
    if problem.plant_label is not None:
        lines.append(
            f"Design plant: the {html.escape(problem.plant_label)}; grey: the handout's plant."
        )
    if problem.overlay is not None:
        o = problem.overlay
        lines.append(f"Red: {html.escape(o.name)}, from its start y0 = {o.y0:.4f} m.")
    return "<p style='font-size:85%;color:#555'>" + " ".join(lines) + "</p>"
