"""Between-factor measurements of SE(2) poses: moved onto an anchor and fused.

The reduced pose graph (``basestation.pose_graph_reduction``) expresses an aliased
node through its anchor (node = anchor * offset) and fuses measurements between the
same two variables into one; these are the formulas, on (x, y, theta) arrays and
3 x 3 covariances in gtsam's tangent convention (error at the second pose).
"""

from __future__ import annotations

import gtsam
import numpy as np

from basestation.pose_graph_state import FloatArray, pose2
from common.geometry import se2_between, se2_compose, se2_inverse


def pose_array(p: gtsam.Pose2) -> FloatArray:
    return np.array([p.x(), p.y(), p.theta()])


def adjoint(T: FloatArray) -> FloatArray:
    return np.asarray(pose2(T).AdjointMap())


def noise_with(noise: gtsam.noiseModel.Base, cov: FloatArray) -> gtsam.noiseModel.Base:
    """``noise`` with its Gaussian part replaced by ``cov`` (robust kernels kept)."""
    gauss = gtsam.noiseModel.Gaussian.Covariance(0.5 * (cov + cov.T))
    if isinstance(noise, gtsam.noiseModel.Robust):
        return gtsam.noiseModel.Robust.Create(noise.robust(), gauss)
    return gauss


def covariance_of(noise: gtsam.noiseModel.Base) -> FloatArray:
    if isinstance(noise, gtsam.noiseModel.Robust):
        noise = noise.noise()
    return np.asarray(noise.covariance())


def moved_measurement(
    z: FloatArray, cov: FloatArray, side: int, offset: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """A between-factor measurement T_a_b (covariance at b) once end ``side`` (0: a,
    1: b) is expressed through its anchor, node = anchor * offset."""
    if side == 0:  # T_anchor_b = offset * z, error unchanged
        return se2_compose(offset, z), cov
    ad = adjoint(offset)  # T_a_anchor = z * offset^-1; error rotates by Ad(offset)
    return se2_compose(z, se2_inverse(offset)), ad @ cov @ ad.T


def fuse(
    z1: FloatArray, cov1: FloatArray, z2: FloatArray, cov2: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Two Gaussian measurements of the same T_a_b as one (tangent space at z1)."""
    info1, info2 = np.linalg.inv(cov1), np.linalg.inv(cov2)
    cov = np.linalg.inv(info1 + info2)
    xi = np.asarray(gtsam.Pose2.Logmap(pose2(se2_between(z1, z2))))
    step = cov @ info2 @ xi
    return se2_compose(z1, pose_array(gtsam.Pose2.Expmap(step))), 0.5 * (cov + cov.T)
