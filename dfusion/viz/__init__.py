"""Looking at runs: figures (PNG, matplotlib's Agg backend) and MCAP recordings for Foxglove.

* :mod:`dfusion.viz.plots`: error plots of a run (:func:`plot_result`, URUS Figure 33
  :func:`plot_figure33`);
* :mod:`dfusion.viz.topdown`: the top-down figure (truth, estimates with 3-sigma ellipses,
  sensor footprints, the tree) of a run and of real-data examples;
* :mod:`dfusion.viz.foxglove`: a run as an MCAP file with Foxglove's schemas
  (``docs/ros.md``).
"""
from dfusion.viz.foxglove import record_mcap
from dfusion.viz.plots import plot_figure33, plot_result
from dfusion.viz.topdown import Scene, Track, draw_scene, plot_topdown, scene_of_result

__all__ = ["plot_result", "plot_figure33", "plot_topdown", "draw_scene", "scene_of_result", "Scene", "Track",
           "record_mcap"]
