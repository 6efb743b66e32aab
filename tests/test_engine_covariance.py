"""The engine's robust and naive covariances (tuning/estimation/engine/covariance.py) against
textbook references: ordinary least squares with white noise, and the error of a position read
through an encoder count."""

import warnings

import numpy as np
import pytest

from tuning.estimation.engine.covariance import covariances, runs


def _least_squares_residual(jac, noise):
    """The residual a least-squares fit leaves of ``noise``: (I - H) noise."""
    coef, *_ = np.linalg.lstsq(jac, noise, rcond=None)
    return noise - jac @ coef


def test_white_noise_matches_the_textbook_covariance():
    """A linear model with white noise, no encoder: the naive and the robust standard errors are
    the textbook sigma sqrt(diag (J^T J)^-1) within 8 % (the naive estimates sigma^2 from
    N = 6000 residuals, about 2 % noise; the robust sandwich's own sampling noise is a few %)."""
    rng = np.random.default_rng(3)
    n, sigma = 6000, 2e-5
    t = np.linspace(0.0, 1.0, n)
    # Columns of very different scales, as a fit's parameters have.
    jac = np.column_stack([np.ones(n), 1e-3 * np.sin(7 * t), 50.0 * t**2])
    r = _least_squares_residual(jac, sigma * rng.standard_normal(n))
    half = n // 2  # two recordings
    cov = covariances(jac, [r[:half], r[half:]], [np.zeros(half), np.zeros(n - half)], [0.0, 0.0])
    textbook = np.sqrt(np.diag(sigma**2 * np.linalg.inv(jac.T @ jac)))
    assert not cov.singular.any()
    assert np.sqrt(np.diag(cov.naive)) == pytest.approx(textbook, rel=0.08)
    assert np.sqrt(np.diag(cov.robust)) == pytest.approx(textbook, rel=0.08)


def test_a_cart_at_rest_has_the_encoder_error_of_one_count():
    """An offset fitted to a cart that rests inside one count for the whole recording: every
    sample reads the same count, the residual is 0, and the one error is the count's uniform
    one, q / sqrt(12) (one run; 1e-9 relative)."""
    n, q = 500, 2.275e-5
    jac = np.ones((n, 1))
    cov = covariances(jac, [np.zeros(n)], [np.full(n, 0.3 * q)], [q])
    assert np.sqrt(cov.robust[0, 0]) == pytest.approx(q / np.sqrt(12), rel=1e-9)
    # The naive one sees no spread at all: that is why the floor is there.
    assert cov.naive[0, 0] == 0.0


def test_one_run_that_misses_gives_a_finite_covariance_without_a_warning():
    """A model that stays within one count while the recording reads elsewhere (a candidate
    whose dead band holds the cart through a slow ramp): one run, one score, so no
    autocorrelation to estimate; the covariance is the encoder's floor, finite, and numpy
    warns of no empty mean (it did, from the bandwidth's AR(1) fit)."""
    n, q = 500, 2.275e-5
    jac = np.ones((n, 1))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cov = covariances(jac, [np.full(n, 3 * q)], [np.full(n, 0.3 * q)], [q])
    assert np.all(np.isfinite(cov.robust))
    assert np.sqrt(cov.robust[0, 0]) >= q / np.sqrt(12) * (1 - 1e-9)


def test_the_encoder_floor_bounds_the_robust_covariance():
    """Quantized data with a residual smaller than a count: the robust covariance is at least
    the encoder's share B^-1 (q^2/12 sum_b g_b g_b^T) B^-1 in every direction (eigenvalues of
    the difference >= -1e-12 of its scale), the runs those of the model within one count."""
    rng = np.random.default_rng(5)
    n, q = 3000, 2.275e-5
    t = np.linspace(0.0, 1.0, n)
    model = 0.01 * (1 - np.exp(-3 * t))  # a cart settling: runs grow as it slows
    jac = np.column_stack([np.exp(-3 * t), t * np.exp(-3 * t)])
    r = _least_squares_residual(jac, 0.1 * q * rng.standard_normal(n))
    cov = covariances(jac, [r], [model], [q])
    starts = runs(model, q)
    assert np.all(np.abs(model[starts[1:]] - model[starts[:-1]]) >= q)
    for a, b in zip(starts, [*starts[1:], n], strict=True):  # within one count of its start
        assert np.all(np.abs(model[a:b] - model[a]) < q)
    assert np.diff(starts)[-1] > 10 * np.diff(starts)[0]  # the runs grow as the cart slows
    g = np.add.reduceat(jac, starts, axis=0)
    b_inv = np.linalg.inv(jac.T @ jac)
    floor = b_inv @ (g.T @ g * q**2 / 12) @ b_inv
    assert np.linalg.eigvalsh(cov.robust - floor).min() >= -1e-12 * np.abs(floor).max()


def test_an_undetermined_direction_is_flagged():
    """Two parameters with the same effect: both flagged, their covariances inf."""
    n = 200
    t = np.linspace(0.0, 1.0, n)
    jac = np.column_stack([t, 2 * t, np.ones(n)])
    r = _least_squares_residual(jac, 1e-5 * np.random.default_rng(0).standard_normal(n))
    cov = covariances(jac, [r], [np.zeros(n)], [0.0])
    assert cov.singular.tolist() == [True, True, False]
    assert np.isinf(cov.robust[0, 0]) and np.isinf(cov.naive[1, 1])
    assert np.isfinite(cov.robust[2, 2])


def test_a_jacobian_whose_squares_overflow_is_judged_without_an_error():
    """A run that blew up at a trial value leaves a column of 1e200 [m per unit]: its squares
    overflow, and eigh of the inf raised LinAlgError out of a whole lab (the independent
    generator's dead-band cart). Each column's norm is taken over its largest entry."""
    from tuning.estimation.engine.covariance import determined

    jac = np.random.default_rng(0).standard_normal((500, 3))
    assert determined(jac)
    jac[:, 1] *= 1e200
    assert determined(jac) is False  # the others are zero beside it: not determined
