"""`sim` of the configuration tree (common/config.py): the simulator's clock, its
sensors (laser, odometry, IMU, altimeter, GNSS) and its vehicles."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class LaserConfig:
    """Hokuyo UTM-30LX defaults (seed 002)."""

    beams: int = 1081
    fov_deg: float = 270.0  # deg
    range_min_m: float = 0.1  # m
    range_max_m: float = 30.0  # m
    rate_hz: float = 40.0  # Hz
    range_noise_std_m: float = 0.01  # m, Gaussian


@dataclass
class OdometryNoiseConfig:
    speed_noise_frac: float = 0.01  # fraction of speed, 1-sigma
    yaw_rate_noise_std: float = 0.002  # rad/s, 1-sigma white noise
    yaw_rate_bias: float = 0.0005  # rad/s, constant gyro-like bias


@dataclass
class ImuConfig:
    gyro_noise_std: float = 0.002  # rad/s
    gyro_bias: float = 0.0005  # rad/s
    accel_noise_std: float = 0.05  # m/s^2
    accel_bias: float = 0.02  # m/s^2


@dataclass
class AltimeterConfig:
    noise_std_m: float = 0.02  # m
    bias_m: float = 0.0  # m


@dataclass
class QuadrotorConfig:
    max_speed_mps: float = 1.0  # m/s
    max_accel_mps2: float = 1.0  # m/s^2
    max_vertical_speed_mps: float = 0.5  # m/s
    max_yaw_rate_rps: float = 1.0  # rad/s
    radius_m: float = 0.25  # m, collision disc
    altitude_m: float = 1.0  # m, cruise height above ground


@dataclass
class GnssConfig:
    """Simulated GNSS receiver (seed 000 §III): fixes in WGS84 with ENU sigmas (eq. 4)."""

    enabled: bool = False  # true: the simulator produces fixes (bench gps uses the model directly)
    rate_hz: float = 1.0  # Hz, fix rate
    sigma_east_m: float = 1.5  # m, nominal 1-sigma of the reported and true east error
    sigma_north_m: float = 1.5  # m, north
    sigma_up_m: float = 3.0  # m, up (GNSS altitude is worse than horizontal)
    # Log-normal spread of the per-fix sigmas around the nominal ones (0: constant); the
    # log factor is an AR(1) with this correlation time, so quality changes slowly.
    sigma_variation: float = 0.3
    sigma_correlation_s: float = 30.0  # s
    bias_east_m: float = 0.1  # m, constant error added to every fix
    bias_north_m: float = -0.1  # m
    bias_up_m: float = 0.5  # m
    vertical_drift_mps: float = 0.002  # m/s, slow drift of the up error (barometric-like)
    outage_rate_per_min: float = 0.5  # outages started per minute of fixes (Poisson)
    outage_duration_s: float = 10.0  # s without any fix per outage
    outlier_fraction: float = 0.0  # fraction of fixes with a multipath jump
    outlier_min_m: float = 5.0  # m, horizontal size of a multipath jump ...
    outlier_max_m: float = 20.0  # m ... uniform between min and max, random direction
    # WGS84 origin of a world whose map YAML has none (Zagreb, seed 000's test site).
    origin_lat_deg: float = 45.8118  # deg
    origin_lon_deg: float = 16.0106  # deg
    origin_alt_m: float = 160.0  # m above the WGS84 ellipsoid


@dataclass
class SimConfig:
    clock: str = "lockstep"  # lockstep | realtime (rate x real time)
    rate: float = 1.0  # sim seconds per wall second when clock = realtime
    seed: int = 0
    lockstep_timeout_s: float = 2.0  # s wall: re-publish a tick if an agent has not answered
    # Lock-step with exploration: every exploration.period_s of sim time the clock waits for
    # the base station's step (Config.base_sync_period_s); waits > basestation_timeout_s end.
    sync_basestation: bool = True
    basestation_timeout_s: float = 60.0  # s wall
    # At a handshake (the first at t = 0) the base station waits for every robot's command
    # of that stamp (its keyframes and state come before it), at most this long (wall).
    sync_wait_s: float = 10.0  # s wall
    start_timeout_s: float = 60.0  # s wall: wait this long for every agent to come alive
    tour_length_m: float = 80.0  # m, scripted tour per robot
    start_spacing_m: float = 1.5  # m between start positions
    start_apart: bool = False  # true: robots start far apart with random headings
    ground_truth_rate_hz: float = 10.0  # Hz, ground-truth samples written
    laser: LaserConfig = field(default_factory=LaserConfig)
    odometry: OdometryNoiseConfig = field(default_factory=OdometryNoiseConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    altimeter: AltimeterConfig = field(default_factory=AltimeterConfig)
    quadrotor: QuadrotorConfig = field(default_factory=QuadrotorConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
