"""The estimator's constants: the tuning and physical constants of estimation that must stay
constants, in one module, grouped by what reads them.

Rule: each constant carries one comment line (two at most) with its unit and its physical
reason (sensor physics, geometry, or a numerical reason). Measured results (tables, "A -> B"
figures, what a value did on one log or scenario) do not live here: they are in
docs/results.md, section "Constants in one module (issue 13; 2026-12-05, session 18)", which
also lists the constants still chosen from results.

This module imports nothing from GTSAM and nothing from the rest of uwbfuse (so every layer
can read it). File formats (`uwbfuse.io`), simulator scenarios (`uwbfuse.sim`), plot
styling, CLI codes, safety/fleet settings and structural values (state layouts, feature and
model name tuples) stay in their modules.
"""

from __future__ import annotations

import math

import numpy as np

# ---------------------------------------------------------------------------------------
# Start: start solve from ranges and wheels (`positioning.start`, `positioning.sparse_start`)
# ---------------------------------------------------------------------------------------

# m: path length before a heading is attempted
MIN_TRAVEL_M = 2.0
# ranges a start solve needs: 6 per unknown (x, y, yaw, common offset, common scale), the
# redundancy of its robust (soft-L1) fit
START_MIN_RANGES = 30
# yaw seeds of the start solve, 45 deg apart (its cost is multimodal in yaw)
N_SEEDS = 8
# ranges a standstill fix needs: 3 unknowns (x, y, common scale) and 5 of redundancy for the
# robust fit, two per anchor at STATIC_MIN_ANCHORS
STATIC_MIN_RANGES = 8
# anchors a standstill fix needs: x, y and a common scale, plus one range of redundancy
STATIC_MIN_ANCHORS = 4
# ranges a standstill fix keeps (the newest) on a long standstill: bounds its work
STATIC_MAX_RANGES = 2000
# m/s: every wheel sample under this speed is standing still (above odometry noise at rest)
STATIC_MAX_SPEED = 0.05
# rad/s: ... and under this yaw rate (above odometry noise at rest)
STATIC_MAX_YAW_RATE = 0.05
# m: largest dead-reckoned drift of a standstill (its ranges are fitted as from one point):
# 3x the noisiest LOS range noise (0.1 m), within the ranges' spread; more is motion
STATIC_MAX_DRIFT_M = 0.3
# rad: ... and turn: 0.3 rad moves a tag 1 m off the turning centre by 0.3 m, the drift bound
STATIC_MAX_TURN_RAD = 0.3
# bound on a standstill fix's common range scale: a guard (clocks err by ppm, radios met read a
# few % long); beyond 15 % a fit on few anchors trades position for scale
STATIC_MAX_SCALE = 0.15
# range sigmas: prior std of the base height where the sparse start holds it on the floor
# (a wheeled base); an exact hold would drop the unknown, this keeps one model and a well
# conditioned solve (1e-3 sigma moves the height by under a millimetre)
HELD_HEIGHT_SIGMAS = 1e-3
# m: soft-L1 scale of the sparse start's solves: SOFT_L1_SIGMAS range sigmas of 0.1 m (UWB LOS)
SOFT_L1_M = 0.2
# m: largest common range offset of a sparse start: an antenna delay is decimetres; a minimum
# beyond is no start
START_MAX_OFFSET_M = 1.0
# largest common range scale error of a sparse start, as STATIC_MAX_SCALE
START_MAX_SCALE = STATIC_MAX_SCALE
# m: anchors spread this far off one plane (level or tilted) observe the tag's offset from
# it, and so its height, apart from a common range offset
HEIGHT_SPREAD_M = 1.0
# s of ranges before the wheel-track start: the initialiser needs fixes and 0.5 m of travel
# (1 s at 0.5 m/s), the solve MIN_TRAVEL_M (4 s); 5 s without a start = too sparse for fixes
FALLBACK_AFTER_S = 5.0
# s of data between two attempts (start solve, standstill fix): a work bound (N_SEEDS
# least-squares fits each); in a second an AGV adds ~0.5 m of track
FALLBACK_RETRY_S = 1.0
# ns: wheel data must reach this close to a standstill's ends
STATIC_WHEEL_GAP_NS = 500_000_000
# s of the newest ranges a start solve fits: keeps each attempt bounded on a log that never
# starts (every FALLBACK_RETRY_S over all ranges so far would grow quadratically)
START_WINDOW_S = 120.0
# s: longest wait between failed start solves (doubling): bounds the work of a log that never
# starts (wrong anchor map, say)
MAX_RETRY_S = 30.0

# Start from an external pose stream (`positioning.pose_start`)
# consecutive consistent poses the start needs
START_POSES = 3
# s: ... within this span (the localisers publish at 5-30 Hz)
START_SPAN_S = 1.0
# m/s: a faster step between two poses is a wrong match
POSE_START_MAX_SPEED = 3.0

# Start-solve range scale (`positioning.initialisation`)
# a start-solve range scale is applied only when it is this far from 1 (start solves find it
# to about 1-2 % at room size)
RANGE_SCALE_MIN_ERROR = 0.02
# m: ... and when it moves the ranges of the start position by this much (at the median anchor
# distance): below it the scale is within the start solve's noise
RANGE_SCALE_MIN_EFFECT_M = 0.5

# Fallback before a method's start (`prestart`)
# epochs the primary must answer in a row before the fallback is dropped (2 s at 10 Hz: past
# the start's first updates)
DROP_AFTER_EPOCHS = 20
# m: fallback fix to provisional fix distance that discredits the fallback: several times a
# LOS fix's error, below a biased fix's (a radio scale of 7 % at 15 m is 1 m)
DISAGREE_M = 1.0
# s: longest hold of the last provisional position in place of a discredited fallback (the
# time a walker needs for the couple of metres the start solve needs)
PROVISIONAL_GRACE_S = 5.0
# ns: the wheels say "still" only when their last sample is this recent (10 samples at 50 Hz)
STILL_WHEEL_GAP_NS = 200_000_000

# Backdated start of the graph methods (`graph.estimator`)
# s: the backdated start's UWB fix is taken this long after it (the initialiser's fixes over
# the last 0.5 s)
PROVISIONAL_FIX_S = 0.5
# rad: allowance for the gyro's drift over the carried-back seconds (a MEMS gyro bias of
# 0.01 rad/s unmodelled over 10 s)
BACKDATE_YAW_DRIFT = 0.1

# ---------------------------------------------------------------------------------------
# Wheels
# ---------------------------------------------------------------------------------------

# Huber threshold of the wheel factor (whitened, in sigmas): wheel slip is an outlier
WHEEL_HUBER_K = 1.345
# prior std of the speed and yaw-rate scale factors (1 = none): wheel radius and track width
# are off by 1-3 % ordinarily
WHEEL_SCALE_SIGMA = 0.05
# the farthest a scale factor may be from 1: 20 % is a wrong wheel radius or encoder count in
# the config, not wear, and beyond it the fit is chasing slip
WHEEL_SCALE_MAX_ERROR = 0.2
# relative scale change that rebuilds the wheel factors: 25 um on a keyframe's 5 cm (0.5 m/s,
# 0.1 s), far under its mm of noise; smaller is not worth the rebuild (work bound)
WHEEL_SCALE_MIN_CHANGE = 5e-4
# wheel sample periods: the farthest the batch time-offset search looks (a driver that
# buffers stamps its samples a few periods late; farther is a clock fault, not an offset)
WHEEL_OFFSET_MAX_PERIODS = 4.0

# Wheel-track reference of the NLOS classifier (`positioning.wheel_reference`)
# s: ranges in one fit. The wheel track's shape over 5 s (2.5 m at AGV speed) is good to a
# few cm (1 % scale error), and 5 s holds ~50 ranges per anchor at 40 Hz over four anchors
REFERENCE_WINDOW_S = 5.0
# ranges of the other anchors a fit needs (three unknowns, robust)
REFERENCE_MIN_RANGES = 8
# s: a track carried further on the last twist is a guess
MAX_WHEEL_GAP_S = 1.0
# m: RMS spread of the window's track points (about their mean) that makes heading
# observable: below it a rotation is a translation to within the range noise
MIN_SPREAD_M = 0.5
# below this share of ranges within 3 scales the fit has lost them
MIN_INLIER_SHARE = 0.3
# Gauss-Newton steps per fit (warm-started from the previous epoch)
REFERENCE_ITERATIONS = 8
# information (1/m^2, 1/m^2, 1/rad^2) on a fit's step from its warm start: keeps the yaw
# of a still window (no lever arm) where it was, and is nothing against ~100 ranges at 0.1 m
STEP_INFO = np.array([1e-6, 1e-6, 100.0])

# ---------------------------------------------------------------------------------------
# IMU
# ---------------------------------------------------------------------------------------

# Bias of the constant-velocity prior's virtual IMU (it has no sensor): random walk
# (m/s^3/sqrt(Hz), rad/s^2/sqrt(Hz)) small against any motion yet keeps 0.1 s factors conditioned
VIRTUAL_BIAS_RANDOM_WALK = 1e-4
# m/s^2, rad/s: prior std of that virtual bias, to match its random walk
VIRTUAL_BIAS_SIGMA = 1e-3
# log2 of the largest IMU noise inflation (256): there the default accelerometer density
# equals the constant-velocity prior's, so an IMU held looser says no more than no IMU
IMU_INFLATION_MAX_LOG2 = 8.0
# log2 of the online IMU noise inflation before its first fit where no wheels carry the
# motion (64): the loosest IMU measured on a real log (ISAS-Walk1's handheld IMU fits
# 67-73x); the maximum would leave the vehicle without a motion model until the fit
IMU_INFLATION_START_NO_WHEELS_LOG2 = 6.0
# s of graph age: with wheels, the gyroscope's white noise is held at its configured density
# from here until the first IMU noise fit (`GraphBuilder._hold_gyro`). Held earlier, a tight
# gyroscope with the start's first keyframes left iSAM2 indeterminate (room seed 0: from 0-1
# s; backdated by 10 s, from 3 s); 5 s: session 20's, where no start measured failed. Not the
# lag: at lag 10 the hold began with the first fit (10 s) (docs/results.md, session 40)
GYRO_HOLD_AGE_S = 5.0
# m/s^2/sqrt(Hz): the constant-velocity prior's acceleration density before the log tells
# it (`graph.motion_accel_density = "auto"`): a walker or pushed trolley changes its speed
# by about 1 m/s within a second
MOTION_ACCEL_DENSITY_START = 1.0
# log2 of the smallest factor on it the evidence may choose (1/64, 0.016 m/s^2/sqrt(Hz)): a
# speed that changes by 0.05 m/s in 10 s, a tag at rest as far as ranges at cm noise tell
MOTION_NOISE_MIN_LOG2 = -6.0
# log2 of the largest (16 m/s^2/sqrt(Hz)): 16 m/s of speed change within a second, no
# indoor vehicle or walker
MOTION_NOISE_MAX_LOG2 = 4.0

# Standstill detection of the filters' dead reckoning (`filters.dead_reckoning`)
# s: longest extrapolation past the last sample: 25 periods of 50 Hz wheels; an AGV's 0.3 m/s^2
# unmodelled over 0.5 s is 4 cm (UWB noise); a longer silence is a dropout
MAX_EXTRAPOLATION_S = 0.5
# m/s^2, rad/s^2: what an AGV's speed and turn rate may change by per second unseen, where
# the wheel track carries a twist through a dropout (0.3 m/s^2 above; a turn of 0.5 rad/s
# begun within a second): a 5 s dropout's factor then says little, as it should
WHEEL_GUESS_ACCEL = 0.3
WHEEL_GUESS_YAW_ACCEL = 0.5
# s: window of the motion test: 40 samples at 200 Hz for a std, short against an AGV's speed-up
# (0.5 m/s at 0.3 m/s^2 takes 1.7 s), so a start shows within a fraction of a second
MOTION_WINDOW_S = 0.2
# s: the still part ends this long before the first sample that shows motion: a jerk-limited
# start is detected late, and its samples in the still means would tilt the levelling
ONSET_GUARD_S = 1.0
# standard errors (of the still samples' noise) a window mean must move to show motion: a
# false alarm <= 6e-7 per window (chi-square 1 dof at 25), ~2e-4 per still minute
MEAN_SHIFT_SIGMAS = 5.0
# m/s^2: floor of that shift, 2 mg: what a consumer MEMS accelerometer's bias moves in a few
# degC of warm-up, or 2 mrad of tilt; far below a start's 0.1-1 m/s^2
MEAN_SHIFT_FLOOR = 0.02

# ---------------------------------------------------------------------------------------
# Ranges and NLOS model (`nlos`, `graph.uwb`, multilateration)
# ---------------------------------------------------------------------------------------

# m: floor of the LOS sigma of the state model's M-step: below it a fit is the one-step
# prediction's luck, not the radio (a DW1000 reads about 2 cm in LOS)
SIGMA_LOS_MIN = 0.02
# m: floor of the NLOS sigma alike
SIGMA_NLOS_MIN = 0.03
# m: floor on the per-range LOS std used for probabilities
MIN_LOS_STD = 0.005
# m: a fitted LOS std beyond this is no UWB radio's
MAX_LOS_STD = 1.0
# ns: residual jumps are taken only between consecutive ranges at most this far apart
JUMP_MAX_GAP_NS = 500_000_000
# m: a residual change beyond this is a gross outlier, not a jump
JUMP_MAX_M = 1.0
# log density (1/m): gross-outlier floor of each component's likelihood, 2 % spread over 20 m
LOG_OUTLIER = math.log(0.02 / 20.0)
# MAD -> standard deviation of a normal distribution (1 / Phi^-1(3/4))
NORMAL_MAD_SCALE = 1.482602218505602
# component weights below this add no factor: at 0.01 it has 10x its sigma, 1 % of a range's
# information; skipping it halves the factors of clear-cut ranges (work bound)
MIN_WEIGHT = 0.01
# m: prior std of the track shift in `los_subset_search`: misclassified ranges pull a track by
# about one NLOS excess ([nlos] excess_mean 0.3 m + excess_slow_sigma 0.13 m), not metres
SEARCH_SHIFT_SIGMA = 0.5
# m: least NLOS excess a `los_subset_search` hypothesis may need (below 0: room for LOS
# biases that have absorbed some NLOS)
EXCESS_FLOOR = -0.2
# `los_subset_search` solves 2^M subsets; with more anchors than this it is skipped (more
# hypotheses, more spurious winners; anchors switch class inside the window)
SEARCH_MAX_ANCHORS = 6
# m: anchors within this RMS of one line count as collinear (message only): the noisiest LOS
# range noise; closer, a 2-D fix and its mirror image differ by less than the ranges resolve
COLLINEAR_RMS_M = 0.1
# DOP above which a fix is degenerate: it errs by DOP x the range noise, 30 x (0.03-0.1 m) =
# 1-3 m, no better than knowing the room
MAX_DOP = 30.0
# m: anchors within this spread of one plane (level: of height) are coplanar (a 3-D fix then
# starts from a 2-D solve in the plane's frame, on the floor's side): 3x the noisiest LOS
# range noise (0.1 m); less leaves the 3-D linear solve's out-of-plane coordinate ill-posed
COPLANAR_SPREAD = 0.3

# ---------------------------------------------------------------------------------------
# Learned NLOS classifier (`positioning.nlos_classifier`)
# ---------------------------------------------------------------------------------------

# m: 3x the LOS ranging std of DW1000-class radios (about 5 cm): a larger error is not LOS
# noise but an excess path (NLOS) or a gross ranging fault, and either should be trusted less
LABEL_THRESHOLD_M = 0.15
# the simulator's laws of the NLOS excess range (`sim.nlos.nlos_excess`), the first the
# default; here so that the CLI lists them without importing the simulator
NLOS_EXCESS_LAWS = ("gaussian", "lognormal")
# s: an older fix says little where a vehicle is (1 m at 0.5 m/s)
MAX_REFERENCE_AGE_S = 2.0
# fixes in the reference's line fit: about 1 s of 0.1 s epochs
TRACK_FIXES = 8
# s: a range jump over a longer gap is motion, not a change of path
MAX_JUMP_GAP_S = 2.0
# nats: a forest's leaf frequencies of 0 or 1 are not certainty (its leaves hold a few
# ranges each); 5 nats is odds of 150:1
MAX_EVIDENCE_NATS = 5.0
# weight of the forest's log-odds: its residual features overlap the consumer's own residual,
# so they count half (a tempered likelihood) rather than twice in full
EVIDENCE_WEIGHT = 0.5
# ranges of one anchor in the running medians: NLOS lasts while an obstacle is in the way
# (5 ranges: 0.5 s at 40 Hz over four anchors)
HISTORY_RANGES = 5
# ranges of one anchor in the long running median: a shelf's delay lasts seconds, so about
# 2 s of one anchor's ranges (20 at 40 Hz over four anchors) average the LOS noise out
HISTORY_LONG = 20
# s: shortest epoch (four anchors at 40 Hz take 0.1 s)
MIN_EPOCH_WINDOW_S = 0.05

# ---------------------------------------------------------------------------------------
# Noise levels fitted from the log's evidence (`graph.noise_fit`)
# ---------------------------------------------------------------------------------------

# log2: factor-2 grid steps of the noise search: 4 (wheels, 1..16) or 8 (IMU, 1..256) per
# factor, one graph solve each (work bound); a parabola through three places the optimum
NOISE_STEP = 1.0
# log2: std of the log-normal hyperprior on each factor (the configured noise is right within
# a factor 4 at one sd): where the evidence is flat the factor stays near 1
NOISE_PRIOR_LOG2 = 2.0
# log2: wheel factors within 1 .. 16 of the configured sigmas: odometry 16x noisier than
# its configuration is no odometry
WHEEL_NOISE_MAX_LOG2 = 4.0
# nats: half the 5 % point of chi-square with 2 dof (2 wheel factors): a likelihood-ratio
# test, so a flat evidence keeps the configuration rather than a vertex placed by noise
WHEEL_NOISE_TEST_NATS = 0.5 * 5.991
# nats: the same test with 1 dof (1 IMU factor)
IMU_NOISE_TEST_NATS = 0.5 * 3.841
# s: first online IMU noise fit after this much of keyframes (~100 IMU factors and a few
# hundred ranges)
ONLINE_FIRST_S = 10.0
# s: the window an online fit looks at (bounds its work; noise levels do not change with time)
ONLINE_WINDOW_S = 30.0
# ranges batch's noise and time-offset fits look at (`graph.evidence_window`): the ranges
# tell the motion noise, and n of them fix a noise level to ~1/sqrt(2n) = 1 %, far finer
# than the fits' factor-2 grid
EVIDENCE_RANGES = 5000

# ---------------------------------------------------------------------------------------
# Batch EM (`graph.offline`)
# ---------------------------------------------------------------------------------------

# LM iterations of an intermediate EM round: only close enough for the next E-step
EM_ROUND_LM_ITERATIONS = 6
# Newton steps of the two-parameter logistic fit of the NLOS classifier's weight
CLASSIFIER_FIT_ITERATIONS = 25
# 1/nats^2: keeps that fit's Hessian invertible when the log-odds are constant
CLASSIFIER_FIT_RIDGE = 1e-6
# switch: E-step LOS/NLOS hypothesis search per stretch (`_search_windows`); tests turn it off
BATCH_SEARCH = True
# nats: a stretch takes another LOS/NLOS assignment when it explains the ranges by this much;
# chosen from simulated results, not derived (docs/results.md, "still chosen from results")
BATCH_SEARCH_NATS = 20.0
# s: stretch of the E-step search: the NLOS excess's correlation time ([nlos] tau), over which
# an anchor keeps its class, as the search assumes; ~50 ranges per anchor at 40 Hz over four
BATCH_SEARCH_WINDOW_S = 5.0
# EM runs of the calibrated mixture after the first, each with the LOS offsets held at the
# last release's: a bound on its cost (the second pass moved them by a centimetre or less)
CALIBRATION_PASSES = 2
# m: the tightest spread of the anchors' offsets the calibrated mixture holds them by: a
# DW1000-class radio's timestamp resolution, 15.65 ps, is 4.7 mm of range
ANCHOR_SPREAD_MIN = 0.005
# LM stops when an iteration lowers the error by less than this fraction
LM_RELATIVE_TOL = 1e-3
# m: each anchor's range bias around the common one, as held in the LM rounds that free the
# biases: looser, the anchors of a mostly blocked site take up NLOS excess EM left on LOS
BATCH_ANCHOR_BIAS_SIGMA = 0.02
# relative step of the log grid the range sigmas are rounded to (weights within ~1 %), so
# that a range whose weight barely moved between EM rounds keeps its factor
SIGMA_STEP = 0.005
# s: held-out stretch of `graph.range_model = "auto"`: holds out a range with its neighbours
# of the same NLOS episode (about 1 s); odometry bridges 2 s
HELDOUT_BLOCK_S = 2.0
# one stretch in eight per phase is held out: 7/8 of the ranges still fit
HELDOUT_EVERY = 8
# phases held out in bit-reversed order (+4 mod 8): each next one halves the gaps, so a stop
# at MIN_SCORED_RANGES leaves them spread over the log; not 0 first (it lacks stretch 0)
HELDOUT_PHASES = (4, 0, 6, 2, 5, 1, 7, 3)
# held-out ranges that end the cross-validation: their mean log score then has a standard
# error of about 0.1 nats (per-range spread ~1 nat), below the gaps that decide
MIN_SCORED_RANGES = 100
# fewer held-out ranges than this cannot rank two models
MIN_HELDOUT_RANGES = 20
# m: a LOS range sigma beyond this is no UWB radio's
MAX_ROBUST_SIGMA = 1.0

# ---------------------------------------------------------------------------------------
# Online smoother (`graph.builder`, `graph.estimator`, `graph.pose_factor`)
# ---------------------------------------------------------------------------------------

# m: anchors are known; a tight prior keeps them fixed
ANCHOR_SIGMA = 1e-3
# m: prior std of the common range bias in the online graph: at a log's start every anchor
# may be in NLOS at once, and a loose prior takes that shared excess for a calibration offset
ONLINE_COMMON_BIAS_SIGMA = 0.05
# m: prior std of the common range bias where the ranges cannot tell it from the tag's
# height (height free, anchors coplanar): held at zero, the offset of calibrated radios
UNOBSERVED_COMMON_BIAS_SIGMA = 1e-3
# m: prior std of each anchor's range bias around the common one online: a few seconds of
# ranges barely separate an offset from the position, and a loosely held one wanders
ONLINE_ANCHOR_BIAS_SIGMA = 0.02
# m/s: a start state faster than this is not trusted (implausible for an indoor vehicle or walker)
ONLINE_MAX_START_SPEED = 3.0
# m/s: a solve that moves the newest keyframe faster has diverged (a Gauss-Newton step on a
# gross range error that no robust kernel bounds), no indoor vehicle or walker moves so fast
MAX_SOLVED_SPEED = 10.0
# ns: the newest ranges a lost filter's restart fix may use: one round robin of slow radios
# (4 anchors at 1 Hz); older ones place a walker metres from where it is
MAX_LOST_FIX_NS = 2_000_000_000
# ranges of an anchor per online scale step (each adds its evidence to all before it): 20 at
# 0.1 m noise pin a step to 0.1 / (sqrt(20) d), 0.2 % at d = 10 m, under the per-cent errors
# sought; 2 s of one anchor at 10 Hz
SCALE_BLOCK = 20
# bound on a range scale error (relative): a guard (clocks err by ppm, radios met read a few %
# long); a larger k is a Gauss-Newton step run away on poor geometry, not a radio
MAX_SCALE = 0.2
# ranges the configured LOS sigma counts as in the online LOS sigma estimates (MAD of the
# ranges classified LOS, `robust_los_sigma`: misclassified NLOS ranges would inflate an RMS)
LOS_SIGMA_PRIOR_RANGES = 20.0
# ns: an identical range of the same anchor within this is a copy
REPEAT_WINDOW_NS = 150_000_000
# one-step residuals of the online robust sigma's MAD: 1000 give it to ~4 % (1.17 / sqrt(n),
# normal) and are 25 s at 40 Hz, so it follows the site's changes
PREQUENTIAL_WINDOW = 1000
# ranges before the online prequential scores start (the robust sigma needs them), and
# scored ranges before their paired test may decide
MIN_PREQUENTIAL_RANGES = 100
# standard errors of the mean score advantage per range that change the online range model
# (a one-sided paired test at about 0.1 %)
PREQUENTIAL_Z = 3.0
# keyframes per iSAM2 update in batch's seeding pass: 1 s at 10 Hz; it needs no per-epoch
# answer, so fewer, larger updates (work bound)
BATCH_CHUNK = 10
# keyframes per isam2 update under `graph.update_every = "auto"` unless an IMU alone
# predicts between updates (a work bound): wheel odometry predicts to millimetres over 0.3 s
# at 10 Hz; without IMU or wheels the constant-velocity graph solved at every keyframe
# turned iSAM2 indefinite on sparse ranges (43 re-anchors in 40 s at 4 ranges/s)
PREDICTED_UPDATE_EVERY = 3
# s: younger ranges keep their insertion class: a review weighs the ranges after a range, and
# 0.5 s brings ~5 more of its anchor (10 Hz) and the smoothed keyframes on both sides
REVIEW_MIN_AGE_S = 0.5
# switch: discrete LOS/NLOS hypothesis search in the review (see `_review`); tests turn it off
REVIEW_SEARCH = True
# nats: log-likelihood gain of a better LOS/NLOS assignment in the review's search; chosen
# from simulated results, not derived (docs/results.md, "still chosen from results")
SEARCH_SWITCH_NATS = 10.0
# ... in this many consecutive reviews before it is adopted: 0.9 s at 3 keyframes per update
# (with wheels), about one NLOS segment ([nlos] segment, 1 s), 0.3 s at 1; not one
# update's noise
SEARCH_PERSIST = 3
# s: ranges this close to leaving the lag window are not reviewed: a guard beyond the next
# update's span, 5 keyframes (10 % of the 5 s lag) the smoother is not about to marginalise
REVIEW_MARGIN_S = 0.5
# s: age at which a keyframe's residuals feed the smoothed LOS sigma: by then 2 s of later ranges
# (two 1 s NLOS segments) are in its estimate, near its final one, inside the 5 s lag
SMOOTHED_STAT_AGE_S = 2.0
# responsibility change (0..1) that replaces a range's factors: a quarter of its information
# moved between LOS and NLOS; less is not worth an iSAM2 removal (work bound)
REVIEW_CHANGE = 0.25
# update latencies `forget_before` keeps (16 min at 10 Hz)
LIVE_LATENCY_KEPT = 10_000
# 1/m^2 or 1/rad^2: information left in the directions a planar pose factor does not
# constrain: small enough to be no constraint, large enough for a PD information
NO_INFORMATION = 1e-8
# successive-range pairs of a standstill before its radio noise s_w counts (fewer: every
# range weighs 1, `graph.rest`): the median of 20 pins s_w to about 30 %
REST_MIN_PAIRS = 20
# s_w is taken again each time the standstill's pairs grow by this factor: a work bound (an
# hour's rest would sort its pairs at every keyframe)
REST_RHO_REFRESH = 1.25
# standard errors of a standstill's range slope (per anchor, against its radio noise) that
# call it a glide: a two-sided test at about 0.3 %
REST_TREND_Z = 3.0
# probability that a standstill test (`graph.rest`: the velocity entering a still run, the
# IMU's velocity within it) calls a true rest a glide, each time it is taken
REST_FALSE_ALARM = 0.01
# s: the IMU blocks' still verdicts kept for the ranges still to come (a keyframe's ranges
# lag the newest IMU sample by a keyframe period and the data's batching, well under this)
REST_HISTORY_S = 10.0

# ---------------------------------------------------------------------------------------
# Kalman filters (`filters`)
# ---------------------------------------------------------------------------------------

# ns: longest stretch of time handled as one predict/update window
MAX_WINDOW_NS = 100_000_000
# rad: largest attitude std the UKF draws sigma points over: its second-order mean of a
# rotated vector is (1 - sigma^2 / 2) of it (the truth: exp(-sigma^2 / 2)), which changes
# sign beyond sqrt(2); wider (a start with an unknown heading), the EKF's window runs
UT_MAX_ATTITUDE_SIGMA = 2.0**0.5
# ns: a range bit-identical to the previous one of its anchor within this is a re-publication
# (some RTLS devices send every epoch twice, ~50 ms apart); noisy ranges never repeat to the bit
REPEAT_NS = 150_000_000
# m/s: initial velocity std of a moving start: its velocity is known to about an indoor
# vehicle's cruise speed (AGV 0.5 m/s, walker ~1 m/s)
MOVING_VELOCITY_SIGMA = 0.5
# m/s: ... of a still start, taken where the standstill tests end: an AGV gains 0.01-0.03 m/s
# within one 0.1 s test block at 0.1-0.3 m/s^2
STILL_VELOCITY_SIGMA = 0.02
# m/s: start speed above which the start counts as moving even when the log began still
# (the start state may come seconds later, from a walk)
MOVING_START_SPEED = 0.05
# rad: initial roll/pitch std when still (levelled from gravity)
TILT_SIGMA_STILL = 0.02
# rad: initial roll/pitch std when moving (levelled from the mean accel): an AGV's 0.3-0.5
# m/s^2 forward acceleration taken for gravity tilts it by a/g = 0.03-0.05 rad
TILT_SIGMA_MOVING = 0.05
# m^2: largest position variance after recoveries, (10 m)^2, a room-to-hall site (5-40 m):
# wider says no more and only worsens P's conditioning
INFLATE_CAP_POS = 100.0
# (m/s)^2: largest velocity variance after recoveries, (5 m/s)^2: above any indoor vehicle's
# or walker's speed (ONLINE_MAX_START_SPEED 3 m/s); wider says no more
INFLATE_CAP_VEL = 25.0
# m: smallest initial height std: anchors near one height see z through dz/r only (0.05-0.2,
# tag 1 m below anchors 5-20 m away), 5-20x worse than x, y (>= 0.05 m); the graph's floor too
Z_SIGMA_MIN = 0.3
# accepted ranges between two EM refits of the range mixture: a work bound, one EM over the
# window per 5 s at 40 Hz, 5 % of the window renewed
REFIT_EVERY = 200
# accepted ranges (the newest) each refit uses: 100 s at 40 Hz; at 20 % NLOS, 800 NLOS ranges
# fix its std to ~2.5 % (1 / sqrt(2n)); a memory and EM work bound
RANGE_NOISE_WINDOW = 4000
# ranges the configured per-range model counts as: a std from 200 is known to 5 % (1 /
# sqrt(2n)), so it holds until the log has as many; 5 % of a full window
PRIOR_RANGES = 200.0
# measurement rows a configured wheel/planar variance counts as: 200 give a variance to 10 %
# (sqrt(2/n)), so it holds until the log has as many (4 s of 50 Hz wheels)
PRIOR_ROWS = 200.0
# measurement rows of the running variance's exponential memory: 2000 give it to 3 %; 40 s of
# 50 Hz wheels (200 s of 10 Hz planar rows), so a change of floor or load is followed
MEMORY_ROWS = 2000.0
# floor of a matched variance as a share of the configured one: sampling noise can drive
# E[y^2 - s] to zero or below, and a zero variance would make the constraint rigid
MATCHED_VARIANCE_MIN_SHARE = 0.01
# bounds of an anchor's prior NLOS probability (the chain never becomes certain)
P_BOUNDS = (0.01, 0.99)
# process-noise factors (on the stds) of the noise bank: log-uniform, ratio sqrt(10) over a
# decade upwards; the configured figure is the floor (docs/results.md)
NOISE_BANK_FACTORS = (1.0, math.sqrt(10.0), 10.0)
# nats: a bank member this far behind is dropped (posterior odds of 1e-4 under a flat prior)
DROP_NATS = math.log(1e4)

# ---------------------------------------------------------------------------------------
# Output grid and live runs (`estimator`, `localizer`)
# ---------------------------------------------------------------------------------------

# epochs the output grid may have: 10^7 is 11.6 days at 10 Hz (about 1 kB each); more means
# stamps on different clocks, not a long log
MAX_EPOCHS = 10_000_000
# s of epochs between `forget_before` calls: a work bound (one per 100 epochs at 10 Hz); memory
# swings between the 2 x lag kept (10 s at the default lag) and 10 s more
FORGET_EVERY_S = 10.0
