"""The relation-based SLAM metric of Kümmerle et al. 2009 ("On measuring the accuracy of
SLAM algorithms", Autonomous Robots 27(4)), as used for the published Intel / ACES numbers.

A relation file has one relation per line, `t1 t2 dx dy dz droll dpitch dyaw` (s, m, rad),
optionally prefixed with the token `REL`; '#' starts a comment. `(dx, dy, dyaw)` is the pose
at `t2` expressed in the frame of the pose at `t1` (checked against the intel / aces odometry:
short relations agree with `se2_between(odom(t1), odom(t2))` to ~2 cm, while the world-frame
difference is off by ~0.4 m). z, roll and pitch are ignored (they are zero in the 2-D files).

Error of one relation: `E = delta_ref^-1 * delta_est` (= delta_est ⊖ delta_ref), with
`delta_est = se2_between(x(t1), x(t2))`; translational error `|E.xy|` (m) and rotational
error `|wrap(E.yaw)|` (deg). Means and sample standard deviations (n - 1, as in
Cartographer's `compute_relations_metrics`) of these absolute errors are reported.

Cartographer's published Intel / ACES numbers come from its own tool, whose error is
`delta_est * delta_ref^-1` (compute_relations_metrics_main.cc: its translation is
`t_est - R(dyaw) t_ref`, which also counts a yaw error over the relation's length; its
own comment says so). The same rotational error; its translational mean is reported too
(`trans_err_cartographer_mean_m`): compare that one with Cartographer's numbers (on
Intel it is ~6 % above ours, on ACES ~1 %).

A relation stamp with no pose of its own in the trajectory is looked up (`poses_at`:
the nearest pose within 50 ms, else interpolated, as Cartographer's tool interpolates);
such relations are counted (`n_approximate`) and named in a warning: on Intel, whose
scans come in bursts 1.2 ms apart at places up to 0.87 m apart, scoring a trajectory of
keyframes only had reported 0.065 m where its full trajectory scores 0.016 m.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from common.errors import CollabSlamError, FileFormatError
from common.geometry import se2_between, se2_compose, se2_inverse, wrap_angle
from common.trajectory_io import Trajectory, read_tum

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class Relations:
    """Reference relative motions between pairs of timestamps."""

    t1: FloatArray  # (N,) s
    t2: FloatArray  # (N,) s
    delta: FloatArray  # (N, 3) [dx, dy, dyaw]: pose at t2 in the frame of the pose at t1

    def __len__(self) -> int:
        return len(self.t1)


@dataclass(frozen=True, eq=False)
class RelationErrors:
    """Scores of one trajectory against a relations file (NaN statistics if nothing scored)."""

    trans_err_mean_m: float
    trans_err_std_m: float
    rot_err_mean_deg: float
    rot_err_std_deg: float
    n_relations: int  # relations scored
    n_skipped: int  # relations with t1 or t2 outside the trajectory
    scored: NDArray[np.bool_]  # (len(relations),) which relations were scored
    trans_err_m: FloatArray  # (n_relations,) absolute translational errors, scored order
    rot_err_deg: FloatArray  # (n_relations,) absolute rotational errors
    trans_err_cartographer_mean_m: float = float("nan")  # by Cartographer's tool's formula
    trans_err_cartographer_std_m: float = float("nan")
    n_approximate: int = 0  # scored with t1 or t2 looked up, not at a pose's own stamp

    def as_dict(self) -> dict[str, float | int | None]:
        """JSON-able summary (NaN becomes None)."""
        out: dict[str, float | int | None] = {}
        for key in ("trans_err_mean_m", "trans_err_std_m", "rot_err_mean_deg", "rot_err_std_deg",
                    "trans_err_cartographer_mean_m", "trans_err_cartographer_std_m"):  # fmt: skip
            value = float(getattr(self, key))
            out[key] = None if np.isnan(value) else value
        out["n_relations"] = self.n_relations
        out["n_skipped"] = self.n_skipped
        out["n_approximate"] = self.n_approximate
        return out


def read_relations(path: str | Path) -> Relations:
    """Read a Kümmerle-style relations file (see the module docstring)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"{path}: cannot read relations: {exc}") from exc
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split("#", 1)[0].split()
        if not fields:
            continue
        if fields[0] == "REL":
            fields = fields[1:]
        if len(fields) != 8:
            raise FileFormatError(
                f"{path}:{lineno}: expected 8 values '[REL] t1 t2 dx dy dz droll dpitch dyaw', "
                f"got {len(fields)}: {raw!r}"
            )
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise FileFormatError(f"{path}:{lineno}: expected 8 numbers, got {raw!r}") from None
        if not all(np.isfinite(values)):
            raise FileFormatError(f"{path}:{lineno}: non-finite value in {raw!r}")
        rows.append(values)
    if not rows:
        raise FileFormatError(
            f"{path}: holds no relations ('[REL] t1 t2 dx dy dz droll dpitch dyaw')"
        )
    data = np.array(rows, dtype=np.float64).reshape(-1, 8)
    if np.any(data[:, 4:7] != 0.0):
        logger.warning("%s: non-zero dz / droll / dpitch ignored (2-D metric)", path)
    logger.debug("read %d relations from %s", len(data), path)
    return Relations(t1=data[:, 0].copy(), t2=data[:, 1].copy(), delta=data[:, [2, 3, 7]].copy())


def poses_at(
    traj: Trajectory, stamps: ArrayLike, max_dt: float = 0.05
) -> tuple[FloatArray, NDArray[np.bool_]]:
    """SE(2) poses of `traj` at `stamps` (s): the nearest pose if within `max_dt` (s), else
    linear interpolation (shortest-way yaw) between the two neighbours when the stamp lies
    inside the trajectory's span. Returns ((M, 3) poses, (M,) valid); invalid rows are NaN."""
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    out = np.full((len(t), 3), np.nan)
    valid = np.zeros(len(t), dtype=bool)
    s = traj.stamps
    if len(s) == 0:
        return out, valid
    poses = traj.poses_se2()
    hi = np.clip(np.searchsorted(s, t), 1, max(len(s) - 1, 1))
    lo = hi - 1
    if len(s) == 1:
        hi = lo = np.zeros(len(t), dtype=np.intp)
    nearest = np.where(np.abs(s[hi] - t) < np.abs(s[lo] - t), hi, lo)
    exact = np.abs(s[nearest] - t) <= max_dt
    out[exact] = poses[nearest[exact]]
    inside = ~exact & (t >= s[0]) & (t <= s[-1])
    if inside.any():
        a, b = lo[inside], hi[inside]
        span = s[b] - s[a]
        alpha = np.divide(t[inside] - s[a], span, out=np.zeros_like(span), where=span > 0)
        pa, pb = poses[a], poses[b]
        xy = pa[:, :2] + alpha[:, None] * (pb[:, :2] - pa[:, :2])
        yaw = wrap_angle(pa[:, 2] + alpha * wrap_angle(pb[:, 2] - pa[:, 2]))
        out[inside] = np.column_stack([xy, yaw])
    valid = exact | inside
    return out, valid


def relation_errors(delta_est: ArrayLike, delta_ref: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """(translational m, rotational deg) absolute errors of `delta_est ⊖ delta_ref`, (N,) each."""
    err = se2_compose(se2_inverse(delta_ref), delta_est)
    return np.hypot(err[..., 0], err[..., 1]), np.degrees(np.abs(wrap_angle(err[..., 2])))


def cartographer_trans_errors(delta_est: ArrayLike, delta_ref: ArrayLike) -> FloatArray:
    """Translational errors (m) as Cartographer's `compute_relations_metrics` has them:
    of `delta_est * delta_ref^-1`, (N,)."""
    err = se2_compose(delta_est, se2_inverse(delta_ref))
    return np.hypot(err[..., 0], err[..., 1])


def _at_own_pose(traj: Trajectory, stamps: FloatArray, tol_s: float = 1e-4) -> NDArray[np.bool_]:
    """Whether each stamp is one of the trajectory's own (to `tol_s`)."""
    s = traj.stamps
    if len(s) < 2:
        return np.abs(stamps - s[0]) <= tol_s if len(s) else np.zeros(len(stamps), dtype=bool)
    k = np.clip(np.searchsorted(s, stamps), 1, len(s) - 1)
    near = np.minimum(np.abs(s[k] - stamps), np.abs(s[k - 1] - stamps))
    return near <= tol_s


def score_relations(traj: Trajectory, rel: Relations, max_dt: float = 0.05) -> RelationErrors:
    """Score `traj` (any frame: the metric only uses relative motions) against `rel`.

    Relations whose t1 or t2 cannot be looked up (see `poses_at`) are skipped and counted.
    """
    p1, ok1 = poses_at(traj, rel.t1, max_dt)
    p2, ok2 = poses_at(traj, rel.t2, max_dt)
    scored = ok1 & ok2
    delta_est = se2_between(p1[scored], p2[scored])
    trans, rot = relation_errors(delta_est, rel.delta[scored])
    n = int(scored.sum())
    own = _at_own_pose(traj, rel.t1[scored]) & _at_own_pose(traj, rel.t2[scored])

    def stats(v: FloatArray) -> tuple[float, float]:
        if n == 0:
            return float("nan"), float("nan")
        return float(v.mean()), float(v.std(ddof=1)) if n > 1 else 0.0

    t_mean, t_std = stats(trans)
    r_mean, r_std = stats(rot)
    c_mean, c_std = stats(cartographer_trans_errors(delta_est, rel.delta[scored]))
    result = RelationErrors(
        trans_err_mean_m=t_mean,
        trans_err_std_m=t_std,
        rot_err_mean_deg=r_mean,
        rot_err_std_deg=r_std,
        n_relations=n,
        n_skipped=len(rel) - n,
        scored=scored,
        trans_err_m=trans,
        rot_err_deg=rot,
        trans_err_cartographer_mean_m=c_mean,
        trans_err_cartographer_std_m=c_std,
        n_approximate=int((~own).sum()),
    )
    if result.n_approximate:
        logger.warning("%d of %d relations scored at poses looked up near their stamps, not at "
                       "poses of their own (nearest within %.0f ms, or interpolated): their "
                       "errors include the lookup's", result.n_approximate, n,
                       1e3 * max_dt)  # fmt: skip
    if result.n_skipped:
        logger.info("skipped %d of %d relations outside the trajectory", result.n_skipped, len(rel))
    return result


def main_eval_relations(traj_path: str | Path, rel_path: str | Path) -> dict[str, Any]:
    """`collabslam eval relations TRAJ.tum RELATIONS`: the JSON-able scores.

    Raises CollabSlamError if no relation falls inside the trajectory.
    """
    traj = read_tum(traj_path)
    if len(traj) == 0:
        raise CollabSlamError(f"{traj_path}: holds no poses ('t x y z qx qy qz qw' lines)")
    rel = read_relations(rel_path)
    errors = score_relations(traj, rel)
    if errors.n_relations == 0:
        raise CollabSlamError(
            f"{traj_path}: none of the {len(rel)} relations of {rel_path} fall inside the "
            f"trajectory ({len(traj)} poses)"
        )
    return {"trajectory": str(traj_path), "relations": str(rel_path), **errors.as_dict()}
