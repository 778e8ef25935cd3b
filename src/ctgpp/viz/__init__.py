"""Pictures and animations of scenes and rollouts, labelled with the displayed vehicle numbers."""

from ctgpp.viz.animation import animate_rollout, render_frames
from ctgpp.viz.caption import QueryCaption
from ctgpp.viz.events import Event, event_lines, rollout_events
from ctgpp.viz.scene_plot import draw_scene, plot_scene

__all__ = [
    "Event",
    "QueryCaption",
    "animate_rollout",
    "draw_scene",
    "event_lines",
    "plot_scene",
    "render_frames",
    "rollout_events",
]
