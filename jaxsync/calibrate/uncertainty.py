"""How far a calibration's answer can be from the truth, from the recording alone.

``noise_floor``: each joint's white position noise, from the samples
themselves. ``clustered_intervals``: half-widths that hold where the fit's
residual is not white noise (a model error that each window's samples share),
and the Gauss-Newton step the fit left open.
"""

from __future__ import annotations

import numpy as np


def clustered_intervals(residuals, jac: np.ndarray, alpha: float = 0.05) -> tuple[np.ndarray, ...]:
    """95 % half-widths and standard errors that hold where the residual is not white noise: the sandwich
    H^-1 (sum_w g_w g_w^T) H^-1 over the windows w (``residuals``: one array per window, in the rows of
    ``jac``; g_w = J_w^T r_w), so that a model error shared by a window's samples counts once per window,
    not as independent noise per sample. Each parameter's Student quantile takes as degrees of freedom
    its effective number of windows less one ((sum a_w)^2 / sum a_w^2, a_w its share of the variance):
    a joint moved in five windows of forty is known from five. Also returns the Gauss-Newton step still
    open at the fit's end (-H^-1 J^T r): a parameter the fit has not settled moves by it."""
    import scipy.special  # noqa: PLC0415 -- with the toolbox, only calibration needs it

    sizes = [np.size(r) for r in residuals]
    if sum(sizes) != jac.shape[0] or len(sizes) < 3:
        nan = np.full(jac.shape[1], np.nan)
        return nan, nan, nan
    hinv = np.linalg.pinv(jac.T @ jac)
    edges = np.cumsum([0, *sizes])
    # each window's pull on the parameters, through H^-1: (W, P)
    pull = np.stack(
        [hinv @ (jac[a:b].T @ np.ravel(r)) for a, b, r in zip(edges[:-1], edges[1:], residuals, strict=True)]
    )
    g = len(sizes)
    share = pull**2
    var = g / (g - 1) * share.sum(axis=0)
    dof = share.sum(axis=0) ** 2 / np.maximum((share**2).sum(axis=0), 1e-300)
    se = np.sqrt(var)
    return scipy.special.stdtrit(np.maximum(dof - 1.0, 1.0), 1 - alpha / 2) * se, se, np.abs(pull.sum(axis=0))


def noise_floor(q: np.ndarray) -> np.ndarray:
    """(J,) each joint's white position noise, rad, from its samples' third differences (whose variance is
    20 sigma^2; a smooth motion's share is (h^3 dddq)^2, far below at a few hundred Hz), median-based so
    that the steps of the motion do not count."""
    d3 = np.diff(np.asarray(q, float), 3, axis=0)
    mad = np.median(np.abs(d3 - np.median(d3, axis=0)), axis=0)
    return 1.4826 * mad / np.sqrt(20.0)
