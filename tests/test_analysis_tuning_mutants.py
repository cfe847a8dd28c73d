"""K_fc root search: the Illinois step on one-sided convex objectives (issue 16).

The other tests use objectives that are near-linear or odd-symmetric about the root, on
which plain regula falsi is already fast, so halving the wrong end (or not halving) went
unnoticed. On a convex objective one bracket end stays fixed for many steps: only the
Illinois halving of that end's value keeps the convergence superlinear.
"""
import numpy as np
import pytest

from fftune.analysis.tuning import SignedRootSearch

# s > 0 at K = 0 and s < 0 at K = 1 for both, as for an under-/over-compensated drive
CONVEX_OBJECTIVES = {
    # root 0.37, convex: regula falsi keeps the upper end (a = the moving end)
    "root-low-convex": (0.37, lambda k: np.exp(3 * (0.37 - k)) - 1),
    # root 0.63, concave: the lower end is kept (b = the moving end)
    "root-high-concave": (0.63, lambda k: 1 - np.exp(3 * (k - 0.63))),
}


@pytest.mark.parametrize("name", list(CONVEX_OBJECTIVES))
def test_illinois_search_needs_few_evaluations_on_one_sided_objective(name):
    root, objective = CONVEX_OBJECTIVES[name]
    calls = []

    def counted(k):
        calls.append(k)
        return objective(k)

    res = SignedRootSearch(0.0, 1.0, xtol=1e-6, max_evaluations=60).run(counted)
    assert res.converged
    assert res.k_fc == pytest.approx(root, abs=1e-5)
    assert res.n_evaluations == len(calls)
    # Illinois: 11 evaluations here; halving the wrong end takes 39, no halving 20
    assert res.n_evaluations <= 14, res.history
