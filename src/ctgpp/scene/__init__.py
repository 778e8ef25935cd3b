"""The scene model: agent tracks, lane graph, drivable area."""

from ctgpp.scene.types import AgentTracks, AgentType, DrivableArea, LaneGraph, Scene
from ctgpp.scene.vehicles import controlled_vehicles

__all__ = ["AgentTracks", "AgentType", "DrivableArea", "LaneGraph", "Scene", "controlled_vehicles"]
