"""Typed, frozen environment configuration; scenario presets live in ``scenarios.py``."""

from __future__ import annotations

import dataclasses
import math

from aswarm.envs.crazyflie import CrazyflieParams
from aswarm.envs.firmware_mellinger import FirmwareMellinger
from aswarm.envs.firmware_pid import FirmwarePid
from aswarm.envs.onboard_controller import ControllerGains
from aswarm.envs.presets import SCENARIOS
from aswarm.envs.randomization import OFF, Randomization

REWARDS = ("shaped", "paper")
# The onboard controller between the policy's velocity command and the motors. "pid": the Crazyflie
# firmware's default controller_pid (firmware_pid.py), what a stock Crazyflie runs on velocity setpoints;
# "mellinger": the firmware's controller_mellinger (firmware_mellinger.py) on full-state setpoints that integrate
# the velocity command; "geometric": the SO(3) controller every run before the firmware's was trained with
# (onboard_controller.py).
CONTROLLERS = ("pid", "mellinger", "geometric")
# The firmware runs controller_pid's attitude and rate loops at 500 Hz and its velocity loop at 100 Hz
# (stabilizer_types.h: ATTITUDE_RATE, POSITION_RATE): the physics steps at the attitude rate. Mellinger runs
# whole at 500 Hz; its setpoint is latched at the 100 Hz tick (where command latency is counted).
PID_RATES = {"sim_freq": 500, "ctrl_freq": 100}
FORMATIONS = ("column", "grid")
MAX_AGENTS = 64


@dataclasses.dataclass(frozen=True)
class EnvConfig:
    scenario: str = "race"
    num_agents: int = 4
    num_obstacles: int = 8  # static cylinders
    num_moving: int = 0  # moving cylinders, at most, per episode
    min_moving: int = 0  # moving cylinders, at least, per episode
    # Moving cylinders, at most, per episode, of the num_moving slots the observation holds (-1: all of them). A
    # policy trained on 1-3 flies exactly k of its 3 slots with min_moving = max_moving = k (the safety matrix).
    max_moving: int = -1
    num_gates: int = 4  # 0: each drone flies to a goal point instead
    # Geometry (metres). Gate tracks are ellipses with these semi-axes.
    track_radii: tuple[float, float] = (6.0, 4.0)
    track_height: float = 1.0
    arena_low: tuple[float, float, float] = (-8.0, -6.0, 0.0)
    arena_high: tuple[float, float, float] = (8.0, 6.0, 3.0)
    gate_half_opening: float = 0.3
    gate_bar: float = 0.05
    obstacle_radius: float = 0.15
    obstacle_height: float = 3.0  # up to the ceiling: no way over the top
    obstacle_spacing: float = 1.5  # between obstacle slots along the track / grid
    obstacle_lateral: float = 0.6  # random offset of a static obstacle from the racing line
    gate_clearance: float = 1.2  # no obstacle slot closer than this (along the track) to a gate or the start
    # Smallest surface gap (m) between two static cylinders. A narrower gap is a dead end for the CBF filter,
    # which needs 2 (drone radius + margin) = 0.32 m at the defaults: it held drones at the mouth of 0.15-0.19 m
    # gaps between 2 cylinders until time ran out (4 % of `obstacles` episodes, README). Layouts redraw the
    # offsets of the static cylinders (up to layout_draws times) until every gap is at least this wide.
    min_obstacle_gap: float = 0.45
    layout_draws: int = 16
    moving_amplitude: float = 0.8
    moving_period: float = 4.0  # s
    # Each moving cylinder's speed, per episode, a uniform draw from this range times the one moving_period
    # gives (the same amplitude swept faster): training among faster cylinders than the default.
    moving_speed_scale: tuple[float, float] = (1.0, 1.0)
    goal_radius: float = 0.2
    start_spacing: float = 0.5
    # Neighbours in each drone's observation. 0: every other drone, in index order (the row grows with n, and
    # so does the cost per drone). K >= 1: the K nearest drones still flying, nearest first, padded with absent
    # rows when there are fewer: the row, and so a trained actor and its filter, no longer depend on n.
    max_neighbours: int = 0
    # The safety filter's neighbour rows, when larger than max_neighbours (K >= 1): the filter_neighbours nearest
    # flying drones (at most every other one), from the same observation pipeline (noise, delay), of which the
    # policy reads its K nearest. A drone the policy does not observe is still one the filter keeps apart: the
    # 4-drone `obstacles` policy (K = 3) flown by 32 drones had 18.8 % collision episodes (all drone-drone) with its
    # filter on the 3 nearest and none with it on the 8 nearest (128 episodes each; README, swarms). 0 or <= K:
    # the filter takes the policy's rows, as before this field.
    filter_neighbours: int = 8
    # The safety filter's observation carries each of its neighbours' accelerations from their attitude (what
    # motion capture measures of every drone), for a second-order look-ahead (SafetyFilterConfig.lookahead_accel,
    # which needs it; aswarm.core.layout.NBR_ACCEL). The policy's observation is unchanged.
    filter_neighbour_accel: bool = False
    # Track starts: "column", single file along the racing line, so the swarm reaches each gate one
    # drone at a time (a 4-drone grid jammed at the first gate, see README); or a compact "grid".
    start_formation: str = "column"
    # Track starts: drone i holds its position until i * start_interval s, so the column reaches each gate
    # one drone at a time (released all at once, the followers caught up and the swarm jammed at gate 0).
    start_interval: float = 0.0
    layout_jitter: float = 1.0  # 0 gives the nominal layout every episode
    # Rates (Hz). Physics >= 240 Hz; the controller and the policy divide it. controller "pid" runs its
    # attitude loop every physics step and its velocity loop every 1 / ctrl_freq s, at the firmware's rates.
    controller: str = "pid"
    sim_freq: int = 500
    ctrl_freq: int = 100
    policy_freq: int = 25  # 10 Hz: the command held 0.1 s outran the filter (README)
    episode_seconds: float = 40.0
    max_speed: float = 2.0  # m/s, per-axis clip of the velocity command
    # Reward and cost.
    reward: str = "shaped"
    progress_weight: float = 10.0  # per metre of progress towards the current target
    # Per gate passed, paid on the step through the opening. Off by default since session 34: without it (and
    # without wrong_side_clearance) the main command's seeds 0-2 flew 99.9 / 99.9 / 100.0 % with 1 collision
    # episode in 3,000, against 99.5 % and 3 with both (seeds 3-4: 99.6 / 99.2 %, 1 more); progress already pays
    # for the metre through the gate, and the one-step spike of 10 looks like what a drone beside the frame
    # turned back for (README "Where the main command's failures come from"). The shipped policies trained with
    # 10 and keep it in their config.
    gate_bonus: float = 0.0
    finish_bonus: float = 20.0
    collision_penalty: float = 100.0  # the paper's -100
    time_penalty: float = 0.5  # per second, while flying
    # Per (m/s)² of change of the velocity command from one policy step to the next. The firmware drone gives up
    # thrust to the attitude loop when the commanded tilt swings (its power distribution caps the motors), and
    # commands that swing every step made it sink into the floor while commanded up (README, issue #12). Off by
    # default: 0.02 gave 91.5 % and 87.5 % race success in two runs, no penalty 90.4 % (not a measurable gain).
    command_rate_penalty: float = 0.0
    # m/s², 0 = off: the fastest the velocity command the drone receives may change (per axis), applied to the
    # filtered command on every policy step (the flight runtime does the same). The firmware's velocity PID
    # saturates its 20° tilt at 0.8 m/s of velocity error, so a command that jumps further than that in one step
    # swings the tilt setpoint end to end, the rate loop saturates and the power distribution takes thrust: the
    # drone sank into the floor while commanded up. 3 m/s² is under what 20° of tilt gives (3.6 m/s²), so the
    # drone can follow the command it receives (measured in the README, "On the firmware drone").
    command_accel_limit: float = 3.0
    # Track progress is measured in the current gate's frame as |along| + lateral_weight * |off the axis|
    # + wrong_side_weight * (depth past the plane, not through the opening). With plain distance to the
    # centre, policies learnt to hover beside or behind the gate (1 drone, 1M steps: no gate passed);
    # weighing the offset from the axis makes the drone line up before the plane, as racing lines do.
    lateral_weight: float = 2.0
    wrong_side_weight: float = 2.0
    # m, 0 = off. Past the plane, an offset from the axis under this counts as this: a drone that flew beside
    # the frame is drawn straight back to the approach side, not diagonally towards the axis through the frame
    # (where the filter holds it). It holds on the step through the opening too, where it takes back most of
    # gate_bonus. 0.5 was the default in session 33 (99.9 / 99.6 / 99.0 % on the main command's seeds); off
    # since session 34, with gate_bonus off, which flew better (see gate_bonus).
    wrong_side_clearance: float = 0.0
    paper_epsilon: float = 0.001  # r = 1 / (d + eps)
    safety_margin: float = 0.15  # m; the cost grows as clearance falls below it
    # s, 0 = off. The cost also counts each drone's clearance to where the cylinders will be over this horizon
    # (their scripted motion, sampled at the policy's period; the drone taken as staying put), so a drone that
    # waits in a fast cylinder's path pays before the cylinder arrives rather than on the step the filter can no
    # longer hold it (the 1.5x cells' collisions: README, "A cost on the cylinders' reach"). Training only: the
    # cost shapes the penalty and the gain target, and neither the policy's nor the filter's inputs change.
    moving_cost_horizon: float = 0.0
    cf: CrazyflieParams = CrazyflieParams()
    gains: ControllerGains = ControllerGains()  # controller "geometric"
    pid: FirmwarePid = FirmwarePid()  # controller "pid"; its thrust map also serves "mellinger"
    mellinger: FirmwareMellinger = FirmwareMellinger()  # controller "mellinger"
    # m, controller "mellinger": the full-state setpoint's position (the integrated command) is kept this close
    # to the drone, so a drone that fell behind is not pulled back along the whole way it missed. At 0.3 m the
    # position term alone asks for kp_xy * 0.3 / (mass * g) = 0.42, about 23 degrees of tilt: near what the
    # PID's 20-degree limit allows.
    reference_leash: float = 0.3
    randomize: Randomization = Randomization()

    def __post_init__(self) -> None:
        validate(self)

    @property
    def substeps(self) -> int:
        return self.sim_freq // self.policy_freq

    @property
    def ctrl_every(self) -> int:
        return self.sim_freq // self.ctrl_freq

    @property
    def dt(self) -> float:
        return 1.0 / self.policy_freq

    @property
    def max_steps(self) -> int:
        return int(round(self.episode_seconds * self.policy_freq))

    @property
    def num_cylinders(self) -> int:
        return self.num_obstacles + self.num_moving

    @property
    def most_moving(self) -> int:
        """Moving cylinders at most in an episode (max_moving, -1 read as num_moving)."""
        return self.num_moving if self.max_moving < 0 else self.max_moving


# Fields of cf., gains. and pid. where 0 means "left out" rather than nonsense.
MAY_BE_ZERO = {("cf.", "motor_tau"), ("cf.", "motor_tau_down"),
               ("cf.", "drag"), ("pid.", "yaw_kd"), ("pid.", "rate_kd"), ("pid.", "vel_xy_ki"),
               ("pid.", "vel_z_ki"), ("pid.", "att_ki"), ("pid.", "yaw_ki"), ("pid.", "rate_ki"),
               ("pid.", "yaw_rate_ki"), ("mellinger.", "ki_xy"), ("mellinger.", "ki_z"), ("mellinger.", "ki_m_xy"),
               ("mellinger.", "ki_m_z"), ("mellinger.", "kd_omega_rp")}

# The drone every run before the firmware-faithful one (issue #12) trained on, as EnvConfig fields: what a stored
# run's or bundle's env that lacks the newer fields meant (``with_legacy_drone`` fills them from here), and what
# tests of the geometric controller build (``registry.preset(name, **LEGACY_DRONE)``).
LEGACY_DRONE = {"controller": "geometric", "sim_freq": 250, "ctrl_freq": 250,
                "cf": dataclasses.replace(CrazyflieParams(), motor_tau=0.0), "pid": FirmwarePid(), "randomize": OFF,
                "command_accel_limit": 0.0}


def legacy_drone_stored() -> dict:
    """:data:`LEGACY_DRONE` as config.json and export manifests write it (dataclasses as tables)."""
    return {k: dataclasses.asdict(v) if dataclasses.is_dataclass(v) else v for k, v in LEGACY_DRONE.items()}


# EnvConfig fields added after issue #12 (nested ones dotted), as a stored env without them was.
ADDED_SINCE = {"command_rate_penalty": 0.0, "command_accel_limit": 0.0, "randomize.velocity_window": 0,
               "mellinger": dataclasses.asdict(FirmwareMellinger()), "reference_leash": EnvConfig.reference_leash,
               "max_moving": -1, "filter_neighbours": 0, "cf.motor_tau_down": 0.0,
               "moving_speed_scale": (1.0, 1.0), "wrong_side_clearance": 0.0, "filter_neighbour_accel": False,
               "moving_cost_horizon": 0.0}


def with_legacy_drone(env: dict) -> dict:
    """A stored ``env`` section with the fields issue #12 added filled in as the drone was before them (the
    geometric controller at 250 Hz, no rotor lag, no drag, nothing randomised): a run that predates them was
    trained on that drone. Fields added later (:data:`ADDED_SINCE`) get the value that leaves the env as it was.
    Fields it has are kept."""
    if not isinstance(env, dict):
        return env
    env = dict(env)
    for key, value in ADDED_SINCE.items():
        group, _, name = key.rpartition(".")
        if not group:
            env.setdefault(name, value)
        elif isinstance(env.get(group), dict):
            env[group] = {name: value, **env[group]}
    if "controller" in env:
        return env
    out = dict(env)
    for k, v in legacy_drone_stored().items():
        if k not in out:
            out[k] = v
        elif isinstance(v, dict) and isinstance(out[k], dict):
            out[k] = {**v, **out[k]}
    return out


def _fail(name: str, value, allowed: str) -> None:
    raise ValueError(f"invalid {name}={value!r}: {allowed}")


def _check_finite(prefix: str, obj) -> None:
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        vals = v if isinstance(v, tuple) else (v,)
        for x in vals:
            if isinstance(x, float) and not math.isfinite(x):
                _fail(prefix + f.name, v, "must be a finite number")


def validate(c: EnvConfig) -> None:
    """Raise ``ValueError`` naming the first bad field and what is allowed."""
    if c.scenario not in SCENARIOS:
        _fail("scenario", c.scenario, f"allowed: {', '.join(SCENARIOS)}")
    _check_finite("", c)
    _check_finite("cf.", c.cf)
    _check_finite("gains.", c.gains)
    _check_finite("pid.", c.pid)
    _check_finite("mellinger.", c.mellinger)
    if c.controller not in CONTROLLERS:
        _fail("controller", c.controller, f"allowed: {', '.join(CONTROLLERS)}")
    if c.controller in ("pid", "mellinger"):
        for name, rate in PID_RATES.items():
            if getattr(c, name) != rate:
                _fail(name, getattr(c, name),
                      f"controller {c.controller!r} runs at the firmware's rates: {name}={rate}")
    if not c.pid.max_tilt_deg < 90:
        _fail("pid.max_tilt_deg", c.pid.max_tilt_deg, "must be in (0, 90) degrees")
    if not c.pid.motor_thrust_min < c.pid.motor_thrust_max:
        _fail("pid.motor_thrust_min", c.pid.motor_thrust_min,
              f"must be < pid.motor_thrust_max={c.pid.motor_thrust_max}")
    # Physical constants and gains: a zero or negative one has no meaning (MuJoCo itself would refuse a mass
    # of 0 with a multi-line error), and a drone that cannot lift its weight never takes off.
    for prefix, obj in (("cf.", c.cf), ("gains.", c.gains), ("pid.", c.pid), ("mellinger.", c.mellinger)):
        for f in dataclasses.fields(obj):
            if (prefix, f.name) in MAY_BE_ZERO:
                if any(x < 0 for x in (getattr(obj, f.name) if f.name == "drag" else (getattr(obj, f.name),))):
                    _fail(prefix + f.name, getattr(obj, f.name), "must be >= 0")
                continue
            v = getattr(obj, f.name)
            if any(isinstance(x, (int, float)) and x <= 0 for x in (v if isinstance(v, tuple) else (v,))):
                _fail(prefix + f.name, v, "must be > 0")
    if c.cf.thrust_to_weight <= 1:
        _fail("cf.thrust_to_weight", c.cf.thrust_to_weight, "must be > 1 (the drone must lift its own weight)")
    if not c.gains.max_tilt_deg < 90:
        _fail("gains.max_tilt_deg", c.gains.max_tilt_deg, "must be in (0, 90) degrees")
    for name in ("num_agents", "num_obstacles", "num_moving", "min_moving", "num_gates",
                 "sim_freq", "ctrl_freq", "policy_freq", "layout_draws", "max_neighbours", "filter_neighbours"):
        if not isinstance(getattr(c, name), int) or isinstance(getattr(c, name), bool):
            _fail(name, getattr(c, name), "must be an integer")
    if not 1 <= c.num_agents <= MAX_AGENTS:
        _fail("num_agents", c.num_agents, f"must be between 1 and {MAX_AGENTS}")
    for name in ("num_obstacles", "num_moving", "min_moving", "num_gates", "max_neighbours", "filter_neighbours"):
        if getattr(c, name) < 0:
            _fail(name, getattr(c, name), "must be >= 0")
    if not isinstance(c.filter_neighbour_accel, bool):
        _fail("filter_neighbour_accel", c.filter_neighbour_accel, "allowed: true or false")
    if c.min_moving > c.num_moving:
        _fail("min_moving", c.min_moving, f"must be <= num_moving={c.num_moving}")
    if not isinstance(c.max_moving, int) or isinstance(c.max_moving, bool) or not (
            c.max_moving == -1 or c.min_moving <= c.max_moving <= c.num_moving):
        _fail("max_moving", c.max_moving, f"allowed: -1 (num_moving) or min_moving={c.min_moving} to "
                                          f"num_moving={c.num_moving}")
    if not c.reference_leash > 0:
        _fail("reference_leash", c.reference_leash, "must be > 0 m")
    if c.sim_freq < 240:
        _fail("sim_freq", c.sim_freq, "must be >= 240 Hz")
    if c.ctrl_freq <= 0 or c.sim_freq % c.ctrl_freq:
        _fail("ctrl_freq", c.ctrl_freq, f"must divide sim_freq={c.sim_freq}")
    if c.policy_freq <= 0 or c.ctrl_freq % c.policy_freq:
        _fail("policy_freq", c.policy_freq, f"must divide ctrl_freq={c.ctrl_freq}")
    for name in ("episode_seconds", "max_speed", "gate_half_opening", "gate_bar", "obstacle_radius",
                 "obstacle_height", "obstacle_spacing", "goal_radius", "start_spacing", "moving_period",
                 "safety_margin", "track_height"):
        if getattr(c, name) <= 0:
            _fail(name, getattr(c, name), "must be > 0")
    for name in ("lateral_weight", "wrong_side_weight", "wrong_side_clearance", "command_rate_penalty",
                 "command_accel_limit", "moving_cost_horizon"):
        if getattr(c, name) < 0:
            _fail(name, getattr(c, name), "must be >= 0")
    if c.start_interval < 0:
        _fail("start_interval", c.start_interval, "must be >= 0")
    lo, hi = c.moving_speed_scale
    if not 0 < lo <= hi:
        _fail("moving_speed_scale", c.moving_speed_scale, "allowed: LOW,HIGH with 0 < LOW <= HIGH (1,1: one speed)")
    if c.layout_jitter < 0:
        _fail("layout_jitter", c.layout_jitter, "must be >= 0")
    if c.min_obstacle_gap < 0:
        _fail("min_obstacle_gap", c.min_obstacle_gap, "must be >= 0")
    if c.layout_draws < 1:
        _fail("layout_draws", c.layout_draws, "must be >= 1")
    if c.start_formation not in FORMATIONS:
        _fail("start_formation", c.start_formation, f"allowed: {', '.join(FORMATIONS)}")
    if c.reward not in REWARDS:
        _fail("reward", c.reward, f"allowed: {', '.join(REWARDS)}")
    if any(lo >= hi for lo, hi in zip(c.arena_low, c.arena_high)):
        _fail("arena_low", c.arena_low, f"must be below arena_high={c.arena_high} on every axis")
