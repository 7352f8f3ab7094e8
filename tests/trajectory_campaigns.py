"""Shared helper of the trajectory tests: a one-anchor campaign from a path function and its ranges."""

import numpy as np

from jaxcal.data import TrajectoryDataset


def one_anchor_dataset(name, body, anchor, t, rt, r):
    """TrajectoryDataset of one tag on the path `body(time) -> ((n, 3) positions [m], (n,) yaw [rad])`, posed at
    times `t` [s], with ranges `r` [m] to the anchor `anchor` ((1, 3) truth [m]) at times `rt` [s]."""
    p, yaw = body(t)
    q = np.stack([0 * t, 0 * t, np.sin(yaw / 2), np.cos(yaw / 2)], 1)
    return TrajectoryDataset(
        name=name,
        anchor_ids=["a0"],
        tag_ids=["t"],
        lever_arm=[[0.0, 0.0, 0.0]],
        pose_time=t,
        pose_position=p,
        pose_orientation=q,
        range_time=rt,
        range_anchor=np.zeros(rt.size, int),
        range_tag=np.zeros(rt.size, int),
        range=r,
        anchor_truth=anchor,
    )
