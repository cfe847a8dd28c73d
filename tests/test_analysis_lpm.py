"""lpm_moments against a slow reference: every line fitted on its own by np.linalg.lstsq
on the whole record's DFT (issue 31: the fast path fits the lines in blocks, one
realization at a time, into reused buffers; these must give the same moments)."""
import numpy as np

from fftune.analysis.lpm import lpm_moments, lpm_offsets


def _reference(u, y, band, settle, order, n_side):
    """Per realization and line: the degree-``order`` polynomial in offset / P fitted by
    lstsq to the 2 n_side neighbours, its value at 0 removed from the line; the noise
    (co)variances from the residuals times (1 + |w|^2) / q."""
    m_real, n_total, n = u.shape
    p = n_total - settle
    q = 2 * n_side - order - 1
    XU = np.fft.rfft(u[:, settle:].reshape(m_real, -1).astype(np.float64), axis=-1)
    XY = np.fft.rfft(y[:, settle:].reshape(m_real, -1).astype(np.float64), axis=-1)
    n_full = XU.shape[1]
    shape = (m_real, band.size)
    Uc, Yc = np.empty(shape, complex), np.empty(shape, complex)
    var_u, var_y, cov = np.empty(shape), np.empty(shape), np.empty(shape, complex)
    for i, k in enumerate(band):
        off = lpm_offsets(int(k * p), p, n_side, n_full)
        K = (off[:, None] / p) ** np.arange(order + 1)[None, :]
        w = np.linalg.pinv(K)[0]
        for m in range(m_real):
            res = {}
            for key, X, out in (("u", XU, Uc), ("y", XY, Yc)):
                x = X[m, k * p + off]
                coef = np.linalg.lstsq(K, x, rcond=None)[0]
                out[m, i] = X[m, k * p] - coef[0]
                res[key] = x - K @ coef
            f = (1.0 + w @ w) / q
            var_u[m, i] = np.sum(np.abs(res["u"]) ** 2) * f
            var_y[m, i] = np.sum(np.abs(res["y"]) ** 2) * f
            cov[m, i] = np.sum(res["y"] * np.conj(res["u"])) * f
    return Uc / p, Yc / p, var_u, var_y, cov, p


def test_lpm_moments_equal_a_per_line_lstsq_reference():
    """Two realizations, a settle period, a noisy (measured) float32 input and a
    Fortran-ordered output from rest; the band from line 1 to fs/2 - 1, so the edge lines
    (their own offset patterns) are fitted besides the interior block. (A float32 record
    failed before: its complex64 spectrum was viewed as float64 pairs.)"""
    rng = np.random.default_rng(31)
    m_real, settle, p, n = 2, 1, 4, 64
    t = np.arange((settle + p) * n)
    x = np.stack([np.cos(2 * np.pi * 3 * t / n + 0.4 * r) + 0.5 * np.sin(2 * np.pi * 11 * t / n)
                  for r in range(m_real)])
    u = (x + 0.05 * rng.standard_normal(x.shape)).astype(np.float32).reshape(m_real, -1, n)
    tr = 0.7 * np.exp(-t / 90.0) * np.cos(0.3 * t)
    y = 1.7 * np.roll(x, 2, axis=-1) + tr + 0.03 * rng.standard_normal(x.shape)
    y = np.asfortranarray(y.reshape(m_real, -1, n))
    band = np.arange(1, n // 2)
    excited = np.array([3, 11])
    order, n_side = 2, 5
    mom, G_per, info = lpm_moments(u, y, band=band, excited=excited, settle_periods=settle,
                                   order=order, n_side=n_side)
    U, Y, var_u, var_y, cov, p_kept = _reference(u, y, band, settle, order, n_side)
    kp = p_kept * (p_kept - 1) / p_kept ** 2
    assert mom.n_periods == p_kept == p
    np.testing.assert_allclose(mom.U, U, rtol=1e-10, atol=1e-10 * np.abs(U).max())
    np.testing.assert_allclose(mom.Y, Y, rtol=1e-10, atol=1e-10 * np.abs(Y).max())
    np.testing.assert_allclose(mom.ss_u, var_u * kp, rtol=1e-8, atol=1e-10 * var_u.max())
    np.testing.assert_allclose(mom.ss_y, var_y * kp, rtol=1e-8, atol=1e-10 * var_y.max())
    np.testing.assert_allclose(mom.s_yu, cov * kp, rtol=1e-8,
                               atol=1e-10 * np.sqrt(var_u.max() * var_y.max()))
    pos = np.searchsorted(band, excited)
    np.testing.assert_allclose(G_per[0], Y[:, pos] / U[:, pos], rtol=1e-10)
    assert info.dof == 2 * n_side - order - 1 and info.neighbours == 2 * n_side
