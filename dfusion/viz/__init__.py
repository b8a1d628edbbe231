"""Looking at runs: figures (PNG, matplotlib's Agg backend) and MCAP recordings for Foxglove.

* :mod:`dfusion.viz.plots`: error plots of a run (:func:`plot_result`, URUS Figure 33
  :func:`plot_figure33`);
* :mod:`dfusion.viz.topdown`: the top-down figure (truth, estimates with 3-sigma ellipses,
  sensor footprints, the tree) of a run and of real-data examples;
* :mod:`dfusion.viz.tracks`: many targets: every node's tracks in their identity's colour
  with the truth, seen from above, and the identity timeline per node with the network
  label agreement (``docs/multi-target.md``);
* :mod:`dfusion.viz.foxglove`: a run as an MCAP file with Foxglove's schemas
  (``docs/ros.md``), and every node's tracks of a many-target run.
"""
from dfusion.viz.foxglove import record_mcap, record_tracks_mcap
from dfusion.viz.plots import plot_figure33, plot_result
from dfusion.viz.topdown import Scene, Track, draw_scene, plot_topdown, scene_of_result
from dfusion.viz.tracks import identity_color, identity_timeline, plot_identity_timeline, plot_tracks_topdown

__all__ = ["plot_result", "plot_figure33", "plot_topdown", "draw_scene", "scene_of_result", "Scene", "Track",
           "record_mcap", "record_tracks_mcap", "identity_color", "identity_timeline", "plot_identity_timeline",
           "plot_tracks_topdown"]
