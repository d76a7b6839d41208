"""The agent's local SLAM (Cartographer's local trajectory builder, seed 002 §1.1).

Per scan: preprocess (range limits, NaN/inf dropped, IMU roll/pitch
projection, voxel filters), predict the pose from odometry, match the scan
against the older active submap (refinement on the smoothed grid from the
prediction; optionally a real-time correlative search first), and, when the
motion filter agrees (a local keyframe every 0.25 s), insert it into both active
submaps. Height comes from the altimeter.
No loop closing: this is the smooth, drifting `odom` pose the drone flies on.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from agent.correlative_matcher import RealTimeCorrelativeMatcher
from agent.grid_refiner import CeresLikeRefiner
from agent.motion_filter import MotionFilter
from agent.pose_extrapolator import PoseExtrapolator
from agent.scan_matcher import MatchResult, ScanMatcher
from agent.scan_preprocessor import PreparedScan, ScanPreprocessor
from agent.submaps import ActiveSubmaps, Submap
from common.config import LocalSlamConfig
from common.geometry import (
    quat_to_rpy,
    se2_compose,
    se2_inverse,
    se2_rotate_covariance,
    wrap_angle,
)
from common.logging_setup import worth_logging
from common.stamps import JumpGate
from protocol import LaserScan

log = logging.getLogger(__name__)

MAX_SPEED_MPS = 50.0  # m/s: no drone flown with this goes faster (odometry sanity check)
JUMP_SLACK_M = 5.0  # m
SUSPECT_TURN_RAD = math.radians(10.0)  # one scan's odometry turn checked against the scan
SUSPECT_STEP_M = 1.0  # m, the same for its step
# ... and taken only when it matches well too: a 5 Hz laser's fast real turns on
# MIT-CSAIL score 0.37-0.42 either way, and 24 of them had been refused for good
RESET_MIN_SCORE = 0.55
# ... and beats the odometry's match by this much: simulated resets win by 0.46-0.59
# (0.80 against 0.21-0.34); a real MIT-CSAIL turn, once the walls ahead were no longer
# eroded (grazing_keep_cells), scored 0.553 against 0.517 and was refused at 0.02
RESET_MIN_GAIN = 0.1


@dataclass
class LocalSlamResult:
    stamp: float
    pose: np.ndarray  # T_odom_base [x, y, z, yaw]
    covariance: np.ndarray  # 3x3 [x, y, yaw] of the match, odom frame (m, rad)
    score: float  # mean cell probability of the matched points (nan: not matched)
    matched: bool
    inserted: bool
    num_points: int


class LocalTrajectoryBuilder:
    def __init__(self, cfg: LocalSlamConfig, local_keyframe_period_s: float = 0.25) -> None:
        self.cfg = cfg
        self.preprocessor = ScanPreprocessor(cfg)
        self.extrapolator = PoseExtrapolator(cfg.use_odometry)
        self.motion_filter = MotionFilter(
            local_keyframe_period_s,
            cfg.motion_filter_min_distance_m,
            math.radians(cfg.motion_filter_min_angle_deg),
            cfg.motion_filter_max_time_s,
        )
        self.submaps = ActiveSubmaps(
            cfg.resolution_m,
            cfg.scans_per_submap,
            p_hit=cfg.p_hit,
            p_miss=cfg.p_miss,
            max_finished_submaps=cfg.max_finished_submaps,
            grazing_keep_cells=cfg.grazing_keep_cells,
        )
        self.matcher = ScanMatcher(
            RealTimeCorrelativeMatcher(
                linear_window=cfg.linear_search_window_m,
                angular_window=math.radians(cfg.angular_search_window_deg),
            ),
            CeresLikeRefiner(
                translation_weight=cfg.translation_weight, rotation_weight=cfg.rotation_weight
            ),
            use_correlative=cfg.use_correlative,
            min_num_points=cfg.min_num_points,
        )
        self.roll = 0.0
        self.pitch = 0.0
        self.altitude: float | None = None
        self.last_stamp: float | None = None
        self.pose = np.zeros(4)  # latest T_odom_base [x, y, z, yaw]
        self.scans = 0
        self.matched = 0
        self.rejected_scans = 0
        self.few_point_scans = 0  # gone on with the odometry's prediction (min_num_points)
        self.jumped_scans = 0  # of them: the odometry jumped farther than a drone flies
        self._jump = JumpGate()  # a stamp far ahead of the last (`common.stamps`)
        self.odometry_resets = 0  # odometry steps the scan refused (matched from the last pose)
        self.gated_matches = 0  # matches that turned too far from the prediction
        self.distance_m = 0.0

    def resume(self, stamp: float, pose: np.ndarray, odometry: np.ndarray | None) -> None:
        """Go on from an agent before this one (agent/resume.py): its last keyframe at
        `stamp` was at `pose` [x, y, z, yaw], the odometry source then at `odometry`
        [x, y, yaw] (None: none); the next scans are predicted from there by the odometry
        since (one far off, the source's frame reset too, is dropped as a jump)."""
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self.last_stamp = stamp
        self.extrapolator.add_pose(stamp, self.pose[[0, 1, 3]])
        if odometry is not None:
            self.extrapolator.add_odometry(stamp, np.asarray(odometry, dtype=np.float64))

    def odometry_at(self, stamp: float) -> np.ndarray | None:
        """The odometry source's pose [x, y, yaw] at `stamp` (None: no odometry)."""
        return self.extrapolator.odometry_at(stamp)

    # --- other sensors ------------------------------------------------------------------
    def add_odometry(self, stamp: float, pose_xyyaw: np.ndarray) -> None:
        self.extrapolator.add_odometry(stamp, pose_xyyaw)

    @property
    def rejected_odometry(self) -> int:
        """Odometry messages dropped because their stamp went back."""
        return self.extrapolator.rejected_odometry

    def add_imu(self, stamp: float, orientation_xyzw: np.ndarray) -> None:
        if self.cfg.use_imu_attitude:
            self.roll, self.pitch, _ = quat_to_rpy(orientation_xyzw)

    def add_altitude(self, stamp: float, altitude_m: float) -> None:
        self.altitude = float(altitude_m)
        self.pose[2] = self.altitude

    def _gated(self, m: MatchResult, submap: Submap, predicted: np.ndarray) -> bool:
        """A match that turns the pose further from the odometry's prediction than
        `max_match_yaw_jump_deg` in one scan: the refiner slid into a wrong minimum (a
        drone spinning on the spot in random:1 jumped 28.6 deg in one scan and mapped a
        room turned by that much). The prediction is used instead."""
        limit = math.radians(self.cfg.max_match_yaw_jump_deg)
        jump = abs(float(wrap_angle(submap.to_local(m.pose)[2] - predicted[2])))
        if limit <= 0.0 or jump <= limit:
            return False
        self.gated_matches += 1
        log.warning(
            "scan match turned %.1f deg from the odometry's prediction (> %.1f): not used",
            math.degrees(jump),
            self.cfg.max_match_yaw_jump_deg,
        )
        return True

    def keyframe_ranges(self, scan: LaserScan) -> np.ndarray:
        """The scan's readings for a keyframe: the floor's left out (no reading)."""
        return self.preprocessor.level_ranges(scan.angle_min, scan.angle_increment,
                                              scan.range_max, scan.ranges, self.roll,
                                              self.pitch, self.altitude)  # fmt: skip

    def _refuse_odometry_reset(
        self,
        m: MatchResult,
        predicted: np.ndarray,
        submap: Submap,
        prep: PreparedScan,
        stamp: float,
    ) -> tuple[MatchResult, np.ndarray]:
        """An odometry that turned or moved a lot in one scan (an EKF's heading reset, a
        VIO relocalisation: under the jump check, it had gone into the pose for good):
        the scan is matched from the last pose too, and the better match wins; the
        odometry before is then forgotten. (match, prediction) to go on with."""
        last = self.pose[[0, 1, 3]]
        step = se2_compose(se2_inverse(last), predicted)
        if not self.scans or (
            abs(step[2]) <= SUSPECT_TURN_RAD and np.hypot(*step[:2]) <= SUSPECT_STEP_M
        ):
            return m, predicted
        alt = self.matcher.match(submap.grid, prep.match_points, submap.to_submap(last))
        if not alt.score > max(m.score + RESET_MIN_GAIN, RESET_MIN_SCORE):
            return m, predicted
        self.odometry_resets += 1
        log.warning("scan at %.3f: the odometry's step (%.2f m, %.1f deg) does not fit the "
                    "scan: matched from the last pose, the odometry before forgotten", stamp,
                    np.hypot(*step[:2]), math.degrees(step[2]))  # fmt: skip
        self.extrapolator.forget_odometry()
        return alt, last

    def _jumped(self, predicted: np.ndarray, stamp: float) -> bool:
        """Whether the odometry put the drone farther from its last pose than it can fly
        since (`MAX_SPEED_MPS`, plus `JUMP_SLACK_M`): a reset or a corrupt source. The
        scan is dropped, not mapped (an offset of 1e7 m once made a submap grow to
        petabytes, and the agent died with its unsent keyframes), and the odometry
        before the jump is forgotten: the next scans follow the odometry from there."""
        if self.last_stamp is None:
            return False
        far = float(np.hypot(*(predicted[:2] - self.pose[:2])))
        if far <= JUMP_SLACK_M + MAX_SPEED_MPS * (stamp - self.last_stamp):
            return False
        if self.jumped_scans % 400 == 0:  # ~10 s of scans at 40 Hz between two lines
            log.error(
                "odometry puts the drone %.3g m from its pose %.3f s before: scan dropped "
                "(%d so far)", far, stamp - self.last_stamp, self.jumped_scans + 1,
            )  # fmt: skip
        self.jumped_scans += 1
        self.extrapolator.forget_odometry()
        return True

    # --- scans --------------------------------------------------------------------------
    def add_scan(self, scan: LaserScan) -> LocalSlamResult | None:
        """Process one scan; None if it was rejected (time going back, an odometry jump).
        One with too few usable points is not matched or mapped: the pose goes on with
        the odometry's prediction (it had stood still while the drone flew on)."""
        if self._jump.holds(scan.stamp, self.last_stamp):
            log.error("scan stamp %.3f is far past the previous %.3f: dropped unless the "
                      "next scan follows it", scan.stamp, self.last_stamp)  # fmt: skip
            self.rejected_scans += 1
            return None
        if self.last_stamp is not None and scan.stamp <= self.last_stamp:
            if worth_logging(self.rejected_scans):
                log.error("scan stamp %.3f is not after the previous %.3f: dropped (%d so "
                          "far)", scan.stamp, self.last_stamp, self.rejected_scans + 1)  # fmt: skip
            self.rejected_scans += 1
            return None
        prep = self.preprocessor.prepare(
            scan.angle_min,
            scan.angle_increment,
            scan.range_max,
            scan.ranges,
            self.roll,
            self.pitch,
            self.altitude,
            scan.range_min,
        )
        few = len(prep.points) < self.cfg.min_num_points  # (a dropout, open space, fog)
        if few and self.few_point_scans % 400 == 0:  # ~10 s of scans at 40 Hz a line
            log.warning("scan at %.3f has %d usable points (< %d): the pose goes on with the "
                        "odometry's prediction, the scan is not matched or mapped (%d so "
                        "far)", scan.stamp, len(prep.points), self.cfg.min_num_points,
                        self.few_point_scans + 1)  # fmt: skip
        self.few_point_scans += few
        predicted = self.extrapolator.predict(scan.stamp)
        if self._jumped(predicted, scan.stamp):
            self.rejected_scans += 1
            return None
        self.last_stamp = scan.stamp
        pose2, cov, score, matched = predicted, np.diag([0.1, 0.1, 0.05]) ** 2, math.nan, False
        submap = None if few else self.submaps.matching_submap()
        if submap is not None:
            m = self.matcher.match(submap.grid, prep.match_points, submap.to_submap(predicted))
            m, predicted = self._refuse_odometry_reset(m, predicted, submap, prep, scan.stamp)
            # LM never accepts a step that raises the cost, so a refinement that ran out
            # of iterations (slow convergence along a corridor: ~4 % of the Intel scans)
            # is still at least as good as its start: use it rather than the odometry
            # prediction. Only a failed correlative search (no candidate) or a poor
            # final score falls back to the prediction.
            found = m.converged or not (
                self.cfg.use_correlative and math.isnan(m.correlative_score)
            )
            good = found and m.score >= self.cfg.min_match_score
            if good and not self._gated(m, submap, predicted):
                pose2, score, matched = submap.to_local(m.pose), m.score, True
                cov = se2_rotate_covariance(m.covariance, submap.T_local_submap[2])
                self.matched += 1
            else:
                log.debug(
                    "scan at %.3f not matched (score %.2f): using the prediction",
                    scan.stamp,
                    m.score,
                )
        step = se2_compose(se2_inverse(self.pose[[0, 1, 3]]), pose2)
        if self.scans:
            self.distance_m += float(np.hypot(step[0], step[1]))
        self.extrapolator.add_pose(scan.stamp, pose2)
        inserted = not few and self.motion_filter.accept(scan.stamp, pose2)
        if inserted:
            self.submaps.insert(pose2, prep.points, prep.miss_points)
        self.scans += 1
        self.pose = np.array([pose2[0], pose2[1], self.pose[2], float(wrap_angle(pose2[2]))])
        return LocalSlamResult(
            scan.stamp, self.pose.copy(), cov, score, matched, inserted, len(prep.match_points)
        )
