"""Non-negative least squares from the normal equations, shared by the PSF solves.

argmin ||A h - v||^2 subject to h >= 0, given Q = A^T A (positive definite)
and c = A^T v, by block principal pivoting (Judice & Pires, Comput. Oper.
Res. 21, 1994; one of the two methods compared by Portugal, Judice & Vicente,
Math. Comp. 63, 1994, the NNLS reference of Delbracio et al., IJCV 2012,
sec. 4), with scipy's Lawson & Hanson active set method (Solving Least Squares
Problems, 1974, ch. 23) as a safeguard. It solves the Bernoulli estimate's
system (IJCV 2012, problem (P)) and the sharp-edge estimate's regularised one
(Joshi et al., CVPR 2008, eq. (5)) alike: both are strictly convex quadratics
over the non-negative orthant, whose minimiser is unique.

numpy and OpenCV: scipy.optimize.nnls (Lawson-Hanson on A itself) needs
scipy.linalg and scipy.optimize, 0.3-0.5 s of a process's start-up, and can
neither start from a guess nor take the normal equations; it is loaded only
for the safeguard, which no photograph has reached.
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["nnls_normal"]


def nnls_normal(q: np.ndarray, c: np.ndarray, passive: np.ndarray | None = None) -> np.ndarray:
    """argmin ||A h - v||^2 s.t. h >= 0 from the normal equations Q = A^T A, c = A^T v.

    Block principal pivoting (Judice & Pires, Comput. Oper. Res. 21, 1994; one of
    the two methods compared by Portugal, Judice & Vicente, Math. Comp. 63, 1994,
    the NNLS reference of IJCV 2012 sec. 4): the optimality conditions
    h_F = Q_FF^-1 c_F >= 0 on the free set F and y = Q h - c >= 0 elsewhere are
    met by moving every variable that violates them to the other set at once;
    when three such exchanges in a row do not reduce their number, one variable
    moves at a time (Murty's rule), which ends in finitely many steps.
    scipy.optimize.nnls (Lawson-Hanson) cannot start from a guess and frees one
    variable per step from the empty set; started from the positive samples of
    the LS kernel (``passive``), as here, the exchanges end after 3-6 Cholesky
    solves of the free block on the example photo's windows (6-10 on the ~800
    observations of a 24 MP frame's 10 x 10 grid, where the noisy tails change
    sign more): 7-27x faster on 17 x 17 to 33 x 33 kernels, the same minimiser
    (1e-15, tests/test_bernoulli.py). The sharp-edge solve starts from nothing:
    1-12 solves on the real wall photo's windows, the minimiser of the former
    scipy path to 2e-12 (tests/test_scipy_reference.py). Each exchange gathers
    the free rows of Q once (`_kkt`).

    Parameters
    ----------
    q : ndarray (n, n)
        Q, symmetric positive definite.
    c : ndarray (n,)
    passive : ndarray of bool (n,), optional
        The variables to start free (positive); none by default.

    Returns
    -------
    ndarray (n,)
        The minimiser, >= 0.

    Raises
    ------
    numpy.linalg.LinAlgError
        A free block of Q is not positive definite.
    """
    n = q.shape[0]
    free = np.zeros(n, dtype=bool) if passive is None else np.asarray(passive, dtype=bool).copy()
    tol = 1e-10 * max(float(np.abs(c).max()), 1e-300)
    h, y = _kkt(q, c, free)
    best, trials = n + 1, 3
    for _ in range(10 * n):
        # h is 0 on the bound set and y on the free set: each test only flags variables of its own set
        wrong = (h < 0) | (y < -tol)
        count = int(np.count_nonzero(wrong))
        if count == 0:
            return np.maximum(h, 0.0)
        if count < best:
            best, trials = count, 3
            free ^= wrong
        elif trials > 0:
            trials -= 1
            free ^= wrong
        else:
            last = int(np.flatnonzero(wrong)[-1])
            free[last] = ~free[last]
        h, y = _kkt(q, c, free)
    # not reached in exact arithmetic (Murty's rule terminates); the slow solver as a safeguard
    from scipy import linalg, optimize  # 0.3-0.5 s of imports: only here

    lower = linalg.cholesky(q, lower=True, check_finite=False)
    return optimize.nnls(lower.T, linalg.solve_triangular(lower, c, lower=True), maxiter=50 * n)[0]


def _kkt(q: np.ndarray, c: np.ndarray, free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """h with h_F = Q_FF^-1 c_F on the free set F and 0 elsewhere, and the multipliers y = Q h - c (0 on F).

    The rows Q_F. are gathered once: their columns F are the block to solve, and
    with Q symmetric Q h = Q_F.^T h_F, |F| / n of the product with all of Q.
    """
    h = np.zeros(q.shape[0])
    idx = np.flatnonzero(free)
    if idx.size == 0:
        return h, -c
    rows = q.take(idx, axis=0)
    h_free = _cholesky_solve(rows.take(idx, axis=1), c.take(idx))
    h[idx] = h_free
    y = h_free @ rows
    y -= c
    y[idx] = 0.0
    return h, y


def _cholesky_solve(q: np.ndarray, c: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
    """Q_FF^-1 c_F for the rows and columns ``idx`` (all by default) of a symmetric positive definite Q.

    OpenCV's Cholesky solve: as fast as LAPACK's potrf and potrs on these
    sizes (10-300 unknowns, one thread), one call, and no scipy.linalg to
    import (0.2 s of start-up); the block is gathered by two takes (a third
    of the time of np.ix_).

    Raises
    ------
    numpy.linalg.LinAlgError
        The block is not positive definite.
    """
    block = q if idx is None else q.take(idx, axis=0).take(idx, axis=1)
    rhs = c if idx is None else c[idx]
    if block.shape[0] <= 3:  # OpenCV solves up to 3 x 3 by Cramer's rule, without the Cholesky test
        np.linalg.cholesky(block)
    ok, x = cv2.solve(block, rhs.reshape(-1, 1), flags=cv2.DECOMP_CHOLESKY)
    if not ok or not np.isfinite(x).all():
        raise np.linalg.LinAlgError("the free block of the normal equations is not positive definite")
    return x[:, 0]
