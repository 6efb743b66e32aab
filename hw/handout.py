"""The handout's appendix: the IP02 cart's constants, written once (numpy-free, so that the
hardware side, the simulated device in :mod:`hw.devices.sim` and jaxcart's plant all read the
same numbers).

>>> round(APPENDIX["Kt"] * APPENDIX["Kg"] / (APPENDIX["Rm"] * APPENDIX["r_mp"]), 4)  # gamma [N/V]
1.7235
"""

#: The plant's own parameters (SI units): cart plus weight M [kg], equivalent viscous friction
#: B_eq [kg/s], armature resistance Rm [ohm], torque constant Kt [N m/A], back-EMF constant Km
#: [V s/rad], rotor inertia Jm [kg m^2], gearbox ratio Kg [-], pinion radius r_mp [m], gearbox
#: and motor efficiencies eta_g, eta_m [-], and the fitted input-gain multiplier gamma_scale [-].
APPENDIX = {
    "M": 0.94,
    "B_eq": 5.4,
    "Rm": 2.6,
    "Kt": 0.00767,
    "Km": 0.00767,
    "Jm": 3.9e-7,
    "Kg": 3.71,
    "r_mp": 6.35e-3,
    "eta_g": 1.0,
    "eta_m": 1.0,
    "gamma_scale": 1.0,
}
#: The range each of them may take (inclusive, SI units): beyond it a value is in other units
#: or not this lab's cart (B_eq 4600 is g/s, M 940 is grams).
VALID = {
    "M": (1e-3, 100.0),
    "B_eq": (0.0, 200.0),
    "Rm": (1e-3, 1e3),
    "Kt": (0.0, 10.0),
    "Km": (0.0, 10.0),
    "Jm": (0.0, 1.0),
    "Kg": (1e-3, 1e3),
    "r_mp": (1e-5, 1.0),
    "eta_g": (1e-3, 1.0),
    "eta_m": (1e-3, 1.0),
    "gamma_scale": (0.01, 100.0),
}
#: Encoder resolution of the IP02 [m/count].
ENCODER_RESOLUTION = 2.275e-5
#: Length of the track [m] and usable travel of the cart [m].
TRACK_LENGTH = 0.990
TRAVEL = 0.814
