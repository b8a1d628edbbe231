"""Multi-target tracking: tracks with network-unique identities, gating, GNN and JPDA (EHM) association, M-of-N initiation, deletion, the multi-target tracker, scans from anonymous robot sightings, and the history of a run (tracks per node over time, the truth)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from dfusion.lazy import lazy_exports

if TYPE_CHECKING:  # the names, for type checkers and IDEs; imported on first use at run time
    from dfusion.tracking.association import GNN, JPDA, Association, DataAssociator, ehm_marginals, gated_clusters
    from dfusion.tracking.deletion import (AnyDeleter, CovarianceDeleter, Deleter, MissDeleter, NoDeleter,
                                           ObserverDeleter, RegionDeleter, StaleDeleter)
    from dfusion.tracking.gating import GaussianHypothesiser, Hypotheses, Hypothesiser
    from dfusion.tracking.history import TrackHistory, TruthPaths
    from dfusion.tracking.initiation import Initiator, MofNInitiator, NoInitiator, two_point_state
    from dfusion.tracking.sightings import CameraView, sightings_scan
    from dfusion.tracking.track import IdentityIssuer, Scan, Track, TrackId
    from dfusion.tracking.track_to_track import TrackToTrackAssociator
    from dfusion.tracking.tracker import MultiTargetTracker, track_update_information

_WHERE = {
    "Association": ("dfusion.tracking.association", "Association"),
    "DataAssociator": ("dfusion.tracking.association", "DataAssociator"),
    "GNN": ("dfusion.tracking.association", "GNN"),
    "JPDA": ("dfusion.tracking.association", "JPDA"),
    "ehm_marginals": ("dfusion.tracking.association", "ehm_marginals"),
    "gated_clusters": ("dfusion.tracking.association", "gated_clusters"),
    "Deleter": ("dfusion.tracking.deletion", "Deleter"),
    "MissDeleter": ("dfusion.tracking.deletion", "MissDeleter"),
    "CovarianceDeleter": ("dfusion.tracking.deletion", "CovarianceDeleter"),
    "StaleDeleter": ("dfusion.tracking.deletion", "StaleDeleter"),
    "ObserverDeleter": ("dfusion.tracking.deletion", "ObserverDeleter"),
    "RegionDeleter": ("dfusion.tracking.deletion", "RegionDeleter"),
    "AnyDeleter": ("dfusion.tracking.deletion", "AnyDeleter"),
    "NoDeleter": ("dfusion.tracking.deletion", "NoDeleter"),
    "Hypotheses": ("dfusion.tracking.gating", "Hypotheses"),
    "Hypothesiser": ("dfusion.tracking.gating", "Hypothesiser"),
    "GaussianHypothesiser": ("dfusion.tracking.gating", "GaussianHypothesiser"),
    "Initiator": ("dfusion.tracking.initiation", "Initiator"),
    "MofNInitiator": ("dfusion.tracking.initiation", "MofNInitiator"),
    "NoInitiator": ("dfusion.tracking.initiation", "NoInitiator"),
    "two_point_state": ("dfusion.tracking.initiation", "two_point_state"),
    "CameraView": ("dfusion.tracking.sightings", "CameraView"),
    "sightings_scan": ("dfusion.tracking.sightings", "sightings_scan"),
    "TrackId": ("dfusion.tracking.track", "TrackId"),
    "IdentityIssuer": ("dfusion.tracking.track", "IdentityIssuer"),
    "Track": ("dfusion.tracking.track", "Track"),
    "Scan": ("dfusion.tracking.track", "Scan"),
    "MultiTargetTracker": ("dfusion.tracking.tracker", "MultiTargetTracker"),
    "TrackToTrackAssociator": ("dfusion.tracking.track_to_track", "TrackToTrackAssociator"),
    "TrackHistory": ("dfusion.tracking.history", "TrackHistory"),
    "TruthPaths": ("dfusion.tracking.history", "TruthPaths"),
    "track_update_information": ("dfusion.tracking.tracker", "track_update_information"),
}

__all__ = list(_WHERE)

__getattr__, __dir__ = lazy_exports(__name__, _WHERE, globals(), __all__)
