"""The batch fitter's compressed forward-mode Jacobian (engine.batch: values of different
recordings' own share a tangent) against the plain one, a tangent per slot."""

from __future__ import annotations

import numpy as np
import pytest

from jaxcart.files import read_experiment
from tests.test_diagnose import BY_NAME, make_case


@pytest.fixture(scope="module")
def search(tmp_path_factory):
    from tuning.estimation.diagnose.search import Search

    case = BY_NAME["tap + P and PD steps with the drive limit per run"]
    recs = [read_experiment(p) for p in make_case(case, tmp_path_factory.mktemp("batch"))]
    return Search(recs, [None] * 3, [False] * 3, None, lambda line: None, None)


def test_compressed_jacobian_is_the_plain_one(search):
    """A structure with each run's own drive limit and the tap's start state (6 slots in 3
    colours) and one of shared values alone: the Jacobian of one LM step, compressed and
    plain, agrees to 1e-12 of its largest entry; the fits then agree to 1e-9."""
    from tuning.estimation.diagnose import structures
    from tuning.estimation.engine import parameters
    from tuning.estimation.engine.batch import BatchFitter

    per_run = next(c for c in search.round1 if structures.PER_RUN in c.parts)
    single = next(c for c in search.round1 if c.name == "coulomb")
    problems = [
        (
            tuple(c.free) + tuple(search.nuis),
            {k: search.starts_all[parameters.base_name(k)] for k in c.free},
            {},
        )
        for c in (per_run, single)
    ]
    assert any("@" in n for n in problems[0][0] if not n.startswith("y"))
    compressed, plain = (
        BatchFitter(
            search.segments,
            search.base_plants,
            per_recording=search.layout.per_recording,
            compress=compress,
        )
        for compress in (True, False)
    )
    out = {}
    for name, fitter in (("compressed", compressed), ("plain", plain)):
        out[name] = fitter.fit(problems, (1.0,), (1,), kmax=12)
    assert compressed._n_colours < len(problems[0][0])
    for a, b in zip(out["compressed"], out["plain"], strict=True):
        assert np.max(np.abs(a[2] - b[2])) <= 1e-12 * np.max(np.abs(b[2]))
        assert a[2].shape == b[2].shape and np.count_nonzero(b[2]) > 0
        for k in b[0]:
            assert a[0][k] == pytest.approx(b[0][k], rel=1e-9)


def test_recordings_simulated_side_by_side_are_each_simulated_alone(search):
    """The two closed-loop steps (P and PD, the PD step cut to 1.5 s) run as lanes of one
    loop, its signal held to the P step's end; every recording's residual at the start values
    (a fit of 0 iterations) equals its own smooth run, unpadded, to 1e-12 m."""
    import dataclasses

    from jaxcart.smooth_sim import simulate_smooth
    from jaxcart.smoothing import Smoothing
    from tuning.estimation.engine.batch import VOLTAGE_WIDTH, BatchFitter

    tap, p_step, pd_step = search.segments
    n = 1501
    pd_step = dataclasses.replace(
        pd_step,
        target=pd_step.target[:n],
        time=pd_step.time[:n],
        experiment=dataclasses.replace(pd_step.experiment, signal=pd_step.experiment.signal[:n]),
    )
    segs = [tap, p_step, pd_step]
    fitter = BatchFitter(segs, search.base_plants)
    assert sorted(len(g) for g in fitter.shape.groups) == [1, 2]
    names = ("B_eq", "f_c", "y0@0", "yd0@0")
    start = {"B_eq": 4.0, "f_c": 0.3}
    (_, _, _, r), *_ = fitter.fit([(names, start, {})], (1.0,), (0,), kmax=5)
    scale = 1.0 / np.sqrt(sum(s.target.size for s in segs))
    smoothing = dataclasses.replace(Smoothing().scaled(1.0), voltage=VOLTAGE_WIDTH / 4.0)
    full = fitter.base_vector(start)
    offset = 0
    for i, (seg, sup) in enumerate(zip(segs, fitter.supers, strict=True)):
        plant = sup.replace(**{k: v for k, v in start.items() if k in sup.param_names()})
        exp = dataclasses.replace(
            seg.experiment, **{v: full[j] for v, j in fitter.layout.starts[i]}
        )
        assert not seg.counts_in_loop
        alone = simulate_smooth(plant, seg.controller, exp, smoothing=smoothing, substeps=1)
        mine = np.asarray(r[offset : offset + seg.target.size]) / scale
        expected = np.asarray(alone.position) - seg.target
        np.testing.assert_allclose(mine, expected, rtol=0, atol=1e-12)
        offset += seg.target.size
    assert offset == r.size


def test_a_search_compiles_its_step_once(search):
    """The step's tangents: from the first fit on, the most any problem of the search can need
    (K_MAX shared values and a recording's own two slots), so no later round compiles the
    step again; without ``max_shared``, what the fits so far needed, never fewer."""
    from tuning.estimation.diagnose.policy import K_MAX
    from tuning.estimation.engine.batch import BatchFitter

    fitter = BatchFitter(
        search.segments, search.base_plants, per_recording=search.layout.per_recording,
        max_shared=K_MAX,
    )  # fmt: skip
    lay = fitter.layout

    def colours(names, kmax=12):
        idx = np.full((1, kmax), lay.dummy, dtype=np.int32)
        free = np.zeros((1, kmax))
        for s, n in enumerate(names):
            idx[0, s], free[0, s] = lay.index(n), 1.0
        return fitter._colouring(idx, free)[0].shape[1]

    assert colours(["B_eq", "f_c"]) == K_MAX + 2
    assert colours(["B_eq", "f_c", "f_s", "v_sat", "delay"]) == K_MAX + 2
    fitter = BatchFitter(
        search.segments, search.base_plants, per_recording=search.layout.per_recording
    )
    assert colours(["B_eq", "f_c"]) == 2
    assert colours(["B_eq"]) == 2  # never fewer
    assert colours(["B_eq", "f_c", "v_sat"]) == 3
