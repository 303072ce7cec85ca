"""The induced 2-norm and spectral radius of a trial-to-trial map, with what each number proves.

A map's norm is needed in three strengths, and each function here says which one it gives:

* a rigorous LOWER bound, :func:`power_norm` (``||T v||`` for a unit ``v`` from power iteration on ``T^T T``):
  at or above one it settles a verdict (not monotonic) without computing the norm;
* the value, :func:`operator_norm` (a dense SVD for small maps, ARPACK beyond, with a dense fallback when ARPACK
  does not converge) and :func:`matrix_certificate` (the largest eigenvalue of the Gram matrix of a dense map);
* a rigorous UPPER bound, :func:`matrix_norm_bound` and :func:`gram_norm_bound`: a Cholesky factorisation of
  ``rho^2 I - T^T T`` proves ``||T||_2 < rho`` (Rump's test, rounding accounted for), what
  :func:`bounded_matrix_certificate` grants a certificate on.

The limits every certificate shares live here too: :data:`CONTRACTION_LIMIT` (a monotone certificate's 2-norm is
at most it) and :data:`DENSE_LIMIT` (up to it, norms and spectra are computed densely).

Module order: after :mod:`foilc_hil.design.certificate_record` and :mod:`foilc_hil.design.lifted`, before
:mod:`foilc_hil.design.error_map`, :mod:`foilc_hil.design.qmap` and :mod:`foilc_hil.design.certificates`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from foilc_hil.design.certificate_record import PlantCertificate
from foilc_hil.design.lifted import vector_norm

__all__ = [
    "CHOLESKY_METHOD",
    "CONTRACTION_LIMIT",
    "DENSE_LIMIT",
    "UNIT_ROUNDOFF",
    "bounded_matrix_certificate",
    "gram_norm_bound",
    "matrix_certificate",
    "matrix_norm_bound",
    "operator_norm",
    "power_norm",
    "radius_of",
    "rounding_gamma",
]


#: Up to this many rows, norms and spectra are computed densely (exact, LAPACK).
DENSE_LIMIT = 600


#: Up to this many rows the input map's spectral radius is computed densely: these maps are far from normal, and
#: ARPACK's ``eigs`` needs thousands of restarts on them (minutes at 700 rows on a loaded machine), LAPACK a second.
RADIUS_DENSE_LIMIT = 1000


#: ARPACK restarts allowed for one norm; beyond that the dense fallback (or no certificate).
ARPACK_RESTARTS = 60


#: Largest map a non-converged ARPACK norm falls back to a dense SVD for.
DENSE_FALLBACK_LIMIT = 2500


#: Power iterations for the lower bound used when the spectral radius already rules a certificate out.
POWER_ITERATIONS = 40


#: Admissible certificate: the worst-case 2-norm must be at most this (strictly below one).
CONTRACTION_LIMIT = 1.0 - 1e-9


#: The Cholesky test of :func:`matrix_norm_bound` tries ``rho^2 = (1 + gap) lambda`` (``lambda``: an estimate of
#: ``lambda_max(T^T T)``, :func:`_norm_estimate`) for each gap in turn until it succeeds.
CHOLESKY_GAPS = (1e-8, 1e-6, 1e-4, 1e-2, 1e-1, 1.0, 10.0)


#: Bisection steps between the last gap that failed and the one that passed, when they are more than 1e-4 apart.
CHOLESKY_BISECTIONS = 14


#: Unit roundoff of float64.
UNIT_ROUNDOFF = 2.0**-53


def radius_of(matrix: np.ndarray) -> float:
    if matrix.size == 0:
        return 0.0
    values = np.linalg.eigvals(matrix)
    return float(np.max(np.abs(values))) if np.all(np.isfinite(values)) else math.inf


def rounding_gamma(k: int) -> float:
    """``gamma_k = k u / (1 - k u)``: the classical bound on the relative rounding error of ``k`` operations."""
    return k * UNIT_ROUNDOFF / (1.0 - k * UNIT_ROUNDOFF)


def power_norm(
    size: int,
    matvec: Callable[[np.ndarray], np.ndarray],
    rmatvec: Callable[[np.ndarray], np.ndarray],
    iterations: int = POWER_ITERATIONS,
    enough: float = math.inf,
) -> float:
    """A LOWER bound on the largest singular value: ``||T v||`` for ``v`` from power iteration on ``T^T T``;
    it stops early once the bound reaches ``enough`` (all a verdict may need to know)."""
    v = np.random.default_rng(0).standard_normal(size)
    v /= vector_norm(v)
    estimate = 0.0
    for _ in range(iterations):
        w = matvec(v)
        estimate = max(estimate, vector_norm(w))
        if not math.isfinite(estimate):
            return math.inf
        if estimate >= enough:
            break
        v = rmatvec(w)
        norm = vector_norm(v)
        if norm == 0.0:
            break
        v /= norm
    return estimate


def operator_norm(
    size: int,
    matvec: Callable[[np.ndarray], np.ndarray],
    rmatvec: Callable[[np.ndarray], np.ndarray],
    dense: Callable[[], np.ndarray],
    upper_bound: Callable[[], float] | None = None,
) -> tuple[float, str]:
    """Largest singular value: dense SVD for small sizes, ARPACK ``svds`` otherwise.

    ARPACK is capped (``ARPACK_RESTARTS``); when it does not converge -- clustered top singular values, e.g. a
    Toeplitz map whose symbol is flat near its maximum -- a dense SVD is used up to ``DENSE_FALLBACK_LIMIT``
    rows, and beyond that a rigorous ``upper_bound`` when it is below one, else ``inf`` with the method saying why,
    so a certificate is never granted on an unconverged estimate.
    """
    if size <= DENSE_LIMIT:
        matrix = dense()
        if not np.all(np.isfinite(matrix)):
            return math.inf, "dense"
        return float(np.linalg.norm(matrix, 2)), "dense"
    from scipy.sparse.linalg import ArpackNoConvergence, LinearOperator, svds

    operator = LinearOperator((size, size), matvec=matvec, rmatvec=rmatvec, dtype=float)
    try:
        values = svds(
            operator, k=1, which="LM", tol=1e-8, return_singular_vectors=False, random_state=0, maxiter=ARPACK_RESTARTS
        )
    except ArpackNoConvergence:
        lower = power_norm(size, matvec, rmatvec)
        if lower >= 1.0:  # enough for the verdict: no monotonic certificate
            return lower, "lower bound (power iteration; ARPACK did not converge)"
        if size <= DENSE_FALLBACK_LIMIT:
            matrix = dense()
            if not np.all(np.isfinite(matrix)):
                return math.inf, "dense (ARPACK did not converge)"
            return float(np.linalg.norm(matrix, 2)), "dense (ARPACK did not converge)"
        if upper_bound is not None:
            bound = upper_bound()
            if bound < 1.0:
                return bound, "upper bound (triangle inequality; ARPACK did not converge)"
        return math.inf, "not computed: ARPACK did not converge"
    return float(np.max(values)), "svds"


def _matrix_radius(matrix: np.ndarray) -> tuple[float, str]:
    """Spectral radius of a dense map: LAPACK up to :data:`RADIUS_DENSE_LIMIT` rows, beyond that not computed
    (``nan``: the caller bounds it by the 2-norm; ARPACK's ``eigs`` is unbounded in time on these far-from-normal
    maps)."""
    if matrix.shape[0] <= RADIUS_DENSE_LIMIT:
        return radius_of(matrix), "dense"
    return math.nan, "not computed"


def matrix_certificate(matrix: np.ndarray, kind: str) -> PlantCertificate:
    """Spectral radius and induced 2-norm of a trial-to-trial map given as a dense matrix.

    For laws whose map has no Toeplitz structure (norm-optimal ILC). Up to :data:`DENSE_LIMIT` rows: a dense SVD
    and eigenvalues (exact). Beyond: ``||T||_2 = sqrt(lambda_max(T^T T))`` from the largest eigenvalue of the Gram
    matrix (LAPACK ``eigh`` on that one eigenvalue: exact to rounding, and unlike ARPACK unaffected by the
    clustered top singular values these maps have); when it is below one it bounds the spectral radius
    (``rho <= ||T||``, so the verdict needs no eigenvalues) and the method says so, else LAPACK's eigenvalues up
    to :data:`RADIUS_DENSE_LIMIT` rows and beyond that "inconclusive at bound" the 2-norm.
    """
    from scipy.linalg import eigh

    T = np.asarray(matrix, dtype=float)
    if not np.all(np.isfinite(T)):
        return PlantCertificate("", kind, math.inf, math.inf, "overflow")
    size = T.shape[0]
    if size <= DENSE_LIMIT:
        return PlantCertificate("", kind, radius_of(T), float(np.linalg.norm(T, 2)), "dense", "dense")
    top = eigh(T.T @ T, eigvals_only=True, subset_by_index=[size - 1, size - 1])
    norm = math.sqrt(max(float(top[0]), 0.0))
    method = "dense (largest eigenvalue of T^T T)"
    if norm < 1.0:
        return PlantCertificate("", kind, norm, norm, method, "upper bound: the induced 2-norm")
    radius, radius_method = _matrix_radius(T)
    if math.isnan(radius):  # rho <= ||T||: an upper bound, not below one here
        radius, radius_method = norm, f"inconclusive at bound {norm:.6g} (the induced 2-norm)"
    return PlantCertificate("", kind, radius, norm, method, radius_method)


#: ``norm_2_method`` of a certificate from :func:`matrix_norm_bound`.
CHOLESKY_METHOD = "upper bound (Cholesky of rho^2 I - T^T T)"


def _norm_estimate(gram: np.ndarray, column: np.ndarray | None) -> tuple[float, np.ndarray | None]:
    """An estimate of ``||T||_2^2`` to try the Cholesky test at (neither bound nor certificate: the test decides),
    and a start vector for :func:`_power_lower` (``None``: a random one).

    Up to :data:`DENSE_LIMIT` columns (or without ``column``) the largest eigenvalue of the Gram matrix (LAPACK).
    Beyond, the squared sup of the symbol of ``T``'s middle ``column`` (its two-sided impulse response there, by
    FFT): the trial maps certified here are Toeplitz-like away from the trial's ends, and their top singular values
    cluster within about 1e-6 of that sup (Krylov methods stall on such clusters: ARPACK needed seconds and did not
    converge on NOILC's maps). The top singular vectors of such a map (left and right) are close to a sinusoid at
    the sup's frequency, the start vector:
    from it one power step reached within 3e-4 of the top eigenvalue on paper_sim's NOILC draws, where ten steps
    from a random vector stayed 2.5 % below.
    """
    from scipy.linalg import eigh

    size = gram.shape[0]
    if size <= DENSE_LIMIT or column is None:
        return float(eigh(gram, eigvals_only=True, subset_by_index=[size - 1, size - 1])[0]), None
    return _column_estimate(column)


def _column_estimate(column: np.ndarray) -> tuple[float, np.ndarray]:
    """The squared sup of the symbol of a Toeplitz-like map's middle ``column`` (its two-sided impulse response
    there, by FFT) and a sinusoid at the sup's frequency (:func:`_norm_estimate`)."""
    from scipy.fft import next_fast_len

    size = column.shape[0]
    middle = size // 2
    response = np.zeros(next_fast_len(4 * size))
    response[: size - middle] = column[middle:]  # lags 0, 1, ...
    response[response.shape[0] - middle :] = column[:middle]  # lags -middle .. -1, wrapped
    magnitude = np.abs(np.fft.fft(response))
    peak = int(np.argmax(magnitude))
    return float(magnitude[peak]) ** 2, np.cos(2.0 * math.pi * peak / response.shape[0] * np.arange(size))


def _power_lower(gram: np.ndarray, start: np.ndarray | None = None) -> float:
    """A lower bound on ``lambda_max`` of a Gram matrix: the best Rayleigh quotient of a few power steps (two from
    ``start``, ten from a random vector)."""
    steps = 10 if start is None else 2
    vector = np.asarray(np.random.default_rng(0).standard_normal((gram.shape[0],)) if start is None else start)
    best = 0.0
    for _ in range(steps):
        norm = float(np.linalg.norm(vector))
        if not norm > 0:
            break
        vector = vector / norm
        image = np.asarray(gram @ vector)
        best = max(best, float(np.dot(vector, image)))
        vector = image
    return best


def _cholesky_succeeds(gram: np.ndarray, rho2: float) -> bool:
    """Rump's test (Verification of positive definiteness, BIT 46, 2006): a floating-point Cholesky of
    ``fl(A - c I)`` with ``A = fl(rho2 I - gram)`` runs to completion only if ``A`` is positive definite, for
    ``c >= gamma_(n+1) / (1 - gamma_(n+1)) tr(A) + 4 n (2 (n + 1) + max A_ii) eta`` (``eta``: the smallest
    subnormal). We take ``c`` with ``4 gamma_(2n+2)`` and ``16 n (2 (n + 2) + ...)`` to spare."""
    from scipy.linalg import LinAlgError, cholesky

    size = gram.shape[0]
    shifted = -gram
    diagonal = np.arange(size)
    shifted[diagonal, diagonal] += rho2  # A = fl(rho2 I - gram), as the theorem's floating-point matrix
    trace = float(np.sum(shifted[diagonal, diagonal]))
    if not trace > 0:
        return False
    eta = math.ulp(0.0)
    shift = 4.0 * rounding_gamma(2 * size + 2) * trace + 16.0 * size * (2 * (size + 2) + rho2) * eta
    shifted[diagonal, diagonal] -= shift
    try:
        cholesky(shifted, lower=False, overwrite_a=True, check_finite=False)
    except LinAlgError:
        return False
    return True


def matrix_norm_bound(matrix: np.ndarray, error: float = 0.0) -> float | None:
    """A RIGOROUS upper bound on ``||T||_2`` for ``T = matrix + E``, ``||E||_2 <= error``; ``None`` when the test
    fails at every gap of :data:`CHOLESKY_GAPS`.

    ``||T||_2 < rho`` if and only if ``rho^2 I - T^T T`` is positive definite, which a Cholesky factorisation decides
    (``n^3 / 3`` flops, no eigenvalue or singular value decomposition). ``rho^2``, an estimate of ``lambda_max`` of the
    Gram matrix (:func:`_norm_estimate`), is widened by the gap; the rounding is accounted for:
    the computed Gram matrix is within ``gamma_n ||T||_F^2`` of ``T^T T`` (2-norm), forming ``A = rho^2 I - gram``
    rounds its diagonal by at most ``u (rho^2 + max gram_ii)``, and :func:`_cholesky_succeeds` proves ``A``
    positive definite. So ``||matrix||_2^2 < rho^2 + u (rho^2 + max gram_ii) + gamma_n ||matrix||_F^2``, and
    ``||T||_2`` is at most its square root plus ``error``. The bound is as tight as the estimate: at or below the
    exact ``lambda_max`` (the LAPACK value of small maps), the first gap that succeeds; above it (a symbol estimate
    of a large map, measured about 1.5e-7 relative above on paper_sim's NOILC draws), by that much. A poor estimate
    (a map far from Toeplitz) passes only at a wide gap, or far above a power-iteration lower bound: bisection
    (:data:`CHOLESKY_BISECTIONS` Cholesky tests) narrows it.
    """
    T = np.asarray(matrix, dtype=float)
    if not np.all(np.isfinite(T)):
        return None
    gram = T.T @ T  # numpy computes a product with its own transpose by a symmetric rank-k update (syrk)
    column = T[:, T.shape[1] // 2] if T.shape[0] == T.shape[1] else None
    frobenius2 = float(np.einsum("ij,ij->", T, T)) * (1.0 + rounding_gamma(T.shape[0] * T.shape[1]))
    bound = gram_norm_bound(gram, rounding_gamma(T.shape[0]) * frobenius2, column)
    return None if bound is None else bound + error


def gram_norm_bound(gram: np.ndarray, gram_error: float, column: np.ndarray | None = None) -> float | None:
    """A RIGOROUS upper bound on ``sqrt(lambda_max(S))`` for a symmetric ``S`` within ``gram_error`` (2-norm) of the
    computed ``gram`` (its upper triangle is read): :func:`matrix_norm_bound`'s Cholesky tests from the estimate of
    :func:`_norm_estimate` (``column``: the middle column of the square map ``T``, if any); ``None`` when every gap
    of :data:`CHOLESKY_GAPS` fails. ``S`` is ``T^T T`` or ``T T^T`` (the same largest eigenvalue, ``||T||_2^2``).
    """
    estimate, start = _norm_estimate(gram, column)
    estimate = max(estimate, 0.0)
    diagonal_max = float(np.max(np.diag(gram))) if gram.size else 0.0
    failed, passed = 0.0, math.nan
    for gap in CHOLESKY_GAPS:
        if _cholesky_succeeds(gram, estimate * (1.0 + gap) + gram_error):
            passed = estimate * (1.0 + gap) + gram_error
            break
        failed = estimate * (1.0 + gap) + gram_error
    if math.isnan(passed):
        return None
    # A poor estimate (a map far from Toeplitz) passed only at a wide gap, or far above a lower bound (a few power
    # steps: slow on the clustered spectra of Toeplitz-like maps, hence the 5 % before it counts): bisect. The
    # estimate's sinusoid starts the power steps; where it falls short (a map unlike a Toeplitz one), random ones.
    lower = _power_lower(gram, start)
    if start is not None and passed > lower * (1.0 + 0.05):
        lower = max(lower, _power_lower(gram))
    wide = passed > failed * (1.0 + 1e-4) if failed > 0.0 else passed > lower * (1.0 + 0.05)
    failed = max(failed, lower)
    for _ in range(CHOLESKY_BISECTIONS if wide else 0):
        middle = 0.5 * (failed + passed)
        if _cholesky_succeeds(gram, middle):
            passed = middle
        else:
            failed = middle
    bound2 = (passed + UNIT_ROUNDOFF * (passed + diagonal_max) + gram_error) * (1.0 + 4.0 * UNIT_ROUNDOFF)
    return math.nextafter(math.sqrt(bound2) * (1.0 + 2.0 * UNIT_ROUNDOFF), math.inf)


def bounded_matrix_certificate(matrix: np.ndarray, kind: str, error: float = 0.0) -> PlantCertificate:
    """:func:`matrix_certificate` by the Cholesky bound (:func:`matrix_norm_bound`) where that bound is a certificate.

    When the bound is at most :data:`CONTRACTION_LIMIT` it is the certificate: ``norm_2`` is the bound (rigorous,
    slightly above the exact norm: :func:`matrix_norm_bound`) and so is ``spectral_radius`` (``rho <= ||T||``).
    Otherwise the exact dense path of :func:`matrix_certificate` decides. ``error`` bounds (2-norm) how far
    ``matrix`` may be from the exact map (its rounding when it was formed, e.g.
    :func:`~foilc_hil.design.error_map.block_toeplitz_product`'s).
    """
    bound = matrix_norm_bound(matrix, error)
    if bound is not None and bound <= CONTRACTION_LIMIT:
        return PlantCertificate("", kind, bound, bound, CHOLESKY_METHOD, "upper bound: the induced 2-norm")
    return matrix_certificate(matrix, kind)
