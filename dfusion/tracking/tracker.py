r"""The multi-target tracker: hypothesiser, data associator, initiator and deleter over per-track filters.

One scan (the detections of one sensor at one time, :class:`~dfusion.tracking.track.Scan`)
at a time, in time order (scans of several sensors at one time in any order):

1. every confirmed track is predicted to the scan's time (its information filter);
2. the hypothesiser gates and weighs every (track, detection) pair
   (:mod:`dfusion.tracking.gating`); tracks out of the scan's view take no part;
3. the associator gives the weights ``beta_tj``, ``beta_t0`` (GNN or JPDA,
   :mod:`dfusion.tracking.association`);
4. each track in view is updated by the PDA update with these weights, in information
   form: the factor ``(Lambda, y)`` of :func:`dfusion.estimation.pda_information` is added to
   its ``(Omega, eta)`` (for 0/1 weights, the Kalman update ``H^T R^-1 H``,
   ``H^T R^-1 z``); it counts a hit when ``beta_t0 < 1/2``, a miss otherwise when it is in
   the view with probability at least 1/2;
5. detections inside the gate of no confirmed track in view go to the initiator, which
   returns the tracks it confirms, with new identities;
6. the deleter removes tracks that have ended.

A single target is a tracker with one track: nothing else changes. The tracker's tracks
are its confirmed tracks; the tentative ones are the initiator's.
"""
from __future__ import annotations

import logging

import numpy as np

from dfusion.errors import TimeError
from dfusion.estimation.eif import ExtendedInformationFilter
from dfusion.estimation.pda import PDAResult, pda_information, pda_moments
from dfusion.estimation.gaussian import project_psd_information
from dfusion.linalg import Array, cholesky, spd_inverse, spd_solve, symmetrize
from dfusion.models.base import MotionModel
from dfusion.tracking.association import Association, DataAssociator
from dfusion.tracking.deletion import Deleter
from dfusion.tracking.gating import GaussianHypothesiser, Hypotheses, Hypothesiser
from dfusion.tracking.initiation import Initiator
from dfusion.tracking.track import IdentityIssuer, Scan, Track, TrackId

__all__ = ["MultiTargetTracker", "track_update_information"]

log = logging.getLogger(__name__)


def track_update_information(hyp: Hypotheses, assoc: Association, t: int) -> tuple[Array, Array] | None:
    """The information ``(Lambda, y)`` track ``t`` takes from its scan, or ``None`` when none.

    The PDA update of the track's prediction with the association's weights of this track
    (:func:`dfusion.estimation.pda_moments`), expressed as information by
    :func:`dfusion.estimation.pda_information` (exact when every direction is kept).
    """
    if not assoc.active[t]:
        return None
    used = np.flatnonzero(assoc.weights[t] > 0)
    if used.size == 0:
        return None
    beta = assoc.weights[t, used]
    beta0 = float(assoc.miss[t])
    if hyp.pair_S is not None:
        return _per_detection_update_information(hyp, t, used, beta, beta0)
    x, P, H, S = hyp.means[t], hyp.covs[t], hyp.H[t], hyp.S[t]
    nus = hyp.innovations[t, used]
    mean, cov = pda_moments(x, P, H, S, nus, beta0, beta)
    res = PDAResult(mean, cov, x, P, H, S, hyp.d2[t], hyp.gated[t], nus, beta0, beta,
                    float(hyp.detection[t]), hyp.gamma)
    info = pda_information(res)
    return info.info, info.vec


def _per_detection_update_information(hyp: Hypotheses, t: int, used: Array, beta: Array,
                                      beta0: float) -> tuple[Array, Array]:
    r"""The update factor of track ``t`` when each detection has its own noise ``R_j``.

    One detection with weight 1 (GNN, or a JPDA track with a single sure detection): the
    Kalman update in information form, ``Lambda = H^T R_j^-1 H``,
    ``y = H^T R_j^-1 (nu_j + H x^)`` (exact). Otherwise the moments of the mixture
    ``beta_0 N(x^, P^) + sum_j beta_j N(x^ + K_j nu_j, P^ - K_j S_tj K_j^T)``,
    ``K_j = P^ H^T S_tj^-1`` (the PDA mixture of :func:`dfusion.estimation.pda_moments` with
    each detection's own gain; Bar-Shalom, Daum & Huang 2009, eq. 45-47), entered as
    ``Lambda = P^-1 - P^^-1``, ``y = P^-1 x - P^^-1 x^``, projected onto the positive
    semi-definite cone (:func:`dfusion.estimation.project_psd_information`): exact when the
    mixture is narrower than the prediction in every direction, otherwise the directions
    where it is wider take no information.
    """
    x, P, H = hyp.means[t], hyp.covs[t], hyp.H[t]
    if used.size == 1 and beta0 <= 0.0 and abs(float(beta[0]) - 1.0) <= 1e-12:
        j = int(used[0])
        C = cholesky(hyp.noise[j], "detection noise R")
        AH = np.linalg.solve(C, H)
        Ar = np.linalg.solve(C, hyp.innovations[t, j] + H @ x)
        return symmetrize(AH.T @ AH), AH.T @ Ar
    mean = beta0 * x
    second = beta0 * (P + np.outer(x, x))
    for b, j in zip(beta, used):
        S = hyp.pair_S[t, j]
        K = spd_solve(S, H @ P, "innovation covariance S").T     # P H^T S^-1
        xj = x + K @ hyp.innovations[t, j]
        Pj = symmetrize(P - K @ S @ K.T)
        mean = mean + b * xj
        second = second + b * (Pj + np.outer(xj, xj))
    cov = symmetrize(second - np.outer(mean, mean))
    Om_post = spd_inverse(cov, "mixture covariance")
    Om_prior = spd_inverse(P, "predicted covariance")
    info, vec, _ = project_psd_information(Om_post - Om_prior, Om_post @ mean - Om_prior @ x)
    return info, vec


class MultiTargetTracker:
    """Tracks many targets from scans of detections (module docstring).

    Parameters
    ----------
    motion : every track's motion model.
    associator : :class:`~dfusion.tracking.association.GNN` or :class:`~dfusion.tracking.association.JPDA`.
    initiator : starts tracks (e.g. :class:`~dfusion.tracking.initiation.MofNInitiator`).
    deleter : ends them (e.g. :class:`~dfusion.tracking.deletion.AnyDeleter`).
    origin : this tracker's (node's) name: identities are ``origin#0, origin#1, ...``.
    hypothesiser : default :class:`~dfusion.tracking.gating.GaussianHypothesiser` with a 0.99 gate.
    """

    def __init__(self, motion: MotionModel, associator: DataAssociator, initiator: Initiator, deleter: Deleter, *,
                 origin: str = "tracker", hypothesiser: Hypothesiser | None = None) -> None:
        self.motion = motion
        self.associator = associator
        self.initiator = initiator
        self.deleter = deleter
        self.hypothesiser = hypothesiser or GaussianHypothesiser()
        self.issuer = IdentityIssuer(origin)
        self.tracks: list[Track] = []
        self.time: float | None = None
        self.deleted = 0

    def add_track(self, mean: Array, cov: Array, t: float, track_id: TrackId | None = None) -> Track:
        """Start a confirmed track from a known state (a prior, or a neighbour's track); new identity if none given."""
        filt = ExtendedInformationFilter(self.motion)
        filt.initialize(mean, cov)
        track = Track(track_id or self.issuer.next(), filt, float(t), float(t), confirmed=True)
        self.tracks.append(track)
        self.tracks.sort(key=lambda tr: tr.id)
        return track

    def step(self, scan: Scan) -> list[Track]:
        """Process one scan; returns the confirmed tracks after it."""
        if self.time is not None and scan.time < self.time - 1e-9:
            raise TimeError(f"scan at t={scan.time} is older than the tracker's time {self.time}")
        self.time = scan.time if self.time is None else max(self.time, scan.time)
        for track in self.tracks:
            track.predict(scan.time)
        hyp = self.hypothesiser.hypothesise(self.tracks, scan)
        assoc = self.associator.associate(hyp)
        for t, track in enumerate(self.tracks):
            if not assoc.active[t]:
                continue
            factor = track_update_information(hyp, assoc, t)
            if factor is not None:
                track.add_information(*factor)
            hit = assoc.hit(t)
            if hit or hyp.visibility[t] >= 0.5:      # not missed by a sensor that probably does not see it
                track.record(hit, window=1)
        claimed = (hyp.gated & assoc.active[:, None]).any(axis=0) if self.tracks else np.zeros(len(scan.detections), bool)
        born = self.initiator.initiate(scan, scan.detections[~claimed], self.issuer)
        ended = [tr for tr in self.tracks if self.deleter.should_delete(tr)]
        if ended:
            log.debug("deleting tracks %s at t=%.3f", [str(tr.id) for tr in ended], scan.time)
            self.deleted += len(ended)
            gone = {id(tr) for tr in ended}
            self.tracks = [tr for tr in self.tracks if id(tr) not in gone]
        if born:
            self.tracks.extend(born)
            self.tracks.sort(key=lambda tr: tr.id)
        return list(self.tracks)

    def estimates(self) -> list[tuple[TrackId, Array, Array]]:
        """``(identity, mean, cov)`` of every confirmed track at its time."""
        return [(tr.id, *tr.estimate()) for tr in self.tracks]
