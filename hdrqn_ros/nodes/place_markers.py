"""The robot's places as RViz / Foxglove markers (``visualization_msgs/MarkerArray``).

A disc per place in its goal's colour (faint once visited), the current option's place
tall, and the option's subgoal named above it (namespaces ``hdrqn_places``, ``hdrqn_subgoal``).
"""
from __future__ import annotations

from geometry_msgs.msg import Point, Pose, Vector3
from std_msgs.msg import ColorRGBA, Header
from visualization_msgs.msg import Marker, MarkerArray

from hdrqn_ros.envs.gridworld import GOAL0, GOAL_NAMES, PALETTE

MARKERS = "subgoal_markers"
"""The topic (default QoS)."""
DISC_M, TALL_M, FLAT_M = 0.2, 0.4, 0.05
"""A place's disc: diameter; height of the current option's place, of the others."""


def _pose(x: float, y: float, z: float) -> Pose:
    return Pose(position=Point(x=float(x), y=float(y), z=float(z)))


def place_markers(header: Header, places_xy, visited, option_subgoal: int, robot_xy) -> MarkerArray:
    """Markers of ``places_xy`` ``(n, 2)`` m (``visited`` ``(n,)`` bool) with the option's
    place ``option_subgoal`` (-1: none yet; its label then stands over ``robot_xy``)."""
    markers = []
    for g, (x, y) in enumerate(places_xy):
        red, green, blue = (int(c) / 255 for c in PALETTE[GOAL0 + g])
        height = TALL_M if g == option_subgoal else FLAT_M
        markers.append(Marker(header=header, ns="hdrqn_places", id=g, type=Marker.CYLINDER, action=Marker.ADD,
                              pose=_pose(x, y, height / 2), scale=Vector3(x=DISC_M, y=DISC_M, z=height),
                              color=ColorRGBA(r=red, g=green, b=blue, a=0.25 if visited[g] else 0.9)))
    label = GOAL_NAMES[option_subgoal] if 0 <= option_subgoal < len(GOAL_NAMES) else "none"
    x, y = places_xy[option_subgoal] if option_subgoal >= 0 else robot_xy
    markers.append(Marker(header=header, ns="hdrqn_subgoal", id=0, type=Marker.TEXT_VIEW_FACING, action=Marker.ADD,
                          pose=_pose(x, y, 0.6), scale=Vector3(z=0.15), color=ColorRGBA(a=1.0),
                          text=f"subgoal: {label}"))
    return MarkerArray(markers=markers)
