"""After a merge, one pose graph over every placed robot's keyframes, so the seam does not stay.

Placing a robot (mapper/fleet/placement.py) puts its whole trajectory where one match says; each match is
a few centimetres and a degree off, and a robot's own trajectory drifts, so where two robots meet
again the second match disagrees with the first. Each verified match between two robots' keyframes
is a `Link` (the relative pose the depth-verified alignment measured); with more links than it takes
to place the robots, the keyframes no longer fit one rigid placement per robot, and the graph
settles them: nodes are the map's keyframes, edges each robot's consecutive keyframes as its own
tracker sees them (its latest corrections included) and the links, the map's first keyframe fixed.
Solved with gtsam (kit/posegraph.py) at defined points of the fleet merge, from the trackers' poses
and the rigid placements, so the same streams give the same poses and the same map bytes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from octolog.kit.geometry import invert
from octolog.kit.posegraph import optimize_pose_graph

# The noise of each edge, as a weight on kit/posegraph.py's 1 cm / 0.5 degree: a robot's own
# relative poses drift with the path between them (DRIFT_PER_M of it, ORB-SLAM-class RGB-D tracking
# drifts about 1 % of the path), so nearby keyframes hold each other stiffly and only the long way
# round gives; a link is as good as its alignment's residual (ICP, at least MIN_LINK_M).
DRIFT_PER_M = 0.01
MIN_STEP_M = 0.01  # keyframes closer than this are held as if this far apart
MIN_LINK_M = 0.005
BASE_M = 0.01  # kit/posegraph.py's translation sigma at weight 1


@dataclass(frozen=True)
class Link:
    """A verified match: map keyframe `a` sees the place map keyframe `b` sees, from `a_from_b`."""

    a: int  # map-wide keyframe id
    b: int  # map-wide keyframe id (another robot's)
    a_from_b: np.ndarray
    rmse_m: float = BASE_M  # the alignment's residual


def needs_graph(links: list[Link], n_placed: int) -> bool:
    """Whether the links say more than the rigid placements do: one link per placed robot beyond
    the first places it; any more close a cycle the placements alone cannot satisfy."""
    return len(links) > n_placed - 1


def joint_poses(robot_poses: list[dict[int, np.ndarray]], world_from_robot: list[np.ndarray | None],
                links: list[Link]) -> dict[int, np.ndarray]:
    """World poses of every placed robot's keyframes ({map-wide id: world_from_camera}) that best
    agree with each robot's own relative poses (`robot_poses[r]`: {map-wide id: robot_from_camera},
    ids in its order) and the links; starts from the rigid placements `world_from_robot`."""
    ids: list[int] = []
    initial: list[np.ndarray] = []
    edges: list[tuple[int, int, np.ndarray, float]] = []
    for r, poses in enumerate(robot_poses):
        W = world_from_robot[r]
        if W is None or not poses:
            continue
        chain = sorted(poses)
        for k, g in enumerate(chain):
            if k:
                step = invert(poses[chain[k - 1]]) @ poses[g]
                sigma = DRIFT_PER_M * max(float(np.linalg.norm(step[:3, 3])), MIN_STEP_M)
                edges.append((len(ids) - 1, len(ids), step, (BASE_M / sigma) ** 2))
            ids.append(g)
            initial.append(W @ poses[g])
    at = {g: i for i, g in enumerate(ids)}
    edges += [(at[lk.a], at[lk.b], lk.a_from_b, (BASE_M / max(lk.rmse_m, MIN_LINK_M)) ** 2)
              for lk in links if lk.a in at and lk.b in at]
    fixed = at[min(ids)]  # the map's first keyframe: the map's world stays where it is
    out = optimize_pose_graph(np.stack(initial), edges, fixed=fixed)
    return {g: out[i] for g, i in at.items()}
