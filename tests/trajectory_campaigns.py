"""Shared helpers of the trajectory tests: a one-anchor campaign from a path function and its ranges, and a
straight road."""

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


def straight_road(seed, hill=0.0, wiggle=0.0, heading=0.0, noise_m=0.08):
    """Out and back twice along a straight 120 m road at 8 m/s (heading [rad] from +x), terrain rolling by `hill`,
    the road weaving sideways by `wiggle` [m]; one anchor 4-8 m beside it, 2-4 m up; ranges at 10 Hz with a
    0.2 m bias."""
    gen = np.random.default_rng(seed)
    side = gen.choice([-1.0, 1.0])
    local = np.array([gen.uniform(-20, 20), gen.uniform(4, 8) * side, gen.uniform(2, 4)])
    rot = np.array([[np.cos(heading), -np.sin(heading), 0.0], [np.sin(heading), np.cos(heading), 0.0], [0, 0, 1]])
    length, v = 120.0, 8.0
    period = 2 * length / v

    def body(t):
        s = (t % period) * v
        x = np.where(s < length, s, 2 * length - s) - length / 2
        xyz = np.stack([x, wiggle * np.sin(2 * np.pi * x / 50.0), hill * np.sin(2 * np.pi * x / 80.0)], 1)
        return xyz @ rot.T, np.full(x.shape, heading)

    t = np.arange(0.0, 2 * period, 0.1)
    rt = np.arange(0.05, t[-1] - 0.05, 0.1)
    anchor = (rot @ local)[None]
    r = np.linalg.norm(body(rt)[0] - anchor[0], axis=1) + 0.2 + noise_m * gen.normal(size=rt.size)
    return one_anchor_dataset("road", body, anchor, t, rt, r), local
