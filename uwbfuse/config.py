# SPDX-License-Identifier: BSD-3-Clause
"""Typed configuration: the contract's TOML file parsed into pydantic models.

Precedence: defaults < TOML file < command-line options. Unknown keys are errors that name
the key (`extra="forbid"`). Every field documents its unit in its description;
`uwbfuse dump-config` prints the defaults with those descriptions as comments.
"""

from __future__ import annotations

import math
import tomllib
import types
from enum import Enum, StrEnum
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from uwbfuse.errors import ConfigError

# |x| of any number in the config, SI units: larger is a typo or a value whose square
# overflows; a positive quantity (sigma, rate, time) smaller but not 0 is a typo or an
# infinite weight (a sigma of 1e-320). Signed coordinates and quaternion components may be
# tiny (cos(pi / 2) is 6e-17 in float64).
MIN_MAGNITUDE = 1e-12
MAX_MAGNITUDE = 1e9


def _check_plain(v: Any, ann: Any, positive: bool = False) -> None:
    """Raise ValueError where pydantic's lax mode would coerce (true -> 1.0, "0.5" -> 0.5,
    1 -> true) or where a number is above MAX_MAGNITUDE or, for a `positive` quantity,
    non-zero below MIN_MAGNITUDE."""
    origin, args = get_origin(ann), get_args(ann)
    if origin in (Union, types.UnionType):
        errors = []
        for a in args:
            try:
                _check_plain(v, a, positive)
                return
            except ValueError as e:
                errors.append(str(e))
        raise ValueError(" or ".join(errors))
    if origin is Literal:
        if v not in args:
            raise ValueError(f"expected one of {', '.join(map(repr, args))}")
        return
    if origin in (tuple, list) and isinstance(v, (list, tuple)):
        items = args if origin is tuple and Ellipsis not in args else args[:1] * len(v)
        for x, a in zip(v, items, strict=False):
            _check_plain(x, a, positive)
        return
    if origin is dict and isinstance(v, dict) and len(args) == 2:
        for x in v.values():
            _check_plain(x, args[1], positive)
        return
    if ann in (float, int):
        if isinstance(v, (bool, str)):
            got = "a boolean" if isinstance(v, bool) else "text"
            raise ValueError(f"expected a number, got {got}")
        if isinstance(v, (int, float)) and math.isfinite(v) and (
                abs(v) > MAX_MAGNITUDE or (positive and v != 0 and abs(v) < MIN_MAGNITUDE)):
            raise ValueError(f"{v!r} is beyond the magnitudes a setting may have "
                             f"({MIN_MAGNITUDE:g} to {MAX_MAGNITUDE:g})")
    elif ann is bool and not isinstance(v, bool):
        raise ValueError("expected a boolean (true or false)")
    elif ann is str and not isinstance(v, str):
        raise ValueError("expected text")
    elif isinstance(ann, type) and issubclass(ann, Enum) and not isinstance(v, (str, Enum)):
        raise ValueError("expected text")


class _Section(BaseModel):
    # allow_inf_nan: inf and nan (TOML has both) are never a valid setting
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_coercion(cls, v: Any, info: ValidationInfo) -> Any:
        if info.field_name is not None:
            field = cls.model_fields[info.field_name]
            positive = any((getattr(m, "gt", None) is not None and m.gt >= 0)
                           or (getattr(m, "ge", None) is not None and m.ge >= 0)
                           for m in field.metadata)
            _check_plain(v, field.annotation, positive)
        return v


class RobustKernel(StrEnum):
    """Robust loss for UWB range residuals."""

    HUBER = "huber"
    CAUCHY = "cauchy"
    TUKEY = "tukey"
    DCS = "dcs"
    GEMAN_MCCLURE = "geman_mcclure"
    NONE = "none"


# whitened units: each kernel's threshold at 95 % asymptotic efficiency under Gaussian noise,
# the textbook tuning (Huber 1.345, Cauchy 2.385, Tukey 4.685; DCS's is on the squared
# residual, GTSAM's Phi); Huber's 1.345 under Tukey keeps 21 % efficiency and loses lock
KERNEL_THRESHOLD_95 = {
    RobustKernel.HUBER: 1.345,
    RobustKernel.CAUCHY: 2.3849,
    RobustKernel.TUKEY: 4.6851,
    RobustKernel.DCS: 3.6035,
    RobustKernel.GEMAN_MCCLURE: 3.7874,
    RobustKernel.NONE: 1.345,  # read by nothing: no kernel
}


class Extrinsics(_Section):
    tag_in_base: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="UWB antenna position in the base frame, metres; "
        "a log with neither IMU, wheels nor poses measures no heading, so the graph and its "
        "start apply the height only (the base is reported at the tag); wls turns the "
        "horizontal part by the track direction"
    )
    imu_in_base: tuple[float, float, float, float, float, float, float] = Field(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        description="IMU pose in the base frame: x y z (m) qx qy qz qw",
    )
    lidar_map_in_map: tuple[float, float, float, float, float, float, float] = Field(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0),
        description="pose of the frame of the external poses ([topics] pose, e.g. a LiDAR "
        "localiser's map) in the map frame: x y z (m) qx qy qz qw",
    )


class Topics(_Section):
    imu: str = Field("/imu", description="sensor_msgs/msg/Imu topic")
    wheel_odom: str = Field(
        "/wheel_odom", description="nav_msgs/msg/Odometry or sensor_msgs/msg/JointState topic"
    )
    uwb: str = Field("/uwb/range", description="UWB range topic")
    pose: str = Field(
        "/localization/pose", description="external pose topic (optional; a LiDAR or "
        "scan-matching localiser): geometry_msgs/msg/PoseWithCovarianceStamped or PoseStamped")
    ground_truth: str = Field("/ground_truth", description="ground-truth pose topic (eval only)")


class UwbConfig(_Section):
    anchor_field: str = Field(
        "anchor_id", description="dotted path to the anchor id (types other than Range)"
    )
    range_field: str = Field("range", description="dotted path to the range in metres")
    array_field: str = Field("", description="array of ranges in one message ('' = none)")
    valid_field: str = Field("", description="boolean/integer validity flag ('' = none)")
    rssi_field: str = Field(
        "", description="optional received (total) power, dBm: dotted path (inside each "
        "element with array_field; '' = none, or the log's uwb_fields metadata)")
    first_path_power_field: str = Field(
        "", description="optional first-path power, dBm: dotted path as rssi_field ('' = "
        "none, or the log's uwb_fields metadata)")
    range_offset: dict[str, float] = Field(
        default_factory=dict, description="per-anchor offset subtracted from ranges, metres"
    )
    min_range: float = Field(
        0.0, description="ranges below this are dropped, metres (ranges <= 0 always are: many "
        "UWB drivers report 0 for a failed exchange)")
    max_range: float = Field(200.0, description="ranges above this are dropped, metres")
    sigma: float = Field(0.10, gt=0, description="range noise std for LOS ranges, metres")
    robust_kernel: RobustKernel = Field(
        RobustKernel.HUBER, description="huber | cauchy | tukey | dcs | geman_mcclure | none"
    )
    kernel_threshold: float = Field(
        1.345, gt=0, description="robust-kernel threshold, in sigmas (DCS: on the squared "
        "whitened residual); unset, the kernel's 95 %-efficiency value (huber 1.345, cauchy "
        "2.3849, tukey 4.6851, dcs 3.6035, geman_mcclure 3.7874): drop this line when "
        "changing the kernel"
    )

    @model_validator(mode="before")
    @classmethod
    def _kernel_threshold_default(cls, data: Any) -> Any:
        """An unset `kernel_threshold` follows `robust_kernel` (KERNEL_THRESHOLD_95)."""
        if isinstance(data, dict) and "kernel_threshold" not in data:
            try:
                kernel = RobustKernel(data.get("robust_kernel", RobustKernel.HUBER))
            except (TypeError, ValueError):
                return data  # the field's own validation names the bad kernel
            return {**data, "kernel_threshold": KERNEL_THRESHOLD_95[kernel]}
        return data


class WheelConfig(_Section):
    radius: float = Field(0.1, gt=0, description="wheel radius for JointState input, metres")
    track_width: float = Field(0.5, gt=0, description="left-right wheel distance, metres")
    left_joint: str = Field("left_wheel_joint", description="JointState name of the left wheel")
    right_joint: str = Field(
        "right_wheel_joint", description="JointState name of the right wheel"
    )
    sigma_v: float = Field(0.05, gt=0, description="forward-speed noise per sample, m/s")
    sigma_omega: float = Field(0.05, gt=0, description="yaw-rate noise per sample, rad/s")
    sigma_lateral: float = Field(
        0.02, gt=0, description="non-holonomic lateral-speed noise, m/s"
    )


class ImuConfig(_Section):
    gravity: float = Field(9.81, gt=0, description="gravity magnitude, m/s^2")
    accel_noise_density: float = Field(
        4.0e-3, gt=0, description="accelerometer white noise, m/s^2/sqrt(Hz)"
    )
    gyro_noise_density: float = Field(
        3.0e-4, gt=0, description="gyroscope white noise, rad/s/sqrt(Hz)"
    )
    accel_bias_random_walk: float = Field(
        5.0e-4, gt=0, description="accelerometer bias random walk, m/s^3/sqrt(Hz)"
    )
    gyro_bias_random_walk: float = Field(
        2.0e-5, gt=0, description="gyroscope bias random walk, rad/s^2/sqrt(Hz)"
    )
    accel_bias_sigma: float = Field(
        0.2, gt=0, description="prior std of the initial accelerometer bias, m/s^2"
    )
    gyro_bias_sigma: float = Field(
        0.02, gt=0, description="prior std of the initial gyroscope bias, rad/s"
    )


class InitConfig(_Section):
    standstill_window: float = Field(
        0.5, gt=0, description="minimum still time used for gravity/gyro bias, seconds"
    )
    standstill_gyro_max: float = Field(
        0.03, gt=0, description="gyro norm below which the IMU counts as still, rad/s"
    )
    standstill_accel_std_max: float = Field(
        0.15, gt=0, description="accel std below which the IMU counts as still, m/s^2"
    )
    min_motion: float = Field(
        0.10, gt=0, description="wheel speed that counts as motion, m/s"
    )
    level_window: float = Field(
        1.0, gt=0, description="without a still start: accel averaged for roll/pitch, seconds"
    )
    min_displacement: float = Field(
        0.5, gt=0, description="UWB-track displacement needed before heading is solved, m"
    )
    max_yaw_sigma: float = Field(
        0.05, gt=0, description="UWB-only start (no IMU, no wheels): largest std of the "
        "heading read from the fixes' direction of travel, rad (the other starts report theirs)"
    )
    max_window: float = Field(
        12.0, gt=0, description="longest motion window used to solve the heading, seconds"
    )
    heading_timeout: float = Field(
        3.0, gt=0,
        description="UWB only: seconds of fixes after which a still tag starts, heading unknown",
    )
    base_height: float = Field(
        0.0, description="wheeled logs: expected z of the base origin (the floor), m; weak prior"
    )


class GraphConfig(_Section):
    keyframe_rate: float = Field(10.0, gt=0, description="keyframes per second, Hz")
    lag: float = Field(5.0, gt=0, description="fixed-lag window of the online smoother, s")
    motion_accel_density: float | Literal["auto"] = Field(
        "auto", description="logs with neither IMU nor wheels: white-noise acceleration "
        "of the constant-velocity motion prior between keyframes, m/s^2/sqrt(Hz); a number "
        "is used as given; auto = estimated from the log, 1/64 .. 16 times 1 (a walker or "
        "pushed trolley changes its speed by about 1 m/s within a second): batch and "
        "isam2-smoothed's final smoothing take the density of greatest Laplace evidence "
        "where a likelihood-ratio test rejects 1 (searched from the online one); the online "
        "graph starts at 1 and fits it over its newest keyframes as it fits the IMU noise"
    )
    motion_turn_density: float = Field(
        0.5, gt=0, allow_inf_nan=False,
        description="logs with neither IMU nor wheels: white-noise turn rate of that prior, "
        "rad/s/sqrt(Hz) (yaw only matters through the tag's lever arm; roll and pitch are "
        "held level); also the yaw rate an IMU dropout's still guess cannot see on a log with "
        "wheels (graph and filters)"
    )
    imu_noise_inflation: float | Literal["auto"] = Field(
        "auto", description="factor on the IMU noise densities and bias random walks in "
        "the preintegration: room for the unmodelled errors of consumer MEMS (scale, "
        "misalignment, vibration); a number is used as given (1 = trust the [imu] figures "
        "as they are); auto = estimated from the log: batch and isam2-smoothed's final "
        "smoothing take the factor of greatest Laplace evidence of the whole graph, 1 .. "
        "256 (loosen only), where a likelihood-ratio test rejects 1; the online graph "
        "starts at 256 with wheels (64 without: the IMU is then the only motion model) and, "
        "from 10 s of keyframes on, takes the loosest factor the same "
        "evidence over its last 30 s does not reject (again each time the graph's age has "
        "doubled); logs without ranges keep the [imu] figures"
    )
    update_every: int | Literal["auto"] = Field(
        "auto", description="keyframes per iSAM2 update (between updates the output is "
        "the odometry/IMU prediction from the newest solved keyframe): auto = 1 where an "
        "IMU without wheel odometry predicts (double integration drifts by centimetres over "
        "0.3 s), else 3"
    )
    start_backdate: float = Field(
        0.0, ge=0, description="logs with wheels or an IMU: the graph's first keyframe is "
        "set this many seconds before the start (the start state carried back along the "
        "wheel track, else its attitude by the gyro and its position from a UWB fix; no "
        "earlier than the first wheel sample and range), so that the ranges and odometry "
        "buffered while the start was found are in the graph from the first update; s, "
        "0 = at the start state's time. 10 helps sites with a clean start (simulated room: "
        "isam2 -27 %) and costs where the start is poor (three anchors or heavy NLOS: +6 to "
        "+16 %)"
    )
    planar: Literal["auto", "on", "off"] = Field(
        "auto", description="soft planar-motion constraint: auto = on when the log has wheels"
    )
    planar_sigma_z: float = Field(0.01, gt=0, description="planar constraint std on z, m")
    planar_sigma_tilt: float = Field(
        0.02, gt=0, description="planar constraint std on roll/pitch, rad"
    )
    estimate_range_bias: bool = Field(
        True, description="estimate a constant per-anchor range bias"
    )
    range_bias_sigma: float = Field(
        0.3, gt=0, description="prior std of the range bias common to all anchors, m"
    )
    range_bias_anchor_sigma: float = Field(
        0.05, gt=0, description="prior std of each anchor's range bias around the common "
        "one, m (batch's seeding pass; the online graph and batch's LM rounds that free the "
        "biases hold it within the smaller of this and 0.02 m, unless it is set above the "
        "default: anchors known to differ by more)"
    )
    @field_validator("update_every")
    @classmethod
    def _positive_count(cls, v: int | str) -> int | str:
        if not isinstance(v, str) and v < 1:
            raise ValueError(f"must be a positive integer or 'auto', got {v}")
        return v

    @field_validator("imu_noise_inflation", "motion_accel_density")
    @classmethod
    def _positive_inflation(cls, v: float | str) -> float | str:
        if not isinstance(v, str) and not (math.isfinite(v) and v > 0):
            raise ValueError(f"must be a positive number or 'auto', got {v}")
        return v

    estimate_range_scale: bool | Literal["auto"] = Field(
        "auto", description="also estimate a per-anchor range scale factor: auto = when the "
        "start solve (pose and one common scale from the first seconds) finds the ranges more "
        "than 2 % long or short (e.g. the Plaza radios' 7 %); true = always, false = never"
    )
    range_scale_sigma: float = Field(
        0.05, gt=0, description="prior std of range scale factors (1 = none)"
    )
    estimate_wheel_scale: bool = Field(
        True, description="calibrate the wheel odometry's speed and yaw-rate scale "
        "factors (wheel radius and track errors) against the smoothed track: batch over the "
        "whole log, the online graph recursively from the keyframes leaving its lag"
    )
    estimate_wheel_noise: bool = Field(
        True, description="batch: scale the wheel noise (translation and heading sigmas) "
        "by the factors of greatest Laplace evidence of the motion-fit graph"
    )
    nlos: bool = Field(True, description="model NLOS (positive range bias) on top of the kernel")
    em_iterations: int = Field(
        3, ge=0, description="batch: NLOS expectation-maximisation rounds (0 = none)"
    )
    range_model: Literal["auto", "mixture", "mixture, calibrated", "robust",
                         "robust, common scale"] = Field(
        "auto", description="range error model. mixture = LOS/NLOS mixture with "
        "per-anchor NLOS excess states (EM); mixture, calibrated = the same, EM run again "
        "with each anchor's LOS offset held at the one calibrated before and their spread "
        "from the log; robust = Huber around per-anchor offsets, the "
        "LOS sigma from the residuals (1.4826 MAD); robust, common scale = the same with "
        "one range scale for all anchors (batch, where scales are estimated); auto: batch "
        "fits each without a held-out eighth of the log's 2 s stretches and fits the one "
        "that predicts those ranges best (log score; the calibrated mixture by one "
        "standard error over the mixture) to the whole log; the online graph "
        "scores each new range under both before using it (prequential) and weights the "
        "ranges to come by the better model so far"
    )
    lm_max_iterations: int = Field(
        30, ge=1, description="batch: Levenberg-Marquardt iterations per round"
    )
    marginal_covariances: bool | Literal["auto"] = Field(
        "auto", description="pose covariances of isam2, isam2-smoothed and batch from the "
        "graph's marginals, and ekf's consider covariance (the trajectory's covariance, "
        "written by --cov-out and --mcap-out); auto = when an output asks for them (`run` "
        "with --cov-out or --mcap-out, `collisions`, the library's `pipeline.estimate`); "
        "false = skip them (saves one marginal per update online and the marginals of the "
        "final graph in batch) and report the graph's poses' covariance unknown, ekf's "
        "from its own P"
    )


class FilterConfig(_Section):
    imu_noise_inflation: float = Field(
        30.0, gt=0, description="factor on the [imu] noise densities and bias random walks in "
        "the EKF/UKF process noise: room for what a consumer MEMS does beyond its white noise "
        "(scale, misalignment, vibration, timing) between 0.1 s windows; too tight a process "
        "noise makes the filter overconfident, gate good ranges and diverge (ISAS-Walk1: "
        "ATE 0.6 m at 1, 0.18 m at 30); 1 = trust the [imu] figures as they are. The "
        "IMU-driven filters take it as the floor: they run x 1, sqrt 10 and 10 of it and "
        "answer with the level the log's innovations make most likely (`filters.noise_bank`)"
    )
    gate_probability: float = Field(
        0.999, gt=0, lt=1, description="chi-square innovation gate (0..1); 1 - p is rejected"
    )
    gating: bool = Field(True, description="reject ranges outside the innovation gate")


class UkfConfig(_Section):
    alpha: float = Field(1e-3, gt=0, description="sigma-point spread (scaled UKF)")
    beta: float = Field(2.0, description="prior-distribution parameter (2 for Gaussian)")
    kappa: float = Field(0.0, description="secondary scaling parameter")


class WlsConfig(_Section):
    window: float = Field(0.2, gt=0, description="epoch length for grouping ranges, seconds")
    weighted: bool = Field(True, description="NLOS-probability weights (Qiu eq. 10-11)")
    height_projection: Literal["auto", "on", "off"] = Field(
        "auto",
        description="2-D fix with anchor height projection: auto = on when the log has wheels",
    )
    tag_height: float | Literal["auto"] = Field(
        "auto", description="tag antenna height in the map frame for 2-D fixes, m (auto = estimate)"
    )
    nearest_three: bool = Field(False, description="use only the three nearest anchors")
    min_track: float = Field(
        0.3, gt=0, description="track length over which the heading (motion direction) is taken, m"
    )


class LkfConfig(_Section):
    accel_psd: float = Field(
        0.5, gt=0, description="white-acceleration spectral density of the constant-velocity "
        "model on the WLS fixes, m^2/s^3"
    )


class NlosConfig(_Section):
    """The LOS/NLOS range-error model (`uwbfuse.nlos.NlosModel`), read by the graph (online
    and batch), wls and the filters' range weighting. The LOS std is `[uwb] sigma`."""

    classifier: str = Field(
        "", description="optional NLOS classifier model file written by `uwbfuse "
        "train-nlos` ('' = none): its P(NLOS) per range is the graph's prior NLOS "
        "probability, the wls weights and the ekf/ukf range weighting")
    excess_mean: float = Field(
        0.3, gt=0, description="graph: prior mean of an anchor's NLOS excess over its LOS "
        "offset, metres (the mean its NLOS states revert to; the states follow the log); "
        "the online graph re-estimates it from the log, this an upper bound, batch keeps it")
    excess_slow_sigma: float = Field(
        0.13, gt=0, description="graph: std of the slowly varying NLOS excess of an anchor "
        "(the state), metres")
    excess_sigma: float = Field(
        0.07, gt=0, description="graph: std of the fast (per-range) part of the NLOS excess, "
        "metres; an upper bound, the log's EM estimates it")
    tau: float = Field(
        5.0, gt=0, description="correlation time of an anchor's NLOS excess, seconds (the "
        "graph's NLOS states, the filters' range-bias states)")
    segment: float = Field(
        1.0, gt=0, description="graph: time step of the per-anchor NLOS excess states, seconds")
    rate: float = Field(
        0.3, gt=0, lt=1, description="graph: prior fraction of NLOS ranges (EM-adapted)")
    switch: float = Field(
        0.05, gt=0, lt=1, description="the filters' prior probability that an anchor's "
        "LOS/NLOS state changes between two of its ranges (they re-estimate it per range from "
        "their posteriors; the graph's chain runs in time: switch_time)")
    switch_time: float = Field(
        2.0, gt=0, description="graph (online and batch): mean time between redraws of an "
        "anchor's LOS/NLOS state, seconds: two of its ranges dt apart are redrawn with "
        "probability 1 - exp(-dt / switch_time), so a state persists for a time whatever the "
        "radio's rate (2 s: the per-range 0.05 at 10 ranges per anchor per second)")
    range_los_std: float = Field(
        0.026, gt=0, description="per-range model (wls; the filters' EM prior): LOS range "
        "error std, metres (Qiu 2022, Table 2)")
    range_nlos_mean: float = Field(
        0.114, description="per-range model: NLOS range error mean (absolute: no anchor "
        "offset removed), metres (Qiu 2022)")
    range_nlos_std: float = Field(
        0.145, gt=0, description="per-range model: NLOS range error std (slow and fast parts "
        "together), metres (Qiu 2022)")
    range_nlos_prior: float = Field(
        0.2, ge=0, lt=1, description="per-range model: prior probability that a range is "
        "NLOS (0..1)")
    anchor: dict[str, tuple[float, float, float, float]] = Field(
        default_factory=dict,
        description="per-anchor per-range model [los_std, nlos_mean, nlos_std, nlos_prior] "
        "(m, m, m, 0..1) from calibrate-nlos; overrides the range_* values (wls)",
    )

    @field_validator("anchor")
    @classmethod
    def _per_anchor_model(
        cls, v: dict[str, tuple[float, float, float, float]]
    ) -> dict[str, tuple[float, float, float, float]]:
        """Each anchor's model as the range_* fields are bounded: positive stds (at least
        MIN_MAGNITUDE: a std of 1e-300 is an infinite weight), a prior in [0, 1)."""
        for a, (los_std, _mean, nlos_std, prior) in v.items():
            if not (los_std >= MIN_MAGNITUDE and nlos_std >= MIN_MAGNITUDE):
                raise ValueError(f"anchor {a!r}: los_std and nlos_std must be positive (m), "
                                 f"got {los_std:g} and {nlos_std:g}")
            if not 0.0 <= prior < 1.0:
                raise ValueError(f"anchor {a!r}: nlos_prior must be in [0, 1), got {prior:g}")
        return v


class PoseConfig(_Section):
    """External poses ([topics] pose): their noise and the robust kernel of their factor."""

    min_sigma_position: float = Field(
        0.02, gt=0, description="floor on the std of a PoseWithCovarianceStamped position, "
        "m (a localiser's stated covariance is often too small: a scan match is not "
        "better than the map it matches against)")
    min_sigma_rotation: float = Field(
        0.01, gt=0, description="floor on the std of its attitude (yaw; roll, pitch in "
        "3-D), rad")
    sigma_position: float = Field(
        0.05, gt=0, description="position std of a PoseStamped (no covariance) or of a "
        "message whose covariance is all zero (ROS: unknown), m")
    sigma_rotation: float = Field(
        0.02, gt=0, description="attitude std of such a message, rad")
    robust_kernel: RobustKernel = Field(
        RobustKernel.CAUCHY, description="robust loss of the graph's pose factor against "
        "a localiser's wrong matches: huber | cauchy | tukey | dcs | geman_mcclure | none")
    kernel_threshold: float = Field(
        4.0, gt=0, description="its threshold on the whitened pose residual (Mahalanobis "
        "norm), in sigmas (4: a pose that disagrees with the odometry by a wheel slip's "
        "few sigmas keeps most of its weight, a wrong match's metres almost none)")
    gate_probability: float = Field(
        0.999, gt=0, lt=1, description="ekf/ukf: chi-square gate on the pose innovation "
        "(0..1); poses outside it are rejected and counted")


class OutputConfig(_Section):
    rate: float = Field(10.0, gt=0, description="output poses per second for filters, Hz")


Point2 = tuple[float, float]


def check_polygon(name: str, vertices: list[Point2]) -> None:
    """Raise ValueError unless `vertices` (implicitly closed) bound a simple polygon."""
    from shapely import Polygon

    pts = list(vertices)
    if len(pts) > 1 and pts[0] == pts[-1]:
        pts = pts[:-1]  # written closed: the last vertex repeats the first
    if len(pts) < 3:
        raise ValueError(f"{name} is not a closed polygon: {len(pts)} distinct vertices, "
                         "needs >= 3")
    if not all(math.isfinite(c) for xy in pts for c in xy):
        raise ValueError(f"{name} has a non-finite vertex")
    poly = Polygon(pts)
    if not poly.convex_hull.area > 0:
        raise ValueError(f"{name} does not enclose an area (its vertices are on one line)")
    if not poly.exterior.is_simple:
        raise ValueError(f"{name} is self-intersecting (its edges cross or touch)")


class MapConfig(_Section):
    obstacles: list[list[Point2]] = Field(
        default_factory=list, description="obstacle polygons [[x, y], ...] (>= 3 vertices, "
        "not self-intersecting, closed implicitly), metres, map frame"
    )
    walls: list[list[Point2]] = Field(
        default_factory=list, description="walls as polylines [[x, y], ...] (>= 2 vertices, "
        "no thickness), metres, map frame"
    )
    boundary: list[Point2] = Field(
        default_factory=list, description="optional hall outline polygon the vehicles must "
        "stay inside ([] = none), metres, map frame"
    )

    @field_validator("obstacles")
    @classmethod
    def _simple_obstacles(cls, v: list[list[Point2]]) -> list[list[Point2]]:
        for i, poly in enumerate(v):
            check_polygon(f"obstacle {i}", poly)
        return v

    @field_validator("walls")
    @classmethod
    def _walls(cls, v: list[list[Point2]]) -> list[list[Point2]]:
        for i, line in enumerate(v):
            if len(line) < 2 or not all(math.isfinite(c) for xy in line for c in xy):
                raise ValueError(f"wall {i} needs >= 2 finite vertices")
        return v

    @field_validator("boundary")
    @classmethod
    def _boundary(cls, v: list[Point2]) -> list[Point2]:
        if v:
            check_polygon("boundary", v)
        return v


class VehicleConfig(_Section):
    length: float = Field(1.0, gt=0, description="footprint length along base x, m")
    width: float = Field(0.6, gt=0, description="footprint width along base y, m")
    footprint_center: tuple[float, float] = Field(
        (0.0, 0.0), description="footprint centre in the base frame (x, y), m"
    )
    control_delay: float = Field(
        0.5, ge=0, description="prediction horizon: the vehicle keeps its current velocity "
        "and turn rate this long, s"
    )
    safety_margin: float = Field(
        0.2, ge=0, description="clearance below which a warning is raised, m"
    )
    sigma_factor: float = Field(
        2.0, ge=0, description="the margin is widened by this many position std "
        "(largest xy std of the pose covariance, where one is known)"
    )
    position_sigma: float = Field(
        0.0, ge=0, description="position std assumed where no covariance is known, m "
        "(0 = no widening without a covariance)"
    )
    velocity_window: float = Field(
        0.5, gt=0, description="past trajectory window whose line fit gives the velocity "
        "and yaw rate (causal), s"
    )
    prediction_steps: int = Field(
        5, ge=1, description="time slots the horizon is split into (swept area and time "
        "to contact are resolved to control_delay / prediction_steps)"
    )


class Config(_Section):
    """The whole configuration. `anchors` may stay empty when the log carries them."""

    anchors: dict[str, tuple[float, float, float]] = Field(
        default_factory=dict, description="anchor id -> [x, y, z], metres, map frame"
    )
    extrinsics: Extrinsics = Field(default_factory=Extrinsics)
    topics: Topics = Field(default_factory=Topics)
    uwb: UwbConfig = Field(default_factory=UwbConfig)
    wheel: WheelConfig = Field(default_factory=WheelConfig)
    imu: ImuConfig = Field(default_factory=ImuConfig)
    init: InitConfig = Field(default_factory=InitConfig)
    graph: GraphConfig = Field(default_factory=GraphConfig)
    filter: FilterConfig = Field(default_factory=FilterConfig)  # ekf, ukf and lkf read it
    ukf: UkfConfig = Field(default_factory=UkfConfig)
    wls: WlsConfig = Field(default_factory=WlsConfig)
    lkf: LkfConfig = Field(default_factory=LkfConfig)
    pose: PoseConfig = Field(default_factory=PoseConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    nlos: NlosConfig = Field(default_factory=NlosConfig)
    map: MapConfig = Field(default_factory=MapConfig)
    vehicle: VehicleConfig = Field(default_factory=VehicleConfig)

    @field_validator("anchors")
    @classmethod
    def _finite_anchors(
        cls, v: dict[str, tuple[float, float, float]]
    ) -> dict[str, tuple[float, float, float]]:
        for k, xyz in v.items():
            if not all(math.isfinite(c) for c in xyz):
                raise ValueError(f"anchor {k!r} has a non-finite coordinate")
        return v


def _is_union_tag(part: object) -> bool:
    """Whether a pydantic error-location part names a union member, not a field."""
    return isinstance(part, str) and ("[" in part or part in {"bool", "int", "float", "str"})


def _known_keys(loc: tuple[Any, ...]) -> list[str]:
    """The keys allowed inside the table at `loc` (sections at the top level)."""
    model: type[BaseModel] = Config
    for part in loc:
        f = model.model_fields.get(str(part))
        ann = None if f is None else f.annotation
        if not (isinstance(ann, type) and issubclass(ann, BaseModel)):
            return []
        model = ann
    return list(model.model_fields)


def _format_validation_error(source: str, err: ValidationError) -> str:
    errors = err.errors()
    first = errors[0]
    loc = tuple(first["loc"])
    msg = first["msg"]
    # a union field (e.g. `bool | "auto"`) fails once per member, each loc ending in the
    # member's tag: name the field and list what each member wanted
    same = [e for e in errors if tuple(e["loc"])[:-1] == loc[:-1]
            and _is_union_tag(e["loc"][-1])]
    if len(loc) > 1 and len(same) > 1 and _is_union_tag(loc[-1]):
        loc = loc[:-1]
        msg = " or ".join(e["msg"] for e in same)
    key = ".".join(str(p) for p in loc)
    if first["type"] == "extra_forbidden":
        from uwbfuse.suggest import did_you_mean

        what = "section" if len(loc) == 1 else "key"
        return (f"{source}: unknown config {what} '{key}'"
                f"{did_you_mean(str(loc[-1]), _known_keys(loc[:-1]))}")
    return f"{source}: bad value for '{key}': {msg}"


# keys of earlier releases: (section, key or None for the whole section) -> new place
_RENAMED: dict[tuple[str, str | None], tuple[str, str | None]] = {
    ("ekf", None): ("filter", None),
    ("wls", "lkf_accel_psd"): ("lkf", "accel_psd"),
    # the two NLOS models of earlier releases, now one ([nlos], `uwbfuse.nlos`)
    ("graph", "nlos_mean"): ("nlos", "excess_mean"),
    ("graph", "nlos_slow_sigma"): ("nlos", "excess_slow_sigma"),
    ("graph", "nlos_sigma"): ("nlos", "excess_sigma"),
    ("graph", "nlos_tau"): ("nlos", "tau"),
    ("graph", "nlos_segment"): ("nlos", "segment"),
    ("graph", "nlos_rate"): ("nlos", "rate"),
    ("graph", "nlos_switch"): ("nlos", "switch"),
    ("wls", "los_std"): ("nlos", "range_los_std"),
    ("wls", "nlos_mean"): ("nlos", "range_nlos_mean"),
    ("wls", "nlos_std"): ("nlos", "range_nlos_std"),
    ("wls", "nlos_prior"): ("nlos", "range_nlos_prior"),
    ("wls", "anchor_nlos"): ("nlos", "anchor"),
}


def _renamed(data: dict[str, Any], source: str) -> dict[str, Any]:
    """`data` with the keys of earlier releases moved to their sections of today, each
    move logged once as a deprecation warning; a key given at both places is an error."""
    import logging

    out = dict(data)
    for (sec, key), (new_sec, new_key) in _RENAMED.items():
        if not isinstance(out.get(sec), dict):
            continue
        if key is None:
            moved = out.pop(sec)
        elif key in out[sec]:
            out[sec] = dict(out[sec])
            moved = {new_key: out[sec].pop(key)}
        else:
            continue
        target = dict(out.get(new_sec) or {})
        clash = sorted(set(target) & set(moved))
        if clash:
            raise ConfigError(f"{source}: [{new_sec}] {clash[0]} is given twice (also under its "
                              f"old name in [{sec}])")
        target.update(moved)
        out[new_sec] = target
        old = f"[{sec}]" if key is None else f"[{sec}] {key}"
        new = f"[{new_sec}]" if key is None else f"[{new_sec}] {new_key}"
        logging.getLogger(__name__).warning("%s: %s is now %s", source, old, new)
    return out


def config_from_dict(data: dict[str, Any], source: str = "config") -> Config:
    """Validate a nested dict (as TOML gives it) into a `Config`."""
    data = _renamed(data, source)
    try:
        return Config.model_validate(data)
    except ValidationError as e:
        raise ConfigError(_format_validation_error(source, e)) from None


def load_config(path: str | Path | None) -> Config:
    """Read the TOML file at `path` (None -> defaults). Raises ConfigError with the key."""
    if path is None:
        return Config()
    p = Path(path)
    try:
        with p.open("rb") as f:
            data = tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(f"{p}: config file not found") from None
    except IsADirectoryError:
        raise ConfigError(f"{p}: config path is a directory, expected a TOML file") from None
    except tomllib.TOMLDecodeError as e:
        raise ConfigError(f"{p}: not valid TOML: {e}") from None
    except UnicodeDecodeError as e:
        raise ConfigError(f"{p}: not a UTF-8 text file (byte {e.start}): not a TOML "
                          "config") from None
    except RecursionError:
        raise ConfigError(f"{p}: not valid TOML: nested too deeply") from None
    except OSError as e:  # a path through a file, no permission, ...
        raise ConfigError(f"{p}: cannot read config: {e.strerror or e}") from None
    return config_from_dict(data, str(p))


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, StrEnum):
        return f'"{v.value}"'
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return repr(v)


def dump_config(cfg: Config | None = None) -> str:
    """The config as TOML with each field's description (units) as a comment.

    Hand-written: the TOML writers on PyPI (tomli-w) cannot emit comments, and the comments
    are the point of `dump-config`.
    """
    cfg = cfg or Config()
    lines: list[str] = ["# uwbfuse configuration (units: SI, angles in radians)"]

    def emit_table(name: str, model: BaseModel) -> None:
        lines.append("")
        lines.append(f"[{name}]")
        subtables: list[tuple[str, dict[str, Any], str]] = []
        for fname, finfo in type(model).model_fields.items():
            value = getattr(model, fname)
            desc = finfo.description or ""
            if isinstance(value, dict):
                subtables.append((f"{name}.{fname}", value, desc))
                continue
            lines.append(f"{fname} = {_toml_value(value)}  # {desc}".rstrip(" #"))
        for sname, d, desc in subtables:
            lines.append("")
            lines.append(f"[{sname}]  # {desc}")
            lines.extend(f'"{k}" = {_toml_value(v)}' for k, v in d.items())

    lines.append("")
    lines.append(f"[anchors]  # {Config.model_fields['anchors'].description}")
    lines.extend(f'"{k}" = {_toml_value(list(v))}' for k, v in cfg.anchors.items())
    for fname in type(cfg).model_fields:
        if fname == "anchors":
            continue
        emit_table(fname, getattr(cfg, fname))
    return "\n".join(lines) + "\n"
