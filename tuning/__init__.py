"""Tuning, fitting and analysis built on the jaxcart simulator."""
