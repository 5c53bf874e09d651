"""``FlightController``: mocap poses in, bounded world-frame velocity setpoints out.

One :meth:`FlightController.step` per control period (the manifest's rate, 25 Hz for the shipped
scenarios): check the poses, update the velocity estimates (by default a model of the drone driven by the commands
sent, carried to the present: :mod:`aswarm.flight.estimator`), track each drone's gates (or goal, reached on a
measured pose ``SafetyConfig.goal_margin`` inside its radius), build the observations as the simulator does, run
the actor, the attention-CBF gain and the CBF safety filter, and clamp. Arrays take leading batch axes (worlds) so
that software-in-the-loop flies many episodes through this same code.

Safety on bad input (never a NaN, never more than ``max_speed`` per axis):
- a NaN/Inf or zero-length pose, or none (NaN is how a missing pose is passed): the drone keeps its
  last good pose for the estimates and gets a hover (zero velocity) command;
- a pose older than ``stale_after`` s: hover; blind for longer than ``land_after`` s: land request;
- a drone outside the geofence (the arena box of the manifest, less ``geofence_margin``): land
  request;
- a non-finite command (e.g. a corrupted input reaching the networks): hover;
- a swarm that does not match the bundle (number of drones, gates, more obstacles than the policy
  observes, an unknown scenario kind): ``ValueError`` at construction, reset or step, because
  flying it would be unsafe.
Where the bundle sets a command acceleration limit (``EnvConfig.command_accel_limit``), every command,
hover included, moves towards its value no faster than that, as in the simulator.
A drone asked to land stays landing (zero velocity here; the flight loop hands it to the
high-level commander) until :meth:`reset`. Every condition is reported once, when it starts, as an
:class:`Event`; ``StepResult.hover`` and ``land`` give the state at every step.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from aswarm.core.command import limit_change
from aswarm.core.geometry import gate_crossed, horizontal
from aswarm.core.layout import observed_neighbours
from aswarm.core.observation import observe
from aswarm.flight import cbf, estimator, policy
from aswarm.flight.bundle import Bundle

# m: the runtime's gate-crossing test is a trigger with two thresholds on the drone's estimated distance along the
# gate's direction of passage: it arms at GATE_ARM_DISTANCE before the plane and fires, crossing the opening,
# GATE_PASS_DISTANCE past it (past that beside the frame, it disarms). The simulator's test has one threshold, the
# plane, on the true position. One threshold on an estimate counted passes the simulator never saw: a drone
# crawling up to the plane, or one that had passed it beside the frame and crept back to it from the far side, sat
# on it while pose noise flickered across it (SITL, unseen episodes, issue #12: the runtime sent a ghost on to its
# next gate, or landed it as finished while the simulator held it at its gate: 3 of 4 time-outs and 4 of 5
# collision episodes in the 5 cells traced). The estimate strayed up to ~1 cm from the truth at 5 mm pose noise.
# The price: a policy trained on the simulator's test may re-pass a gate it overshot by dipping only millimetres
# back before the plane, which the runtime does not count (2 of 400 traced episodes: the drone kept at it until
# time ran out; a simulator with the same trigger, trained on, would remove that). 1 cm / 5 mm instead of 2 / 1 cm
# did no better on the same cells.
GATE_ARM_DISTANCE = 0.02
GATE_PASS_DISTANCE = 0.01


@dataclasses.dataclass(frozen=True)
class SafetyConfig:
    stale_after: float = 0.1  # s; a newest pose older than this makes the drone hover
    land_after: float = 0.5  # s; blind (no fresh pose) for longer than this: land request
    geofence_margin: float = 0.0  # m inside the manifest's arena box (x, y and the ceiling)
    # A drone that finished (passed its last gate or reached its goal) lands where it is. In the
    # simulator it leaves the course and is no longer a neighbour; a real one is still in the air
    # while it descends, so by default the others keep seeing it (SITL turns this off to match
    # the simulator's episodes).
    finished_are_neighbours: bool = True
    # m inside the goal radius a measured pose must be to finish its drone. The policy learned to touch its goal's
    # edge, and a finished drone stops: mocap noise on a pose that grazed the radius must not stop a drone that never
    # truly entered it (several sigma of the mocap's noise; README, "Goals on measured poses").
    goal_margin: float = 0.01

    def __post_init__(self) -> None:
        for name in ("stale_after", "land_after"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"invalid {name}={v!r}: must be a finite number of seconds > 0")
        for name in ("geofence_margin", "goal_margin"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"invalid {name}={v!r}: must be a finite number of metres >= 0")


@dataclasses.dataclass(frozen=True)
class Obstacles:
    """Vertical cylinders seen by mocap: pos [..., M, 2] (m, world xy), radius [..., M] (m).

    vel [..., M, 2] m/s (zero if None); present [..., M] bool (all if None); accel [..., M] m/s², a bound on each
    one's acceleration (0: static, all if None; the filter's rows for a moving one hold against any motion within
    it, where the bundle's filter has ``hazard_accel``). M may be smaller than the number the policy was trained
    with (the rest are absent), never larger.
    """

    pos: np.ndarray
    radius: np.ndarray
    vel: np.ndarray | None = None
    present: np.ndarray | None = None
    accel: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class Event:
    world: int  # index into the flattened batch axes (0 without a batch)
    drone: int
    kind: str  # see EVENT_KINDS
    time: float  # s, the controller's clock
    detail: str = ""


EVENT_KINDS = ("invalid_pose", "stale_pose", "pose_glitch", "geofence", "land", "finished", "nonfinite_command",
               "filter_unconverged", "obstacle_lost")


@dataclasses.dataclass(frozen=True)
class StepResult:
    velocity: np.ndarray  # [..., n, 3] world-frame setpoints, m/s, finite and within ±max_speed
    land: np.ndarray  # [..., n] bool: hand the drone to a landing
    hover: np.ndarray  # [..., n] bool: the setpoint was forced to zero (blind, landing or bad command)
    events: list[Event]
    nominal: np.ndarray  # [..., n, 3] the actor's command before the filter
    intervened: np.ndarray  # [..., n] bool: the safety filter changed the command
    gain: np.ndarray  # [..., n] class-K gain used by the filter (1/s)
    target: np.ndarray  # [..., n] index of each drone's current gate (or 0 for a goal)
    finished: np.ndarray  # [..., n] bool
    obs: np.ndarray  # [..., n, D] the observations the policy saw
    position: np.ndarray  # [..., n, 3] where the drones are now, as the policy saw them (the estimate's present)


class FlightController:
    """Runs a bundle's policy and safety filter on mocap poses. See the module docstring for the safety rules."""

    def __init__(self, bundle: Bundle, num_drones: int, *, safety: SafetyConfig = SafetyConfig(),
                 estimation: estimator.EstimatorConfig = estimator.EstimatorConfig(), scenario: str | None = None):
        if num_drones != bundle.num_agents:
            raise ValueError(f"the bundle was trained for {bundle.num_agents} drones, the swarm has {num_drones}: "
                             "the observation layout and the centralized training do not transfer; export a policy "
                             f"trained with num_agents={num_drones}")
        if scenario is not None and scenario != bundle.scenario:
            raise ValueError(f"the bundle was trained on scenario {bundle.scenario!r}, not {scenario!r}")
        self.bundle = bundle
        self.n = num_drones
        self.safety = safety
        if estimation.velocity == "model" and estimation.lag is None:
            lag = bundle.velocity_lag
            if lag is None:
                raise ValueError("the bundle does not record its drone's velocity lag, which the model velocity "
                                 "estimate needs: allowed: --velocity-estimate window (EstimatorConfig(velocity="
                                 "'window')), EstimatorConfig(lag=(xy, z)), or a bundle exported with this version")
            estimation = dataclasses.replace(estimation, lag=lag)
        self.estimation = estimation
        env = bundle.env
        self.max_speed = bundle.max_speed
        self._step_limit = bundle.command_accel_limit / bundle.rate_hz  # m/s per control step; 0: no limit
        # The arena as the policy was trained in it: its observation measures the walls of this box.
        self._arena_low, self._arena_high = np.array(env["arena_low"], float), np.array(env["arena_high"], float)
        self.low = np.array(env["arena_low"], float) + safety.geofence_margin
        self.high = np.array(env["arena_high"], float) - safety.geofence_margin
        self.low[2] = -np.inf  # the floor is a barrier of the filter, not a fence (drones start on it)
        self.num_cylinders = int(env["num_cylinders"])
        self.num_gates = int(env["num_gates"])
        self._half_opening = float(env["gate_half_opening"])
        goal_radius = float(env["goal_radius"])
        if bundle.kind != "track" and safety.goal_margin >= goal_radius:
            raise ValueError(f"invalid goal_margin={safety.goal_margin!r}: allowed: 0 <= goal_margin < the bundle's "
                             f"goal radius, {goal_radius:g} m (no pose could finish a drone)")
        self._goal_inside = goal_radius - safety.goal_margin
        self._collision_radius = float(env["collision_radius"])
        # observe's neighbour rows: the safety filter's where it sees more nearest neighbours than the policy
        # (bundle.filter_layout), which then reads their prefix (run_policy).
        self._observed = observed_neighbours(bundle.num_agents, bundle.max_neighbours, bundle.filter_neighbours)
        self._neighbour_accel = bundle.filter_layout.neighbour_accel  # observe's: from each drone's measured attitude
        self._lead: tuple[int, ...] | None = None

    # ------------------------------------------------------------------ course
    def reset(self, gates: np.ndarray | None = None, goals: np.ndarray | None = None) -> None:
        """Start a flight: gates [..., G, 4] rows (x, y, z, yaw rad) for a track, else goals [..., n, 3] (m).

        Leading axes are worlds (none for one swarm). Clears the estimates, progress and landing state.
        """
        kind = self.bundle.kind
        if kind == "track":
            if gates is None:
                raise ValueError(f"scenario kind 'track' needs gates: allowed: an array [..., {self.num_gates}, 4] "
                                 "of (x, y, z, yaw)")
            gates = np.asarray(gates, np.float64)
            if gates.ndim < 2 or gates.shape[-2:] != (self.num_gates, 4) or not np.all(np.isfinite(gates)):
                raise ValueError(f"invalid gates of shape {gates.shape}: allowed: finite [..., {self.num_gates}, 4] "
                                 "rows (x, y, z, yaw), as many gates as the policy was trained with")
            lead = gates.shape[:-2]
            wp = np.broadcast_to(gates[..., None, :, :3], lead + (self.n, self.num_gates, 3))
            nrm = np.broadcast_to(horizontal(gates[..., None, :, 3]), wp.shape)
            self._gates = gates.reshape((-1, self.num_gates, 4))
            # Each gate's centre and direction of passage [B, G, 6], for the crossing test of every step.
            self._gate_geo = np.concatenate([self._gates[..., :3], horizontal(self._gates[..., 3])], -1)
        else:
            if goals is None:
                raise ValueError(f"scenario kind {kind!r} needs goals: allowed: an array [..., {self.n}, 3]")
            goals = np.asarray(goals, np.float64)
            if goals.ndim < 2 or goals.shape[-2:] != (self.n, 3) or not np.all(np.isfinite(goals)):
                raise ValueError(f"invalid goals of shape {goals.shape}: allowed: finite [..., {self.n}, 3]")
            lead = goals.shape[:-2]
            wp = goals[..., None, :]
            nrm = np.zeros_like(wp)
            self._gates = None
        self._lead = lead
        B = int(np.prod(lead, dtype=np.int64))
        self.B = B
        self._wp = np.array(wp).reshape(B, self.n, -1, 3)
        self._normals = np.array(nrm).reshape(B, self.n, -1, 3)
        self._est = estimator.init((B, self.n), self.estimation)
        self._target = np.zeros((B, self.n), np.int64)
        self._finished = np.zeros((B, self.n), bool)
        self._armed = np.zeros((B, self.n), bool)  # the gate-crossing trigger (GATE_ARM_DISTANCE)
        self._landing = np.zeros((B, self.n), bool)
        # The commands sent over the oldest pose that is still fresh and one pose interval more: the model estimate's
        # input; the newest is the acceleration limit's start.
        slots = estimator.Commands.slots(self.safety.stale_after, self.bundle.rate_hz)
        self._sent = estimator.Commands.empty((B,), self.n, slots)
        self._p_now = np.zeros((B, self.n, 3))  # where the drones were at the last step, as the policy saw them
        self._obstacles = np.zeros((B, self.num_cylinders, 2))
        self._known = np.zeros((B, self.num_cylinders), bool)
        self._flags = np.zeros((len(EVENT_KINDS), B, self.n), bool)
        self._rows = np.arange(B)[:, None]
        self._t_reset: np.ndarray | None = None
        # What _obstacle_arrays returns without obstacles, and its every-obstacle-present flags (read-only).
        M = self.num_cylinders
        self._no_obstacles = tuple(_read_only(a) for a in (np.zeros((B, M, 2)), np.zeros((B, M, 2)), np.zeros((B, M)),
                                                           np.zeros((B, M), bool), np.zeros((B, self.n), bool)))
        self._all_present = _read_only(np.ones((B, M), bool))

    # ------------------------------------------------------------------ step
    def step(self, positions, quats, timestamps, now=None, obstacles: Obstacles | None = None,
             hold=None) -> StepResult:
        """One control step. positions [..., n, 3] (m, world), quats [..., n, 4] (wxyz, body->world),
        timestamps [..., n] or broadcastable (s, the clock of ``now``); NaN marks a missing pose.
        ``now`` [...] or scalar (default: the newest timestamp). ``hold`` [..., n] bool: drones not released yet
        (staggered starts, ``EnvConfig.start_interval``): a zero command, as the simulator gives them, and the
        estimates know it. Returns a :class:`StepResult`.
        """
        if self._lead is None:
            raise ValueError("call reset(gates=... or goals=...) before step")
        lead, n, B = self._lead, self.n, self.B
        pos = self._batched(positions, (n, 3), "positions")
        quat = self._batched(quats, (n, 4), "quats")
        ts = _shaped(timestamps, lead + (n,), np.float64).reshape(B, n)
        qn = np.sqrt((quat * quat).sum(-1))
        valid = np.isfinite(pos).all(-1) & np.isfinite(ts) & (qn > 0.5) & (qn < 2.0)  # NaN compares false
        # Unit quaternions with w >= 0: q and -q are the same attitude, and the simulator's start at
        # [1, 0, 0, 0] keeps w > 0 for any attitude a flying drone reaches.
        sign = np.where(quat[:, :, 0] < 0, -1.0, 1.0)
        if valid.all():  # the usual case: the same numbers as below without the masking
            quat = quat * (sign / qn)[:, :, None]
        else:
            scale = np.where(valid, sign / np.where(valid, qn, 1.0), 0.0)
            quat = np.where(valid[:, :, None], quat * scale[:, :, None], 0.0)
            pos = np.where(valid[:, :, None], pos, 0.0)
            ts = np.where(valid, ts, -np.inf)
        if now is None:
            now_b = np.maximum(ts.max(-1), self._est.t[:, :, -1].max(-1))
            now_b = np.where(np.isfinite(now_b), now_b, 0.0)
        else:
            now_b = _shaped(now, lead, np.float64).reshape(B)
        if self._t_reset is None:
            self._t_reset = now_b.copy()

        prev_seen = self._est.count > 0
        prev_pos = self._est.pos[:, :, -1]
        self._est, accepted, glitch = estimator.update(self._est, ts, pos, quat, valid, self.estimation, self._sent)
        seen = self._est.count > 0
        t_last, p, q = estimator.latest(self._est)
        out_of_fence = ((p < self.low) | (p > self.high)).any(-1)
        if seen.all():  # every drone has had a pose (in flight): what the masking below gives then
            age = now_b[:, None] - t_last
            stale = age > self.safety.stale_after
            blind = ~valid | glitch | stale
            fence = out_of_fence
        else:
            age = now_b[:, None] - np.where(seen, t_last, self._t_reset[:, None])
            stale = seen & (age > self.safety.stale_after)
            blind = ~(seen & valid) | glitch | stale
            fence = seen & out_of_fence

        vel, ang = estimator.estimate(self._est, self.estimation)
        p_now, track_from = p, prev_pos
        if self.estimation.velocity == "model" and self.estimation.predict:
            # The present as the model has it: the policy sees it, and the gates are passed in it (with old poses
            # the next gate would show a control step late, a drone already through the last one).
            p_now, vel = estimator.predict(self._est, now_b, self._sent, self.estimation)
            track_from = self._p_now
        self._p_now = p_now

        # Progress along the course, on fresh poses only (the simulator's crossing test).
        moved = accepted & prev_seen & ~self._finished
        if self._gates is not None:
            k = np.minimum(self._target, self.num_gates - 1)
            gate = self._gate_geo[self._rows, k]  # [B, n, 6]
            centre, normal = gate[..., :3], gate[..., 3:]
            armed = self._armed | (moved & (np.sum((track_from - centre) * normal, -1) < -GATE_ARM_DISTANCE))
            crossed = moved & armed & gate_crossed(track_from, p_now, centre + GATE_PASS_DISTANCE * normal, normal,
                                                   self._half_opening)
            # Past the firing plane, through the opening or beside it: the drone must come back before the gate.
            beyond = np.sum((p_now - centre) * normal, -1) >= GATE_PASS_DISTANCE
            self._armed = armed & ~crossed & ~(beyond & moved)
            self._target = self._target + crossed
            reached = self._target >= self.num_gates
        else:
            # A goal is reached on the newest measured pose, not on the present the model predicts from it: a pose in
            # the goal says the drone was there (to the mocap's noise), while a prediction millimetres off (latency, the
            # model's error) finished drones that only grazed their goal, stopped them outside it and lost the episode
            # (README, "Goals on measured poses").
            d = p - self._wp[:, :, 0]
            reached = moved & ((d * d).sum(-1) < self._goal_inside**2)
        newly_finished = reached & ~self._finished
        self._finished |= reached
        self._landing |= self._finished | fence | (blind & (age > self.safety.land_after))

        cyl_pos, cyl_vel, cyl_radius, cyl_present, lost_obstacles = self._obstacle_arrays(obstacles)
        flying = seen & ~self._finished if not self.safety.finished_are_neighbours else seen
        obs = observe(p_now, q, vel, ang, self._wp, self._normals, self._target, flying, cyl_pos, cyl_vel, cyl_radius,
                      cyl_present, self._collision_radius, self._arena_low, self._arena_high, self._observed,
                      self._neighbour_accel)
        pol = run_policy(self.bundle, obs, self._obstacle_accel(obstacles), self._sent.u[-1])

        u = pol.u
        nonfinite = ~np.isfinite(u).all(-1)
        hover = blind | self._landing | nonfinite
        if hold is not None:
            hover = hover | _shaped(hold, lead + (n,), bool).reshape(B, n)
        u = np.where(hover[:, :, None], 0.0, u)
        np.maximum(u, -self.max_speed, out=u)  # np.clip, in place
        np.minimum(u, self.max_speed, out=u)
        if self._step_limit:  # the simulator's command acceleration limit (EnvConfig.command_accel_limit)
            u = limit_change(u, self._sent.u[-1], self._step_limit)
        self._sent = self._sent.sent(now_b, u)

        # One row per EVENT_KINDS entry, written in place (np.stack of small arrays costs several times more).
        flags = np.empty((len(EVENT_KINDS), B, n), bool)
        np.invert(valid, out=flags[0])
        flags[1], flags[2], flags[3], flags[4], flags[5], flags[6] = (stale, glitch, fence, self._landing,
                                                                      newly_finished, nonfinite)
        np.greater(pol.intervened, pol.converged | hover, out=flags[7])  # intervened & ~converged & ~hover
        flags[8] = lost_obstacles
        start = flags > self._flags  # flags & ~previous flags
        self._flags = flags
        events = []
        if start.any():
            for kind, w, dr in zip(*np.nonzero(start)):
                detail = f"pose age {age[w, dr]:.3f} s" if EVENT_KINDS[kind] == "stale_pose" else ""
                events.append(Event(world=int(w), drone=int(dr), kind=EVENT_KINDS[kind], time=float(now_b[w]),
                                    detail=detail))

        def out(a):
            return a.reshape(lead + a.shape[1:])

        return StepResult(velocity=out(u), land=out(self._landing.copy()), hover=out(hover), events=events,
                          nominal=out(pol.nominal), intervened=out(pol.intervened > hover), gain=out(pol.gain),
                          target=out(self._target.copy()), finished=out(self._finished.copy()), obs=out(obs),
                          position=out(self._p_now.copy()))

    # ------------------------------------------------------------------ parts
    def _batched(self, x, tail: tuple[int, ...], name: str) -> np.ndarray:
        x = np.asarray(x, np.float64)
        want = self._lead + tail
        if x.shape != want:
            raise ValueError(f"{name} has shape {x.shape}: allowed shape is {want}")
        return x.reshape((self.B,) + tail)

    def _obstacle_accel(self, obstacles: Obstacles | None) -> np.ndarray | None:
        """[B, M] the obstacles' acceleration bounds (absent slots 0), or None where none was given."""
        if obstacles is None or obstacles.accel is None:
            return None
        m = np.shape(obstacles.pos)[-2]
        acc = _shaped(obstacles.accel, self._lead + (m,), np.float64).reshape(self.B, m)
        if not (np.isfinite(acc).all() and (acc >= 0).all()):
            raise ValueError(f"invalid obstacles.accel={np.asarray(obstacles.accel).tolist()!r}: allowed: finite "
                             "bounds >= 0 m/s^2")
        out = np.zeros((self.B, self.num_cylinders))
        out[:, :m] = acc
        return out

    def _obstacle_arrays(self, obstacles: Obstacles | None):
        """(pos [B, M, 2], vel [B, M, 2], radius [B, M], present [B, M], lost [B, n]) as observe takes them."""
        if obstacles is None:
            return self._no_obstacles
        if not isinstance(obstacles, Obstacles):  # a bare array has no radius: say what to pass
            raise TypeError(f"obstacles is a {type(obstacles).__name__}: allowed: None or "
                            "Obstacles(pos=[..., M, 2], radius=[..., M], vel=None, present=None)")
        B, M = self.B, self.num_cylinders
        op = np.asarray(obstacles.pos, np.float64)
        m = op.shape[-2] if op.ndim >= 2 else -1
        if op.shape != self._lead + (m, 2) or m < 0:
            raise ValueError(f"obstacles.pos has shape {op.shape}: allowed shape is {self._lead + (M, 2)} "
                             f"(at most {M} cylinders)")
        if m > M:
            raise ValueError(f"{m} obstacles but the policy observes at most {M}: flying blind to the others "
                             "is unsafe; export a policy trained with more cylinders or remove some")
        op = op.reshape(B, m, 2)
        rad = _shaped(obstacles.radius, self._lead + (m,), np.float64).reshape(B, m)
        ov = (None if obstacles.vel is None
              else _shaped(obstacles.vel, self._lead + (m, 2), np.float64).reshape(B, m, 2))
        seen = np.isfinite(op).all(-1)
        if obstacles.present is None and m == M and seen.all():
            # The usual case, every step: all M obstacles present and seen. What the general case
            # below computes then, without its masking.
            if not (rad >= 0).all() or not np.isfinite(rad).all():
                raise ValueError("obstacles.radius must be finite and >= 0 for every present obstacle")
            self._obstacles[:] = op
            self._known[:] = True
            vel = self._no_obstacles[1] if ov is None else np.where(np.isfinite(ov), ov, 0.0)
            return op, vel, rad, self._all_present, self._no_obstacles[4]
        pr = (np.ones((B, m), bool) if obstacles.present is None
              else _shaped(obstacles.present, self._lead + (m,), bool).reshape(B, m))
        if np.any(pr & ~(np.isfinite(rad) & (rad >= 0))):
            raise ValueError("obstacles.radius must be finite and >= 0 for every present obstacle")
        good = pr & seen
        # A present obstacle whose pose went missing stays where it was last seen (obstacles
        # are static or slow); one never seen cannot be avoided: reported to every drone.
        self._obstacles[:, :m] = np.where(good[..., None], op, self._obstacles[:, :m])
        self._known[:, :m] |= good
        use = pr & self._known[:, :m]
        pos = np.zeros((B, M, 2))
        vel = np.zeros((B, M, 2))
        radius = np.zeros((B, M))
        present = np.zeros((B, M), bool)
        pos[:, :m] = np.where(use[..., None], self._obstacles[:, :m], 0.0)
        if ov is not None:
            vel[:, :m] = np.where(good[..., None] & np.isfinite(ov), ov, 0.0)
        radius[:, :m] = np.where(use, rad, 0.0)
        present[:, :m] = use
        lost = np.repeat(np.any(pr & ~good, -1)[:, None], self.n, 1)
        return pos, vel, radius, present, lost


def filter_commands(bundle: Bundle, obs: np.ndarray, cmd: np.ndarray, gain: np.ndarray,
                    cyl_accel: np.ndarray | None = None, applied: np.ndarray | None = None) -> cbf.FilterResult:
    """The bundle's safety filter on raw observations [..., n, D] (``bundle.filter_layout``) and commands
    [..., n, 3]; cyl_accel [..., M]; applied [..., n, 3] the commands sent last (for a filter with ``braking``)."""
    sf = bundle.safety_filter
    return cbf.filter_from_obs(bundle.filter_layout, obs, cmd, gain, bundle.max_speed, float(sf["drone_radius"]),
                               bundle.safety, float(sf["gate_half_opening"]), float(sf["gate_bar"]), cyl_accel,
                               applied, (bundle.command_accel_limit, 1.0 / bundle.rate_hz))


def _read_only(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _shaped(x, shape: tuple[int, ...], dtype) -> np.ndarray:
    """``x`` as an array of ``shape`` (broadcast only when needed: this runs every control step)."""
    x = np.asarray(x, dtype)
    return x if x.shape == shape else np.broadcast_to(x, shape)


@dataclasses.dataclass(frozen=True)
class PolicyOutput:
    nominal: np.ndarray  # [..., n, 3] actor command
    u: np.ndarray  # [..., n, 3] after the safety filter (= nominal without one)
    gain: np.ndarray  # [..., n] class-K gain (1/s)
    intervened: np.ndarray  # [..., n] bool
    converged: np.ndarray  # [..., n] bool


def run_policy(bundle: Bundle, obs: np.ndarray, cyl_accel: np.ndarray | None = None,
               applied: np.ndarray | None = None) -> PolicyOutput:
    """Normalizer, actor, gain and filter on raw observations [..., n, D]: what ``Agent.act`` computes in JAX
    (``cyl_accel`` [..., M]: the cylinders' acceleration bounds, m/s²; ``applied`` [..., n, 3]: the commands sent
    last, which a filter with ``braking`` starts from). The observations are in
    ``bundle.filter_layout``: the policy's own, or with the filter's extra nearest neighbours after the policy's
    (``EnvConfig.filter_neighbours``), of which the networks read the prefix."""
    sf, w = bundle.safety_filter, bundle.weights
    wide, size = obs, bundle.layout.size
    if obs.shape[-1] != bundle.filter_layout.size:
        raise ValueError(f"observations of size {obs.shape[-1]}: this bundle's are {bundle.filter_layout.size}"
                         + (f" (the policy reads the first {size})" if size != bundle.filter_layout.size else ""))
    if size != obs.shape[-1]:
        obs = obs[..., :size]
    nobs = policy.normalize(w, obs)
    cmd = policy.actor_command(w, nobs, bundle.max_speed)
    if sf.get("gain_source") == "attention":
        gain = policy.cbf_gain(w, bundle.layout, nobs, obs, gain_min=bundle.safety.gain_min,
                               gain_max=bundle.safety.gain_max)
    else:
        gain = np.full(obs.shape[:-1], bundle.safety.fixed_gain)
    if not sf["enabled"]:
        off = np.zeros(obs.shape[:-1], bool)
        return PolicyOutput(nominal=cmd, u=cmd, gain=gain, intervened=off, converged=~off)
    res = filter_commands(bundle, wide, cmd, gain, cyl_accel, applied)
    return PolicyOutput(nominal=cmd, u=res.u, gain=gain, intervened=res.intervened, converged=res.converged)


def act(bundle: Bundle, obs: np.ndarray, cyl_accel: np.ndarray | None = None,
        applied: np.ndarray | None = None) -> np.ndarray:
    """Deterministic, filtered commands [..., n, 3] from raw observations (``Agent.act``)."""
    return run_policy(bundle, obs, cyl_accel, applied).u
