r"""Front end of a calibrated camera detecting the target in its image, under clutter.

A camera node fuses pixel detections ``z = (u, v)`` of the target's ground point
(:class:`~dfusion.models.PinholeCamera`: ``h``, ``H``, ``R = pixel_std^2 I``). The
simulated world produces a true detection only when the target is in the camera's view
(``in_view``), with probability ``detection``, plus ``false_detection_rate`` false
detections per frame on average, uniformly in the image (:mod:`dfusion.sim.world`).

**Gate.** The detections of one frame (one time stamp) are compared with the node's
*fused* prediction at their time (Bar-Shalom, Li & Kirubarajan, *Estimation with
Applications to Tracking and Navigation*, 2001, sec. 2.4.3 and 5.4)::

    (mu, P) = node.estimate(t)                   t in the window (a state, or between two)
              newest state predicted to t        t newer than the newest state
    nu = z - h(mu),   S = H(mu) P H(mu)^T + R,   d^2 = nu^T S^-1 nu
    validated  iff  d^2 <= chi2_2^-1(gate) = -2 ln(1 - gate)

(the chi-square quantile with 2 degrees of freedom in closed form; ``gate = 0.99`` gives
9.21). Detections outside the gate are counted (``stats.gated``) and not fused; a
prediction behind the camera cannot be projected and rejects the frame
(``stats.unprojectable``). ``gate = 1`` turns the gate off.

**Clutter model** (``clutter_model``). ``"pda"`` (the default): the validated detections
of a frame are associated together by probabilistic data association
(:mod:`dfusion.estimation.pda`) with the clutter density ``false_detection_rate / (width
height)`` per square pixel and ``P_D`` = ``detection`` times the probability that the
prediction projects into the image; the frame enters the node as its conservative
equivalent measurement information. A frame with one validated detection and no
clutter (``beta_0 = 0``) is a plain EIF update. A CUSUM track-loss test withdraws the
camera's own unconfirmed frames when later frames contradict them, and the first frames
of a re-acquisition are held back from the neighbours until a second frame confirms them
(:class:`CameraFrontEnd`; ``docs/clutter.md``). ``"gate"``: each validated detection is
fused on its own as a measurement (no clutter model).

**Reliability.** After each fused frame the front end reports a source ``"camera"`` to
the node (:meth:`FusionNode.report_source`): the node's newest estimate with the camera
reliability of the switching paper (eq. 1-9, :func:`dfusion.reliability.camera_reliability_at`)
at its position, for switching policies; :meth:`CameraFrontEnd.reliability` gives it for
the current estimate at any time.

The scenario kind ``camera`` (:mod:`dfusion.scenario.camera_kind`) builds this front
end from a node table; ``robot_camera`` builds :class:`MountedCameraFrontEnd`, the same for
a camera on a robot that moves (:class:`~dfusion.models.camera.MountedCamera`: the camera
at the detection's time).
"""
from __future__ import annotations

import logging
import math
from typing import Any
from dataclasses import dataclass

import numpy as np

from dfusion.errors import ValidationError
from dfusion.estimation.estimate import Estimate
from dfusion.estimation.pda import ClutterModel, PDAResult, gate_threshold, pda_information, pda_update
from dfusion.frontends.base import FrontEnd, FrontEndStats
from dfusion.fusion.node import FusionNode
from dfusion.linalg import Array
from dfusion.models.camera import MountedCamera, PinholeCamera
from dfusion.reliability import camera_reliability_at

log = logging.getLogger(__name__)

__all__ = ["CameraFrontEnd", "MountedCameraFrontEnd", "CameraStats", "CameraFrame", "gate_threshold", "miss_probability",
           "loss_log_likelihood_ratio", "CLUTTER_MODELS"]

#: ``"pda"``: probabilistic data association of each frame; ``"gate"``: the hard gate alone,
#: each detection fused on its own when inside it (no clutter model).
CLUTTER_MODELS = ("pda", "gate")


@dataclass
class CameraStats(FrontEndStats):
    """Counters of a camera front end: ``processed`` detections, ``contributed`` ones (the
    validated detections of fused frames) and ``rejected`` ones, of which ``gated`` failed the
    gate and ``unprojectable`` had a prediction behind the camera; per frame (the detections of
    one time stamp): ``frames``, ``frames_fused``, ``pda_partial`` (a measurement direction
    dropped, :func:`~dfusion.estimation.pda.pda_information`), the association-weighted NIS
    (``nis_sum`` over ``nis_count`` fused frames), ``losses`` (track losses declared) and
    ``withdrawn`` (own frames withdrawn after a loss)."""

    gated: int = 0
    unprojectable: int = 0
    frames: int = 0
    frames_fused: int = 0
    pda_partial: int = 0
    nis_sum: float = 0.0
    nis_count: int = 0
    losses: int = 0
    withdrawn: int = 0

    @property
    def detections(self) -> int:
        """Detections processed."""
        return self.processed

    @property
    def fused(self) -> int:
        """Detections fused (PDA: the validated detections of fused frames)."""
        return self.contributed

    @property
    def nis_mean(self) -> float:
        """Mean normalized innovation squared per degree of freedom of the fused frames
        (PDA: ``sum_i beta_i d_i^2 / ((1 - beta_0) m)`` per frame; gate: ``d^2 / m``); nan if none.
        Expected just below 1 without clutter (the gate truncates the chi-square)."""
        return self.nis_sum / self.nis_count if self.nis_count else math.nan


def _in_image_probability(cam: PinholeCamera, zhat: Array, A: Array) -> float:
    """Probability that the target projects into the image: the prediction ``N(zhat, A)`` of its
    pixel (``A = H P H^T``) integrated over ``[0, width] x [0, height]``, per axis (correlation ignored)."""
    p = 1.0
    for k, size in enumerate((cam.width, cam.height)):
        s = math.sqrt(max(float(A[k, k]), 1e-12))
        p *= 0.5 * (math.erf((size - zhat[k]) / (s * math.sqrt(2.0))) - math.erf(-zhat[k] / (s * math.sqrt(2.0))))
    return min(max(p, 0.0), 1.0)


@dataclass
class _OwnFrame:
    """Information a fused frame added to the node, until later frames confirm it."""

    t: float
    info: Array
    vec: Array
    shared: bool
    confirmations: int = 0


def miss_probability(detection: float, gate: float, density: float, image_area: float, gate_area: float) -> float:
    """Probability that a frame holding at least one detection has none inside the gate, when the
    target is detected with probability ``detection`` and then falls in the gate with probability
    ``gate``, and false detections are Poisson with density ``density``::

        P(E) = exp(-lambda V_g) [P_D (1 - P_G) + (1 - P_D) (1 - exp(-lambda (V - V_g)))]
        P(N) = 1 - (1 - P_D) exp(-lambda V)                 q = P(E) / P(N)

    ``V`` image area, ``V_g`` area of the gate inside the image. Frames without detections
    never reach a front end, hence the conditioning on a non-empty frame ``N``. ``gate = 0``
    gives the probability when the target, if detected, is always outside the gate.
    """
    V = float(image_area)
    Vg = min(max(float(gate_area), 0.0), V)
    lam = float(density)
    pe = math.exp(-lam * Vg) * (detection * (1.0 - gate) + (1.0 - detection) * -math.expm1(-lam * (V - Vg)))
    pn = 1.0 - (1.0 - detection) * math.exp(-lam * V)
    if pn <= 0.0:
        return 1.0
    return min(max(pe / pn, 0.0), 1.0)


def loss_log_likelihood_ratio(detection_on_track: float, detection: float, gate: float, density: float,
                              image_area: float, gate_area: float) -> float:
    """``log P(E | lost) / P(E | on track)`` of a non-empty frame ``E`` with no detection in the gate.

    *On track*: the estimate is right, the target is detected with ``detection_on_track``
    (``P_D`` times the probability that the estimate projects into the image) and then
    inside the gate with probability ``gate``. *Lost*: the target is in view (detected with
    ``detection``) but outside the gate. Both with the same false detections
    (:func:`miss_probability`). A frame carries no evidence (ratio 1) when the estimate is
    out of view and the camera is as likely to see the target as not.
    """
    q0 = miss_probability(detection_on_track, gate, density, image_area, gate_area)
    q1 = miss_probability(detection, 0.0, density, image_area, gate_area)
    if q0 <= 0.0:
        return math.inf
    if q1 <= 0.0:
        return -math.inf
    return math.log(q1) - math.log(q0)


class CameraFrame:
    """One camera frame for the centralized reference: :meth:`update` applies the same gate and
    clutter model as :class:`CameraFrontEnd` to an EKF's ``(x, P)``
    (:meth:`dfusion.estimation.centralized.CentralizedEKF.add_frame`), without the track-loss
    test and the tentative frames (a centralized filter has no neighbours to hold frames from)."""

    def __init__(self, front: "CameraFrontEnd", t: float, detections: Array) -> None:
        self.front = front
        self.t = float(t)
        self.detections = np.asarray(detections, dtype=float).reshape(-1, 2)

    def __repr__(self) -> str:
        return f"CameraFrame(t={self.t}, detections={len(self.detections)}, model={self.front.clutter_model!r})"

    def update(self, x: Array, P: Array) -> tuple[Array, Array]:
        """The EKF posterior ``(x, P)`` after this frame (the prediction is ``(x, P)``)."""
        fe = self.front
        cam = fe.camera_at(self.t)
        if fe.clutter_model == "gate":
            for z in self.detections:
                if not fe._projectable(x):
                    break
                res = pda_update(x, P, z[None], cam, ClutterModel(0.0, 1.0, fe.gate))
                if res.validated[0]:
                    x, P = res.mean, res.cov
            return x, P
        if not fe._projectable(x):
            return x, P
        res = fe.associate(x, P, self.detections)
        return res.mean, res.cov


class CameraFrontEnd(FrontEnd):
    """Gate camera detections against the node's fused prediction, then fuse them.

    With ``clutter_model = "pda"`` (default) the detections of a frame (one time stamp)
    are associated together by PDA (:mod:`dfusion.estimation.pda`) with the clutter
    density ``false_detection_rate / (width height)`` and the detection probability
    ``P_D`` times the probability that the predicted target projects into the image;
    the frame enters the node as the conservative equivalent measurement information
    (:func:`~dfusion.estimation.pda.pda_information`). A frame whose one validated
    detection has ``beta_0 = 0`` (no clutter model: ``false_detection_rate = 0``) is a
    plain EIF update, exactly as with the gate alone. With ``clutter_model = "gate"``
    each detection inside the gate is fused as a measurement (no clutter model).

    Parameters
    ----------
    camera : PinholeCamera
    gate : float
        Chi-square gate probability in ``(0, 1]`` (1: no gate).
    recognition_error : float or None
        ``k`` of the reliability model (pixels); default the camera's ``pixel_std``.
    source_name : str
        Name of the source reported to the node.
    clutter_model : {"pda", "gate"}
    false_detection_rate : float or None
        False detections per frame assumed by PDA; default the camera's ``clutter_rate`` (0 if none).
    detection : float
        ``P_D`` assumed by PDA (the scenario node's ``detection``).
    loss_false_alarm : float
        Probability, under the model, of declaring a track loss on a run of frames (PDA only).
    confirm : int
        A fused frame is confirmed once this many later frames were fused too; a track loss
        withdraws the own frames not yet confirmed.
    segment_gap : float or None
        Seconds without a fused frame after which the next fused frame starts a new track
        segment (default: ``(confirm + 1)`` frame periods when built from a scenario; None:
        only the first frame and a track loss start one).

    **Track loss** (PDA only). A CUSUM test (Page, "Continuous inspection schemes",
    Biometrika 41, 1954) of "lost" (the target is in view but outside the gate) against
    "on track" (the estimate is right): every frame with detections but none in the gate
    adds its log-likelihood ratio (:func:`loss_log_likelihood_ratio`) to ``S = max(0, S +
    log LR)``; a fused frame resets ``S`` to 0. When ``S > ln(1 / loss_false_alarm)`` the
    camera's view contradicts the estimate: most likely the last frames it fused were
    false detections (a re-acquisition that locked on clutter). The own frames not yet
    confirmed are withdrawn from the node (:meth:`FusionNode.withdraw_local_information`;
    the neighbours lose them with the next messages) and the front end reports ``"lost"``
    until it fuses a frame again.

    **Tentative frames.** The frames of a new track segment (the first fused frame, one
    after a gap or after a track loss: a re-acquisition, where a false detection is most
    likely to be taken for the target) are fused here but held back from the neighbours
    (``share=False``) until the segment has ``confirm + 1`` fused frames; a track loss
    before that withdraws them before anyone else saw them. They are shared without
    confirmation when the camera can no longer test them: a frame whose detections all
    miss the gate while a miss is likelier than not under the estimate (``q > 1/2``: the
    target is predicted out of view), or a new segment after a gap. Later frames of a
    confirmed segment are shared at once. Without a clutter model (``lambda = 0``: no false
    detections expected) a segment starts confirmed and nothing is held.
    :meth:`finish` shares what is still held at the end of a run. :meth:`status` is
    ``"lost"`` from a declared track loss until a frame is fused again.
    """

    def __init__(self, camera: PinholeCamera, gate: float = 0.99, recognition_error: float | None = None,
                 source_name: str = "camera", *, clutter_model: str = "pda",
                 false_detection_rate: float | None = None, detection: float = 1.0,
                 loss_false_alarm: float = 1e-3, confirm: int = 1, segment_gap: float | None = None) -> None:
        self.camera = camera
        self.gate = float(gate)
        self.threshold = gate_threshold(self.gate)
        self.recognition_error = camera.pixel_std if recognition_error is None else float(recognition_error)
        if not (math.isfinite(self.recognition_error) and self.recognition_error >= 0):
            raise ValidationError(f"recognition_error must be >= 0 pixels, got {recognition_error!r}")
        if clutter_model not in CLUTTER_MODELS:
            raise ValidationError(f"clutter_model must be one of {CLUTTER_MODELS}, got {clutter_model!r}")
        self.clutter_model = clutter_model
        rate = getattr(camera, "clutter_rate", 0.0) if false_detection_rate is None else false_detection_rate
        self.model = ClutterModel(float(rate) / (camera.width * camera.height), float(detection), self.gate)
        self.source_name = source_name
        if not isinstance(confirm, int) or isinstance(confirm, bool) or confirm < 0:
            raise ValidationError(f"confirm must be a non-negative integer, got {confirm!r}")
        if not 0.0 < loss_false_alarm < 1.0:
            raise ValidationError(f"loss_false_alarm must be in (0, 1), got {loss_false_alarm!r}")
        self.loss_threshold = -math.log(loss_false_alarm)
        self.confirm = int(confirm)
        self.segment_gap = segment_gap
        self._pending: list[_OwnFrame] = []
        self._last_fused: float | None = None
        self._segment_fused = 0
        self._segment_confirmed = False
        self._miss_log = 0.0
        self._lost = False
        self.stats = CameraStats()
        #: Mahalanobis distances of the detections, in processing order (for diagnostics).
        self.distances: list[float] = []

    def __repr__(self) -> str:
        return f"CameraFrontEnd(gate={self.gate}, clutter_model={self.clutter_model!r}, {self.stats})"

    @staticmethod
    def prediction(node: FusionNode, t: float) -> tuple[Array, Array]:
        """The node's estimate of the state at ``t`` without the detection being gated.

        ``node.estimate(t)`` when ``t`` is inside the window (a window state, or
        between two: the marginal predicted from its neighbours); the newest state
        predicted forward with the motion model when ``t`` is newer than it. Raises
        :class:`~dfusion.errors.OutsideWindowError` when ``t`` is older than the window.
        """
        f = node.filter
        if t <= f.latest_time + f.time_tol:
            return node.estimate(t)
        mean, cov = node.estimate()
        dt = t - f.latest_time
        F = node.motion.F(dt, mean)
        return node.motion.f(mean, dt), F @ cov @ F.T + node.motion.Q(dt, mean)

    def _projectable(self, mean: Array) -> bool:
        cam = self.camera
        return bool(cam.camera_point(mean)[2] > max(cam.min_depth, cam.MIN_PROJECT_DEPTH))

    def distance(self, node: FusionNode, t: float, z: Array) -> float:
        """Squared Mahalanobis distance of detection ``z`` at ``t`` to the prediction (inf if unprojectable)."""
        mean, cov = self.prediction(node, t)
        cam = self.camera
        if not self._projectable(mean):
            return math.inf
        H = cam.H(mean)
        nu = cam.residual(np.asarray(z, dtype=float), cam.h(mean))
        S = H @ cov @ H.T + cam.R
        return float(nu @ np.linalg.solve(S, nu))

    def camera_at(self, t: float) -> PinholeCamera:
        """The camera that took the frame of time ``t`` (a fixed camera: always the same);
        the methods that follow use it as ``self.camera``."""
        return self.camera

    def detection_probability(self, mean: Array, cov: Array) -> float:
        """``P_D`` times the probability that the predicted target projects into the image."""
        cam = self.camera
        H = cam.H(mean)
        return self.model.detection * _in_image_probability(cam, cam.h(mean), H @ cov @ H.T)

    def associate(self, mean: Array, cov: Array, detections: Array) -> PDAResult:
        """PDA of a frame's detections against the prediction ``(mean, cov)`` (projectable)."""
        return pda_update(mean, cov, detections, self.camera, self.model,
                          detection=self.detection_probability(mean, cov))

    def process(self, node: FusionNode, t: float, z: Array) -> bool:
        """Gate and fuse detection ``z`` taken at ``t`` (a frame of one detection); returns whether it was fused."""
        return self.process_frame(node, t, np.asarray(z, dtype=float)[None]) > 0

    def process_frame(self, node: FusionNode, t: float, detections: Array) -> int:
        """Gate and fuse the detections of one frame taken at ``t``; returns how many were fused.

        Raises :class:`~dfusion.errors.OutsideWindowError` (before counting anything) when
        ``t`` is older than the node's window.
        """
        Z = np.asarray(detections, dtype=float).reshape(-1, 2)
        self.camera_at(t)
        if self.clutter_model == "gate":
            return sum(self._gate_one(node, t, z) for z in Z)
        mean, cov = self.prediction(node, t)
        st = self.stats
        st.frames += 1
        st.processed += len(Z)
        st.rejected += len(Z)   # until fused
        if not self._projectable(mean):
            self.distances.extend([math.inf] * len(Z))
            st.unprojectable += len(Z)
            return 0
        res = self.associate(mean, cov, Z)
        self.distances.extend(res.d2.tolist())
        valid = int(np.count_nonzero(res.validated))
        st.gated += len(Z) - valid
        if valid == 0 or res.beta0 >= 1.0:
            self._miss(node, res)
            return 0
        d2v = res.d2[res.validated]
        share = self._continues_segment(node, t)
        if valid == 1 and res.beta0 == 0.0:   # a plain measurement
            Lam, y = node.update(t, Z[np.flatnonzero(res.validated)[0]], self.camera, share=share)
        else:
            info = pda_information(res)
            st.pda_partial += not info.exact
            if info.kept == 0:
                return 0
            Lam, y = info.info, info.vec
            node.add_local_information(t, Lam, y, share=share)
        self._hit(node, t, Lam, y, share)
        st.nis_sum += float(res.beta @ d2v) / ((1.0 - res.beta0) * 2.0)
        st.nis_count += 1
        st.contributed += valid
        st.rejected -= valid
        st.frames_fused += 1
        self._report(node)
        return valid

    # ------------------------------------------------------------------ track loss
    def _continues_segment(self, node: FusionNode, t: float) -> bool:
        """Whether a frame fused at ``t`` is shared at once (its track segment is confirmed);
        starts a new segment after a gap or a loss, tentative when false detections are possible.
        A segment that ended in a gap, uncontradicted, is shared."""
        last = self._last_fused
        if last is None or self._lost or (self.segment_gap is not None and t - last > self.segment_gap):
            if not self._lost:
                self._share_held(node)
            self._segment_fused = 0
            self._segment_confirmed = not self.model.density > 0.0
        return self._segment_confirmed

    #: Grid (columns, rows) on which the gate's area inside the image is counted.
    GATE_GRID = (64, 48)

    def _gate_area(self, res: PDAResult) -> float:
        """Area (pixels^2) of the validation gate ``d^2 <= gamma`` inside the image, counted on
        a grid of :attr:`GATE_GRID` cell centres (the ellipse may be partly or wholly outside)."""
        cam = self.camera
        W, H = float(cam.width), float(cam.height)
        zhat = np.asarray(cam.h(res.prior_mean), dtype=float)
        nu_, nv_ = self.GATE_GRID
        u = (np.arange(nu_) + 0.5) * (W / nu_) - zhat[0]
        v = (np.arange(nv_) + 0.5) * (H / nv_) - zhat[1]
        Si = np.linalg.solve(res.S, np.eye(2))
        d2 = Si[0, 0] * u[None, :] ** 2 + 2.0 * Si[0, 1] * u[None, :] * v[:, None] + Si[1, 1] * v[:, None] ** 2
        return float(np.count_nonzero(d2 <= res.gamma)) * (W * H) / (nu_ * nv_)

    def _hit(self, node: FusionNode, t: float, Lam: Array, y: Array, shared: bool) -> None:
        for fr in self._pending:
            fr.confirmations += 1
        self._pending.append(_OwnFrame(float(t), np.array(Lam, dtype=float), np.array(y, dtype=float), shared))
        self._segment_fused += 1
        if not self._segment_confirmed and self._segment_fused > self.confirm:
            self._segment_confirmed = True
            self._share_held(node)
        self._pending = [fr for fr in self._pending if fr.confirmations < self.confirm or not fr.shared]
        self._last_fused = t if self._last_fused is None else max(self._last_fused, t)
        self._miss_log = 0.0
        self._lost = False

    def _share_held(self, node: FusionNode) -> None:
        for fr in self._pending:
            if not fr.shared:
                node.share_local_information(fr.t, fr.info, fr.vec)
                fr.shared = True

    def finish(self, node: FusionNode) -> None:
        """End of a run: share the frames still held back (nothing will confirm them now)."""
        self._share_held(node)

    def _miss(self, node: FusionNode, res: PDAResult) -> None:
        """A frame with detections, none fused: accumulate the evidence of a track loss (CUSUM)."""
        cam = self.camera
        V, Vg = cam.width * cam.height, self._gate_area(res)
        llr = loss_log_likelihood_ratio(res.detection, self.model.detection, self.model.gate, self.model.density,
                                        V, Vg)
        self._miss_log = max(0.0, self._miss_log + llr)
        q = miss_probability(res.detection, self.model.gate, self.model.density, V, Vg)
        if self._miss_log > self.loss_threshold:
            self._declare_loss(node)
        elif q > 0.5:
            # a miss is likelier than not even if the estimate is right (the target is predicted
            # to have left the view): the camera can no longer test its tentative frames
            self._share_held(node)

    def _declare_loss(self, node: FusionNode) -> None:
        withdrawn = sum(node.withdraw_local_information(fr.t, fr.info, fr.vec, shared=fr.shared)
                        for fr in self._pending)
        self.stats.losses += 1
        self.stats.withdrawn += withdrawn
        log.warning("%s: track loss (frames with detections, none in the gate, improbable under the estimate); "
                    "%d unconfirmed own frame(s) withdrawn", node.name, withdrawn)
        self._pending = []
        self._miss_log = 0.0
        self._lost = True
        self._segment_confirmed = False
        self._segment_fused = 0

    def status(self) -> str:
        """``"lost"`` from a declared track loss until a frame is fused again, else ``"ok"``."""
        return "lost" if self._lost else "ok"

    def _gate_one(self, node: FusionNode, t: float, z: Array) -> bool:
        """The hard gate alone (``clutter_model = "gate"``): fuse ``z`` if inside the gate."""
        d2 = self.distance(node, t, z)
        st = self.stats
        st.processed += 1
        st.frames += 1
        self.distances.append(d2)
        if not math.isfinite(d2):
            st.unprojectable += 1
            st.rejected += 1
            return False
        if d2 > self.threshold:
            st.gated += 1
            st.rejected += 1
            return False
        node.update(t, z, self.camera)
        st.contributed += 1
        st.frames_fused += 1
        st.nis_sum += d2 / 2.0
        st.nis_count += 1
        self._report(node)
        return True

    def reference_frame(self, t: float, detections: Array) -> CameraFrame:
        """The frame as the centralized reference applies it (same gate and clutter model)."""
        return CameraFrame(self, t, detections)

    def _report(self, node: FusionNode) -> None:
        mean, cov = node.estimate()
        node.report_source(Estimate(self.source_name, node.latest_time, mean, cov,
                                    reliability=self._reliability(mean)))

    def _reliability(self, mean: Array) -> float:
        try:
            return camera_reliability_at(self.camera, mean[:2], self.recognition_error)
        except ValidationError:   # camera not above the target's plane
            return 0.0

    def reliability(self, node: FusionNode) -> float:
        """Camera reliability (switching paper eq. 1-9) at the node's newest estimate; 0 out of view."""
        mean, _ = node.estimate()
        return self._reliability(mean)


class MountedCameraFrontEnd(CameraFrontEnd):
    """:class:`CameraFrontEnd` for a camera on a moving robot: each frame is gated, associated
    and fused with the camera where it was at the frame's time (``mounted.at(t)``); the
    centralized reference's :class:`CameraFrame` takes the same camera. Keyword arguments
    (the clutter model and its settings) are those of :class:`CameraFrontEnd`."""

    def __init__(self, mounted: MountedCamera, gate: float = 0.99, recognition_error: float | None = None,
                 source_name: str = "camera", **kwargs: Any) -> None:
        super().__init__(mounted.at(0.0), gate, recognition_error, source_name, **kwargs)
        self.mounted = mounted

    def camera_at(self, t: float) -> PinholeCamera:
        """The mounted camera at ``t``, which becomes ``self.camera``."""
        self.camera = self.mounted.at(t)
        return self.camera
