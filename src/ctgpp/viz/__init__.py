"""Pictures and animations of scenes and rollouts, labelled with the displayed vehicle numbers."""

from ctgpp.viz.animation import animate_rollout, render_frames
from ctgpp.viz.scene_plot import Event, draw_scene, plot_scene

__all__ = ["Event", "animate_rollout", "draw_scene", "plot_scene", "render_frames"]
