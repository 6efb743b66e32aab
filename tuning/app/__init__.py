"""The interactive design page (``jaxcart app``): move kp, ki, kd, the derivative filter and
the setpoint and see the step response on the exact simulator, its metrics against the
handout's specification, the feasible region of the (kp, kd) plane and the closed-loop poles.

The numbers are computed in :mod:`tuning.app.design` (no drawing, tested directly); the page
is drawn by :mod:`tuning.app.view` (Bokeh) and served by :mod:`tuning.app.server` (a local Bokeh
server, or inside a Jupyter notebook); :mod:`tuning.app.browser` drives it in headless
Chromium for the test and the latency benchmark (``tools/app_latency.py``).
"""
