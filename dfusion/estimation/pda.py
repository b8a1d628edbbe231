r"""Probabilistic data association (PDA) of one sensor frame, and its information form.

**Model** (Bar-Shalom & Li, *Multitarget-Multisensor Tracking: Principles and
Techniques*, 1995, sec. 3.4; Bar-Shalom, Daum & Huang, "The probabilistic data
association filter", IEEE Control Systems Magazine 29(6), 2009, eq. 26-41): a
frame holds the detections ``z_1 .. z_k`` taken at one time by one sensor. At
most one of them comes from the target, which is detected with probability
``P_D``; the others are false detections, Poisson in number and uniform with
spatial density ``lambda`` (false detections per unit measurement volume, e.g.
per square pixel). With the prediction ``(x^, P^)`` linearized at ``x^``::

    nu_i = z_i (-) h(x^),   S = H P^ H^T + R,   d_i^2 = nu_i^T S^-1 nu_i
    validated:  d_i^2 <= gamma = chi2_m^-1(P_G)                       (the gate)
    e_i   = exp(-d_i^2 / 2)
    b     = lambda |2 pi S|^(1/2) (1 - P_D P_G) / P_D
    beta_i = e_i / (b + sum_j e_j),  beta_0 = b / (b + sum_j e_j)      (validated i, j)
    nu    = sum_i beta_i nu_i,   K = P^ H^T S^-1
    x     = x^ + K nu
    P     = beta_0 P^ + (1 - beta_0) (P^ - K S K^T) + K (sum_i beta_i nu_i nu_i^T - nu nu^T) K^T

``beta_0`` is the probability that none of the validated detections is the
target. This is the moment-matched Gaussian of the mixture posterior
``beta_0 N(x^, P^) + sum_i beta_i N(x^ + K nu_i, P^ - K S K^T)`` (for a linear
model it is exact: the mixture's mean and covariance).

**Information form** (:func:`pda_information`). An information filter only
adds factors ``(Lambda, y)``; a PDA update is not a plain measurement, because
its covariance term depends on the spread of the innovations. It is expressed
as an *equivalent measurement* of ``h``: a pseudo-innovation ``nu_eq`` with
noise ``R_eq`` such that the ordinary update with them gives the PDA mean and
covariance. With ``S = L L^T`` (Cholesky), whitened ``H~ = L^-1 H``,
``A~ = H~ P^ H~^T``, ``nu~_i = L^-1 nu_i``::

    M~ = (1 - beta_0) I - (sum_i beta_i nu~_i nu~_i^T - nu~ nu~^T)     (PDA: P = P^ - P^ H~^T M~ H~ P^)
    M~ = U diag(mu) U^T,   keep direction u when mu_u > 0
    G  = U diag(sqrt(mu_kept)) U^T,   G+ = U diag(1 / sqrt(mu_kept)) U^T
    W~ = G (I - G A~ G)^-1 G                                            (whitened R_eq^-1)
    Lambda = H~^T W~ H~,   y = Lambda x^ + H~^T G (I - G A~ G)^-1 G+ nu~

Adding ``(Lambda, y)`` to the prior's information gives exactly the PDA mean
and covariance when every direction is kept (``M~`` positive definite).
``W~`` is positive semi-definite and ``R_eq >= R``: the frame never counts for
more than one detection with the sensor's noise. A direction ``u`` is dropped
(no information, no mean shift along it) when ``mu_u <= 0``: there the PDA
posterior is *wider* than the prior (a bimodal posterior: one validated
detection with a large ``beta_0``, or two far apart), which added information
cannot express. Along a dropped direction the frame is ignored (the estimate
is the one without this frame, as after a missed detection): the most
conservative choice information can express, though tighter than the PDA's
moment match of the bimodal posterior.

The equivalent pseudo-measurement of a direction with a small ``mu_u`` lies
far out (``u^T nu~ / mu_u``) with little weight: its information-vector term
``W~ nu~_eq`` stays bounded (about ``u^T nu~``), so the mean shift it causes is
the PDA's for the prior it was computed against, and shrinks in proportion as
the state's information grows later (smoothing, neighbours). Cutting such
directions was tried and loses the information of true detections when a
target re-enters a view with an uncertain prediction (``docs/clutter.md``).

**In a delayed-state information filter** the prediction ``(x^, P^)`` is the
node's fused marginal of the state at the frame's time (neighbours' information
included; for a late frame, the smoothed marginal: later data help the
association). The resulting single-state factor is added at the frame's time
like any measurement information and shared with the neighbours once; it is
not re-associated when later information arrives (as measurement factors are
not relinearized).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from dfusion.errors import ValidationError
from dfusion.linalg import Array, chi2_isf, cholesky, symmetrize

__all__ = ["ClutterModel", "PDAResult", "PDAInformation", "FrameInnovations", "frame_innovations", "pda_weights",
           "pda_update", "pda_moments", "pda_information", "gate_threshold", "MU_TOL"]


def _logsumexp(a: Array) -> float:
    """``log sum exp(a)`` without overflow or underflow (``a`` non-empty and finite)."""
    top = float(np.max(a))
    return top + math.log(float(np.sum(np.exp(a - top))))


def gate_threshold(gate: float, dof: int = 2) -> float:
    """Chi-square quantile of probability ``gate``: ``-2 ln(1 - gate)`` for 2 degrees of freedom.

    ``gate = 1`` gives ``inf`` (no gate). Other ``dof``: :func:`dfusion.linalg.chi2_isf` of
    ``1 - gate`` (no scipy on a node's path).
    """
    if not (isinstance(gate, (int, float)) and not isinstance(gate, bool) and 0.0 < gate <= 1.0):
        raise ValidationError(f"gate must be a probability in (0, 1], got {gate!r}")
    if gate == 1.0:
        return math.inf
    if dof == 2:
        return -2.0 * math.log1p(-gate)
    return chi2_isf(1.0 - gate, dof)


@dataclass(frozen=True)
class ClutterModel:
    """What PDA assumes about a sensor's detections.

    Attributes
    ----------
    density : float
        ``lambda``: false detections per unit measurement volume (a camera: the
        false-detection rate per frame divided by the image area, per square pixel).
    detection : float
        ``P_D``: probability that the target is detected when it is in view.
    gate : float
        ``P_G``: gate probability; the gate is ``d^2 <= chi2_m^-1(P_G)``.
    """

    density: float
    detection: float
    gate: float = 0.99

    def __post_init__(self) -> None:
        if not (math.isfinite(self.density) and self.density >= 0):
            raise ValidationError(f"clutter density must be >= 0, got {self.density!r}")
        if not (0.0 <= self.detection <= 1.0):
            raise ValidationError(f"detection probability must be in [0, 1], got {self.detection!r}")
        gate_threshold(self.gate)

    def threshold(self, dof: int) -> float:
        """The gate ``gamma`` for ``dof``-dimensional measurements."""
        return gate_threshold(self.gate, dof)


@dataclass(frozen=True)
class FrameInnovations:
    """The detections of one frame against a prediction ``(x^, P^)``, linearized at ``x^`` (the first
    line of the module docstring's equations): what the PDA and the multi-target hypothesiser
    (:class:`dfusion.tracking.gating.GaussianHypothesiser`) both gate and weigh.

    Attributes
    ----------
    H : the measurement Jacobian at ``x^``.
    S : ``H P^ H^T + R``.
    L : the lower Cholesky factor of ``S``.
    innovations : (k, m) ``nu_i = z_i (-) h(x^)``.
    d2 : (k,) ``nu_i^T S^-1 nu_i``.
    """

    H: Array
    S: Array
    L: Array
    innovations: Array
    d2: Array

    @property
    def log_norm(self) -> float:
        """``log N(0; 0, S) = -log|2 pi S| / 2 = -(m / 2) log(2 pi) - sum_i log L_ii``: with ``-d2 / 2``
        the log-likelihood of each detection."""
        m = self.S.shape[0]
        return -0.5 * m * math.log(2.0 * math.pi) - float(np.sum(np.log(np.diag(self.L))))


def frame_innovations(mean: Array, cov: Array, detections: Array, sensor: Any) -> FrameInnovations:
    """:class:`FrameInnovations` of ``detections`` ((k, m), k may be 0) against ``(mean, cov)``;
    ``sensor`` has ``h``, ``H``, ``R``, ``residual`` and ``dim_z``."""
    x = np.asarray(mean, dtype=float)
    m = int(sensor.dim_z)
    Z = np.asarray(detections, dtype=float).reshape(-1, m)
    H = np.asarray(sensor.H(x), dtype=float)
    S = symmetrize(H @ np.asarray(cov, dtype=float) @ H.T + np.asarray(sensor.R, dtype=float))
    L = cholesky(S, "innovation covariance S")
    if len(Z):
        hx = np.asarray(sensor.h(x), dtype=float)
        nus = np.array([sensor.residual(z, hx) for z in Z]).reshape(-1, m)
        white = np.linalg.solve(L, nus.T).T
        d2 = np.einsum("ij,ij->i", white, white)
    else:
        nus, d2 = np.zeros((0, m)), np.zeros(0)
    return FrameInnovations(H, S, L, nus, d2)


@dataclass(frozen=True)
class PDAResult:
    """One PDA update (see the module docstring).

    Attributes
    ----------
    mean, cov : the PDA posterior moments.
    prior_mean, prior_cov : the prediction ``(x^, P^)`` (``x^`` is the linearization point).
    H, S : measurement Jacobian at ``x^`` and innovation covariance.
    d2 : (k,) squared Mahalanobis distance of every detection of the frame.
    validated : (k,) bool, inside the gate.
    innovations : (v, m) innovations of the validated detections.
    beta0 : probability that no validated detection is the target.
    beta : (v,) association probabilities of the validated detections.
    detection : the ``P_D`` used.
    """

    mean: Array
    cov: Array
    prior_mean: Array
    prior_cov: Array
    H: Array
    S: Array
    d2: Array
    validated: Array
    innovations: Array
    beta0: float
    beta: Array
    detection: float
    gamma: float

    @property
    def combined_innovation(self) -> Array:
        """``nu = sum_i beta_i nu_i``."""
        return self.beta @ self.innovations if self.beta.size else np.zeros(self.S.shape[0])


def pda_weights(d2: Array, S: Array, density: float, detection: float, gate: float) -> tuple[float, Array]:
    """``(beta_0, beta)`` for validated detections with squared distances ``d2`` (module docstring).

    Computed in the log domain (``log b = log lambda + log|2 pi S| / 2 + log(1 - P_D P_G) - log P_D``),
    so that far detections do not underflow. ``P_D = 0`` gives ``beta_0 = 1``; ``lambda = 0``
    (no clutter) or ``P_D P_G = 1`` gives ``beta_0 = 0`` when a detection is validated.
    """
    d2 = np.asarray(d2, dtype=float)
    if d2.size == 0 or detection <= 0.0:
        return 1.0, np.zeros(d2.size)
    log_e = -0.5 * d2
    miss = 1.0 - detection * gate
    if density <= 0.0 or miss <= 0.0:
        return 0.0, np.exp(log_e - _logsumexp(log_e))
    sign, logdet = np.linalg.slogdet(2.0 * math.pi * np.asarray(S, dtype=float))
    if sign <= 0:
        raise ValidationError("innovation covariance S is not positive definite")
    log_b = math.log(density) + 0.5 * logdet + math.log(miss) - math.log(detection)
    norm = _logsumexp(np.append(log_e, log_b))
    return float(math.exp(log_b - norm)), np.exp(log_e - norm)


def pda_update(
    mean: Array,
    cov: Array,
    detections: Array,
    sensor: Any,
    model: ClutterModel,
    *,
    detection: float | None = None,
) -> PDAResult:
    """PDA update of the prediction ``(mean, cov)`` with the detections of one frame.

    ``sensor`` has ``h``, ``H``, ``R``, ``residual`` and ``dim_z``; it is linearized at
    ``mean``. ``detection`` overrides ``model.detection`` (e.g. ``P_D`` times the
    probability that the target projects into the image). Equations: module docstring.
    """
    x = np.asarray(mean, dtype=float)
    P = symmetrize(np.asarray(cov, dtype=float))
    fi = frame_innovations(x, P, detections, sensor)
    H, S, nus, d2 = fi.H, fi.S, fi.innovations, fi.d2
    gamma = model.threshold(int(sensor.dim_z))
    valid = d2 <= gamma
    pd = model.detection if detection is None else float(detection)
    beta0, beta = pda_weights(d2[valid], S, model.density, pd, model.gate)
    nv = nus[valid]
    if beta.size == 0 or beta0 >= 1.0:
        return PDAResult(x.copy(), P.copy(), x, P, H, S, d2, valid, nv, 1.0, beta, pd, gamma)
    mean, post = pda_moments(x, P, H, S, nv, float(beta0), beta)
    return PDAResult(mean, post, x, P, H, S, d2, valid, nv, float(beta0), beta, pd, gamma)


def pda_moments(x: Array, P: Array, H: Array, S: Array, innovations: Array, beta0: float,
                beta: Array) -> tuple[Array, Array]:
    """Mean and covariance of the mixture ``beta_0 N(x, P) + sum_i beta_i N(x + K nu_i, P - K S K^T)``.

    The last lines of the module docstring's equations: ``nu = sum_i beta_i nu_i``,
    ``K = P H^T S^-1``. Any weights summing to one may be given: the single-target PDA's
    (:func:`pda_weights`) or a joint association's marginals (JPDA, Bar-Shalom, Daum &
    Huang 2009, eq. 45-47, which have the same form with ``beta_i`` the marginal
    probability that detection ``i`` is this target's).
    """
    nv = np.asarray(innovations, dtype=float).reshape(len(beta), S.shape[0])
    nu = beta @ nv
    K = np.linalg.solve(S, (P @ H.T).T).T     # P H^T S^-1 (S symmetric)
    spread = (nv * beta[:, None]).T @ nv - np.outer(nu, nu)
    post = beta0 * P + (1.0 - beta0) * (P - K @ S @ K.T) + K @ spread @ K.T
    return x + K @ nu, symmetrize(post)


@dataclass(frozen=True)
class PDAInformation:
    """The equivalent measurement information of a PDA update (:func:`pda_information`).

    Attributes
    ----------
    info, vec : ``(Lambda, y)`` to add to the state's information.
    kept : number of measurement-space directions that carry information.
    dropped : directions dropped because the PDA posterior is wider than the prior there.
    exact : every direction kept: prior + ``(Lambda, y)`` reproduces the PDA mean and covariance.
    """

    info: Array
    vec: Array
    kept: int
    dropped: int

    @property
    def exact(self) -> bool:
        return self.dropped == 0


#: Eigenvalues of the whitened PDA gain matrix ``M~`` at or below this carry no information.
MU_TOL = 1e-12


def pda_information(res: PDAResult) -> PDAInformation:
    """The conservative equivalent measurement information ``(Lambda, y)`` of a PDA update.

    See the module docstring (information form): ``prior + (Lambda, y)`` gives the PDA
    mean and covariance in every kept direction and the prior elsewhere.
    """
    n = res.prior_mean.shape[0]
    m = res.S.shape[0]
    if res.beta.size == 0 or res.beta0 >= 1.0:
        return PDAInformation(np.zeros((n, n)), np.zeros(n), 0, 0)
    C = cholesky(res.S, "innovation covariance S")
    Ht = np.linalg.solve(C, res.H)                                    # L^-1 H (C lower triangular, m x m)
    A = symmetrize(Ht @ res.prior_cov @ Ht.T)                         # A~ = I - L^-1 R L^-T
    wn = np.linalg.solve(C, res.innovations.T).T                       # whitened innovations
    nu = res.beta @ wn
    Mt = (1.0 - res.beta0) * np.eye(m) - ((wn * res.beta[:, None]).T @ wn - np.outer(nu, nu))
    mu, U = np.linalg.eigh(symmetrize(Mt))
    keep = mu > MU_TOL
    if not keep.any():
        return PDAInformation(np.zeros((n, n)), np.zeros(n), 0, m)
    Uk = U[:, keep]
    r = np.sqrt(mu[keep])
    G = (Uk * r) @ Uk.T
    Gp = (Uk / r) @ Uk.T
    B = np.eye(m) - G @ A @ G                                        # positive definite: G A~ G < I
    W = symmetrize(G @ np.linalg.solve(B, G))
    Lam = symmetrize(Ht.T @ W @ Ht)
    y = Lam @ res.prior_mean + Ht.T @ (G @ np.linalg.solve(B, Gp @ nu))
    return PDAInformation(Lam, y, int(keep.sum()), int(m - keep.sum()))
