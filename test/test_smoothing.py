"""Smoothed trajectories: exact at the visits, rigid odometry when nothing changes, drift removed."""

from __future__ import annotations

import numpy as np
import pytest

from ptm_ros.errors import ModelError
from ptm_ros.geometry import compose
from ptm_ros.smoothing import smoothed_trajectory


def square(n_per_side=20, noise_yaw=0.0):
    steps = []
    for _ in range(4):
        steps += [(0.5, 0.0, 0.0)] * n_per_side + [(0.0, 0.0, np.pi / 2 + noise_yaw)]
    pose = np.zeros(3)
    out = [pose]
    for s in steps:
        pose = compose(pose, s)
        out.append(pose)
    return np.array(out)


def test_identity_when_visit_poses_equal_odometry():
    u = square()
    t = np.arange(len(u), dtype=float)
    vis = np.array([0, 21, 42, 63, 84])
    sm = smoothed_trajectory(t, u, t[vis], u[vis])
    assert np.allclose(sm, u, atol=1e-12)


def test_exact_at_visits_and_removes_heading_drift():
    truth = square()
    drift = square(noise_yaw=0.05)  # odometry with a heading bias at every corner
    t = np.arange(len(truth), dtype=float)
    vis = np.array([0, 21, 42, 63, 84])
    sm = smoothed_trajectory(t, drift, t[vis], truth[vis])  # optimised poses = the truth here
    assert np.allclose(sm[vis], truth[vis])
    err_raw = np.hypot(*(drift[:, :2] - truth[:, :2]).T)
    err_smooth = np.hypot(*(sm[:, :2] - truth[:, :2]).T)
    assert err_smooth.max() < 0.25 * err_raw.max()


def test_bad_input():
    u = square()
    t = np.arange(len(u), dtype=float)
    with pytest.raises(ModelError, match="odometry stamps"):
        smoothed_trajectory(t, u, [0.5, 3.0], u[:2])
    with pytest.raises(ModelError, match="matching"):
        smoothed_trajectory(t, u, [0.0], u[:2])
