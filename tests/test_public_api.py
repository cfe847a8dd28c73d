"""The public API of fftune.analysis: re-exported names, their docstrings, and that the
convenience entry point plays the same signal as the drive."""
import inspect

import numpy as np
import pytest

import fftune.analysis as fa
from fftune.analysis import hosidf, random_odd_multisine, robust_bla
from fftune.analysis.errors import InputError
from fftune.analysis.multisine import drive_multisine


def test_all_names_exist_and_are_documented():
    assert {"robust_bla", "hosidf", "random_odd_multisine"} <= set(fa.__all__)
    for name in fa.__all__:
        obj = getattr(fa, name)
        assert inspect.getdoc(obj), f"fftune.analysis.{name} has no docstring"
        if inspect.isfunction(obj) and len(inspect.signature(obj).parameters) > 1:
            doc = inspect.getdoc(obj)
            assert "Parameters\n----------" in doc or "Returns\n-------" in doc, \
                f"fftune.analysis.{name}: docstring without numpy-style sections"
    from fftune.analysis.bla import robust_bla as bla_fn
    from fftune.analysis.hosidf import hosidf as hosidf_fn
    assert robust_bla is bla_fn and hosidf is hosidf_fn      # re-exports, not copies


def test_random_odd_multisine_is_what_the_drive_plays():
    u, design = random_odd_multisine(2560.0, 2048, 3, k_min=3, k_max=99, group=5, rms=0.4,
                                     seed=11)
    assert u.shape == (3, 2048)
    for m in range(3):
        np.testing.assert_allclose(u[m], drive_multisine(2048, 3, 99, 5, 11, m, 0.4),
                                   atol=1e-12)
    assert np.all(design.excited % 2 == 1) and design.removed.size > 0
    spectrum = np.abs(np.fft.rfft(u, axis=-1))
    assert np.all(spectrum[:, design.even] < 1e-9 * spectrum.max())
    assert np.all(spectrum[:, design.removed] < 1e-9 * spectrum.max())
    np.testing.assert_allclose(np.sqrt(np.mean(u ** 2, axis=-1)), 0.4, rtol=1e-12)


def test_random_odd_multisine_feeds_robust_bla():
    u, design = random_odd_multisine(1000.0, 512, 4, f_min=2, f_max=200, rms=1.0, seed=3)
    periods = np.repeat(u[:, None, :], 3, axis=1)          # (M, P, N)
    res = robust_bla(periods, 2.0 * periods, fs=1000.0)
    np.testing.assert_array_equal(res.bins, design.excited)
    np.testing.assert_allclose(res.G, 2.0, rtol=1e-9)


def test_random_odd_multisine_rejects_zero_realizations():
    with pytest.raises(InputError, match="n_realizations"):
        random_odd_multisine(1000.0, 512, 0)
