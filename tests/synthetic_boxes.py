"""Synthetic rigid bodies shared by the refinement tests (tests/estimator/test_refine_sided.py,
tests/ops/test_rigid_lm.py): a box's four sides, sampled on a regular step, in its body frame,
and the same body after a planar rigid motion."""

from __future__ import annotations

import math

import numpy as np


def box_sides(length=4.5, width=1.8, height=1.5, step=0.15):
    """The four vertical sides of a box centred on the origin (z from 0.2 m), every ``step``."""
    xs = np.arange(-length / 2, length / 2 + 1e-6, step)
    ys = np.arange(-width / 2, width / 2 + 1e-6, step)
    zs = np.arange(0.2, height, step)
    faces = [np.stack(np.meshgrid(xs, [y], zs, indexing="ij"), -1).reshape(-1, 3) for y in (-width / 2, width / 2)]
    faces += [np.stack(np.meshgrid([x], ys, zs, indexing="ij"), -1).reshape(-1, 3) for x in (-length / 2, length / 2)]
    return np.concatenate(faces)


def posed(body, centre, yaw):
    """``body`` turned by ``yaw`` about z, then moved to ``centre``."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return body @ rot.T + np.asarray(centre, dtype=np.float64)
