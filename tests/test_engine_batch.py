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
    from tuning.estimation.diagnose import core as C
    from tuning.estimation.engine.batch import BatchFitter

    per_run = next(c for c in search.round1 if C.PER_RUN in c.parts)
    single = next(c for c in search.round1 if c.name == "coulomb")
    problems = [
        (
            tuple(c.free) + tuple(search.nuis),
            {k: search.starts_all[search.layout.kind(k)] for k in c.free},
            {},
        )
        for c in (per_run, single)
    ]
    assert any("@" in n for n in problems[0][0] if not n.startswith("y"))
    plain = BatchFitter(
        search.segments,
        search.base_plants,
        per_recording=search.layout.per_recording,
        compress=False,
    )
    out = {}
    for name, fitter in (("compressed", search.fitter), ("plain", plain)):
        out[name] = fitter.fit(problems, (1.0,), (1,), kmax=12)
    assert search.fitter._n_colours < len(problems[0][0])
    for a, b in zip(out["compressed"], out["plain"], strict=True):
        assert np.max(np.abs(a[2] - b[2])) <= 1e-12 * np.max(np.abs(b[2]))
        assert a[2].shape == b[2].shape and np.count_nonzero(b[2]) > 0
        for k in b[0]:
            assert a[0][k] == pytest.approx(b[0][k], rel=1e-9)
