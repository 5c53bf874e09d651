"""The swarm environment: pure ``reset(key, params=None)`` and ``step(state, action)``.

``EnvConfig`` fixes the shapes and the program; ``EnvParams`` (``params.py``: physical constants, controller
gains, reward weights, margin, speed limit, obstacle motion) are data that ``reset`` stores in the state and
``step`` reads, so one compiled program serves many values (vmap ``reset`` over a batch of params).

One env step (``1 / policy_freq`` s) holds the velocity command (late by the episode's latency, in
controller ticks), runs the onboard controller's outer loop at ``ctrl_freq`` (the firmware's velocity PID,
or the geometric controller) and, every physics step, its attitude and rate loops (firmware PID), the rotor
lag and MJX physics at ``sim_freq``, all inside ``lax.scan``; collisions, gate crossings and goal arrivals are
checked after every physics step. With domain randomisation (``config.randomize``) ``reset`` draws the
episode's drone (``Onboard.params``) around the nominal parameters, and the policy sees observations built
from noisy positions (the critic's are exact). A drone that completes its mission leaves the course (it
stops and no longer counts for collisions or as a neighbour), as a finished
drone lands in real flights. Track starts can be staggered (``start_interval``): a drone
hovers where it is, earning nothing, until its release time. The episode terminates when every drone has
finished or any drone collides, and is truncated at ``episode_seconds``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from aswarm.core import geometry as geo
from aswarm.core.command import advance_reference, setpoint_position
from aswarm.core.command import limit_change as limit_command_change
from aswarm.core.estimation import slope_weights
from aswarm.core.layout import ObsLayout, neighbour_slots, observed_neighbours
from aswarm.core.observation import observe
from aswarm.envs import collisions as col
from aswarm.envs import firmware_mellinger, firmware_pid, randomization
from aswarm.envs.config import EnvConfig
from aswarm.envs.crazyflie import SPIN_DOWN_REFERENCE_RPM
from aswarm.envs.dynamics import (
    DroneState,
    drone_state,
    physics_model,
    physics_step,
    quat_to_rotmat,
    rotor_lag,
    set_drone_state,
)
from aswarm.envs.mjx_import import mjx
from aswarm.envs.onboard_controller import velocity_controller
from aswarm.envs.params import EnvParams
from aswarm.envs.params import check as check_params
from aswarm.envs.presets import SCENARIOS
from aswarm.envs.scenarios import Layout, cylinders_at, geometry, sample_layout


@struct.dataclass
class Tracker:
    """Per-episode progress and accumulators; leading axis is the drone."""

    target: jax.Array  # [n] int32, index of the current waypoint
    finished: jax.Array  # [n] bool
    collided: jax.Array  # [n] bool
    collision_kind: jax.Array  # [n] int32, collisions.KINDS
    min_clearance: jax.Array  # [n] m, to cylinders
    separation_sum: jax.Array  # [n] sum over steps of the nearest-neighbour distance
    speed_sum: jax.Array  # [n]
    finish_time: jax.Array  # [n] s (episode time while not finished)
    episode_return: jax.Array  # [n]
    steps: jax.Array  # [] int32


@struct.dataclass
class Onboard:
    """What sits between the policy and the rigid bodies, per drone: the onboard controller's memory, the rotor
    speeds, the commands still on their way and the poses motion capture still has to hand over."""

    pid: firmware_pid.PidState | None  # controller "pid"; None for "geometric" (it has no memory)
    rpm: jax.Array  # [n, 4] rotor speeds (RPM), lagging their commands where cf.motor_tau > 0
    commands: jax.Array  # [2, n, 3] the velocity commands of the last two policy steps, the newest first
    obs_history: jax.Array  # [max_delay, n, obs_dim] the last observations (with filter_obs's rows), newest first
    key: jax.Array  # draws the motion-capture noise of each step
    params: EnvParams | None  # this episode's draw (domain randomisation); None where nothing is drawn
    # [velocity_window, n, 3] the noisy positions the seen velocities are fitted to, the newest first; None
    # where the policy sees the true velocities
    pos_history: jax.Array | None = None
    mellinger: firmware_mellinger.MellingerState | None = None  # controller "mellinger"
    # [3, n, 3] controller "mellinger": where the full-state setpoints of this policy step and of the last two
    # start (the velocity commands integrated, core.command), the newest first
    reference: jax.Array | None = None


@struct.dataclass
class State:
    """Brax / MuJoCo Playground style state of one world."""

    data: mjx.Data  # physics of record
    obs: jax.Array  # [n_agents, obs_dim]
    critic_obs: jax.Array  # [critic_obs_dim] centralized critic input (all rows of obs)
    reward: jax.Array  # [n_agents]
    cost: jax.Array  # [n_agents] in [0, 1]: 1 at collision, rising as clearance falls below the margin
    done: jax.Array  # [] float, terminated or truncated
    truncated: jax.Array  # [] float, time limit reached (not a terminal state)
    layout: Layout
    tracker: Tracker
    metrics: dict
    info: dict
    # What step reads that may vary per world (reset stores them; auto-reset keeps them). None: the config's
    # defaults, read as constants compiled into the program, as before they were data: XLA folds and reorders
    # constant arithmetic (reciprocals, products of gains), so they give other last bits than the same values
    # as data; None keeps the numbers of every run and checkpoint made before this split.
    params: EnvParams | None
    onboard: Onboard
    # [n_agents, filter obs_dim] what the safety filter sees where it takes more neighbours than the policy
    # (EnvConfig.filter_neighbours): the observation with the filter's nearest rows (SwarmEnv.filter_layout), whose
    # prefix is ``obs``. None where the filter takes the policy's rows, from ``obs``.
    filter_obs: jax.Array | None = None


class SwarmEnv:
    """A scenario's swarm environment. Use :func:`aswarm.envs.make` to build one."""

    def __init__(self, config: EnvConfig):
        self.config = config
        self.geometry = geometry(config)  # raises if the obstacles cannot be placed
        self.kind = SCENARIOS[config.scenario].kind
        self.mj_model, self.mjx_model = physics_model(config.num_agents, config.sim_freq, config.cf)
        self._data0 = mjx.make_data(self.mjx_model, device=jax.local_devices()[0])  # see physics_model
        n = config.num_agents
        k_policy, k_filter = neighbour_slots(n, config.max_neighbours, config.filter_neighbours)
        self.obs_layout = ObsLayout(num_cylinders=config.num_cylinders, num_neighbours=k_policy)
        # The safety filter's rows (State.filter_obs): the policy's, or more nearest neighbours, or with the
        # neighbours' accelerations (static choices: without them every program traces as before the fields).
        self.filter_layout = ObsLayout(num_cylinders=config.num_cylinders, num_neighbours=k_filter,
                                       neighbour_accel=config.filter_neighbour_accel)
        self.wide_filter = self.filter_layout != self.obs_layout
        self._observed = observed_neighbours(n, config.max_neighbours, config.filter_neighbours)  # observe's argument
        stagger = config.start_interval if self.kind == "track" else 0.0
        self._release_time = np.arange(n, dtype=np.float32) * stagger - 1e-6
        self.default_params = EnvParams.from_config(config)
        self.randomize = config.randomize.enabled
        self.lag = config.cf.motor_tau > 0
        self.lag_down = config.cf.motor_tau_down > 0
        self.drag = any(c > 0 for c in config.cf.drag)
        self.ticks = config.substeps // config.ctrl_every  # onboard-controller ticks per policy step
        # The rotor speed the firmware's thrust map commands, per sqrt(thrust): the nominal drone's kf.
        self._kf_nominal = float(config.cf.kf)
        # The velocity estimate's weights over the last W noisy positions, the newest first (core.estimation).
        w = config.randomize.velocity_samples
        self._velocity_weights = (jnp.asarray(slope_weights(-np.arange(w, dtype=np.float64) / config.policy_freq),
                                              jnp.float32) if w else None)

    # Sizes, as MuJoCo Playground names them.
    @property
    def num_agents(self) -> int:
        return self.config.num_agents

    @property
    def observation_size(self) -> int:
        return self.obs_layout.size

    @property
    def critic_observation_size(self) -> int:
        return self.num_agents * self.observation_size

    @property
    def action_size(self) -> int:
        return 3

    @property
    def num_waypoints(self) -> int:
        return self.config.num_gates if self.kind == "track" else 1

    # ------------------------------------------------------------------ reset
    def reset(self, key: jax.Array, params: EnvParams | None = None) -> State:
        """A new episode; ``params`` (None: the config's, ``default_params``, compiled in) are kept in the state
        for ``step``. vmap over both ``key`` and ``params`` to run one compiled program for many values."""
        cfg = self.config
        n = cfg.num_agents
        if params is not None:
            params = check_params(params, self.default_params)
        # fold_in leaves `key` itself to the layout, as before anything else was drawn from it.
        drawn = (randomization.sample(jax.random.fold_in(key, 1), self.params(params), cfg.randomize, self.ticks)
                 if self.randomize else None)
        p = drawn if drawn is not None else self.params(params)
        layout = sample_layout(key, cfg, self.geometry, p.moving_amplitude, p.moving_omega)
        drones = DroneState(
            pos=layout.start_pos,
            quat=jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (n, 1)),
            vel=jnp.zeros((n, 3)),
            ang_vel=jnp.zeros((n, 3)),
        )
        data = set_drone_state(self._data0, drones)
        zeros = jnp.zeros(n)
        tracker = Tracker(
            target=jnp.zeros(n, jnp.int32), finished=jnp.zeros(n, bool), collided=jnp.zeros(n, bool),
            collision_kind=jnp.zeros(n, jnp.int32), min_clearance=jnp.full(n, geo.FAR, jnp.float32),
            separation_sum=zeros, speed_sum=zeros, finish_time=zeros, episode_return=zeros,
            steps=jnp.zeros((), jnp.int32),
        )
        hover_rpm = jnp.sqrt(p.cf.mass * cfg.cf.gravity / (4 * p.cf.kf))
        pid = mel = reference = None
        if cfg.controller != "geometric":  # the firmware's controllers start from the thrust that holds the drone
            hover = firmware_pid.hover_thrust(p.cf.mass * cfg.cf.gravity, p.cf.kf / self._kf_nominal, p.pid)
        if cfg.controller == "pid":
            pid = firmware_pid.initial_state(drones.quat, drones.ang_vel, hover, p.pid)
        elif cfg.controller == "mellinger":
            mel = firmware_mellinger.initial_state(drones.ang_vel, hover, p.mellinger)
            reference = jnp.broadcast_to(drones.pos, (3,) + drones.pos.shape)
        obs = self._observe(drones, layout, tracker, jnp.zeros(()))  # the filter's (wider, or the policy's)
        w = self._velocity_weights
        history = None if w is None else jnp.broadcast_to(drones.pos, (w.shape[0],) + drones.pos.shape)
        onboard = Onboard(pid=pid, rpm=jnp.broadcast_to(hover_rpm, (n, 4)), commands=jnp.zeros((2, n, 3)),
                          obs_history=jnp.broadcast_to(obs, (cfg.randomize.max_delay,) + obs.shape),
                          key=jax.random.fold_in(key, 2), params=drawn,
                          pos_history=history, mellinger=mel, reference=reference)
        seen, onboard = self._mocap(onboard, obs, drones, layout, tracker, jnp.zeros(()), p)
        state = State(data=data, obs=self._policy_view(seen), critic_obs=self._policy_view(obs).reshape(-1),
                      reward=zeros, cost=zeros, done=jnp.zeros(()), truncated=jnp.zeros(()), layout=layout,
                      tracker=tracker, metrics={}, info={}, params=params, onboard=onboard,
                      filter_obs=seen if self.wide_filter else None)
        return state.replace(metrics=self._metrics(tracker))

    # ------------------------------------------------------------------- step
    def step(self, state: State, action: jax.Array) -> State:
        """Advance one policy step; ``action`` [n_agents, 3] are world-frame velocity commands (m/s)."""
        cfg = self.config
        n = cfg.num_agents
        self.check_action(action)
        # Inside jit a NaN cannot raise; a NaN command becomes a hover command.
        p = self.episode_params(state)
        cmd = jnp.clip(jnp.nan_to_num(action, nan=0.0), -p.max_speed, p.max_speed)
        tr0 = state.tracker
        active0 = self.flying(state)
        cmd = jnp.where(active0[:, None], cmd, 0.0)
        if cfg.command_accel_limit:  # (static, as the rate penalty)
            cmd = limit_command_change(cmd, state.onboard.commands[0], p.command_step_limit)
        layout = state.layout
        normals = geo.horizontal(layout.gate_yaw)  # the gates' directions of passage, once a step
        p0 = drone_state(state.data, n).pos
        ob = state.onboard
        dt_ctrl, dt_sim = 1.0 / cfg.ctrl_freq, 1.0 / cfg.sim_freq

        def physics(d, rpm_cmd, rpm):
            if self.lag:
                down = p.cf.motor_tau_down if self.lag_down else None
                rpm = rotor_lag(rpm, rpm_cmd, p.cf.motor_tau, dt_sim, down, SPIN_DOWN_REFERENCE_RPM)
            else:
                rpm = rpm_cmd
            return physics_step(self.mjx_model, d, rpm, p.cf, self.drag), rpm

        if ob.mellinger is not None:
            # The full-state setpoints' positions for this step's command and the last two's (latency).
            sp = setpoint_position(ob.reference, jnp.concatenate([cmd[None], ob.commands]), cfg.dt)

        def control(carry, tick):
            data, pid, mel, rpm, tr, hazard = carry
            now = self._command(cmd, ob.commands, tick, p) if self.latency else cmd
            s = drone_state(data, n)
            if pid is not None:
                pid = firmware_pid.velocity_loop(pid, s.quat, s.vel, now, p.pid, dt_ctrl)
            elif mel is not None:
                sp_pos = self._command(sp[0], sp[1:], tick, p) if self.latency else sp[0]
            else:
                rpm_cmd = velocity_controller(s, now, p.gains, p.cf)

            def inner(c, _):
                d, pid, mel, rpm, t, h = c
                prev = drone_state(d, n)
                if pid is not None:
                    pid, motors = firmware_pid.attitude_loop(pid, prev.quat, prev.ang_vel, p.pid, dt_sim)
                    target = firmware_pid.motor_rpm(motors, p.pid, self._kf_nominal)
                elif mel is not None:
                    mel, motors = firmware_mellinger.control(mel, quat_to_rotmat(prev.quat), prev.ang_vel, prev.pos,
                                                             prev.vel, sp_pos, now, p.mellinger, dt_sim)
                    target = firmware_pid.motor_rpm(motors, p.pid, self._kf_nominal)
                else:
                    target = rpm_cmd
                d, rpm = physics(d, target, rpm)
                t, hz = self._check(prev.pos, drone_state(d, n).pos, d.time, layout, normals, t)
                return (d, pid, mel, rpm, t, jnp.minimum(h, hz)), None

            return jax.lax.scan(inner, (data, pid, mel, rpm, tr, hazard), None, length=cfg.ctrl_every)[0], None

        (data, pid, mel, rpm, tr, hazard), _ = jax.lax.scan(
            control, (state.data, ob.pid, ob.mellinger, ob.rpm, tr0, jnp.full(n, geo.FAR)), jnp.arange(self.ticks)
        )
        drones = drone_state(data, n)
        ob = ob.replace(pid=pid, mellinger=mel, rpm=rpm, commands=jnp.stack([cmd, ob.commands[0]]))
        if mel is not None:
            ahead = advance_reference(ob.reference[0], cmd, cfg.dt, drones.pos, p.reference_leash)
            ob = ob.replace(reference=jnp.concatenate([ahead[None], ob.reference[:2]]))

        t = data.time
        if cfg.moving_cost_horizon:  # (static: without it the program is the one it always was)
            hazard = jnp.minimum(hazard, self._cylinder_reach(drones.pos, layout, t, tr.finished))
        newly_finished = tr.finished & ~tr0.finished
        newly_collided = tr.collided & ~tr0.collided
        passed = (tr.target - tr0.target).astype(jnp.float32)

        # Reward, per drone flying at the start of the step.
        if cfg.reward == "paper":
            d = jnp.linalg.norm(drones.pos - self._target_pos(layout, tr.target), axis=-1)
            reward = 1.0 / (d + p.paper_epsilon)
        else:
            progress = self._to_go(p0, layout, tr0.target, p) - self._to_go(drones.pos, layout, tr0.target, p)
            reward = (p.progress_weight * progress + p.gate_bonus * passed
                      + p.finish_bonus * newly_finished - p.time_penalty_per_step)
        if cfg.command_rate_penalty:  # (a static choice: without it the program is the one it always was)
            change = cmd - state.onboard.commands[0]
            reward = reward - p.command_rate_penalty * jnp.sum(change * change, axis=-1)
        reward = jnp.where(newly_collided, -p.collision_penalty, reward)
        reward = jnp.where(active0, reward, 0.0)
        # Times the reciprocal: what XLA compiled the division by the constant margin into before it was data.
        cost = jnp.clip((p.safety_margin - hazard) * (1.0 / p.safety_margin), 0.0, 1.0)
        cost = jnp.where(active0, jnp.where(tr.collided, 1.0, cost), 0.0)

        # Episode statistics.
        speed = jnp.linalg.norm(drones.vel, axis=-1)
        nearest = jnp.min(geo.drone_clearance(drones.pos, jnp.ones(n, bool), 0.0), axis=-1, initial=geo.FAR)
        tr = tr.replace(
            separation_sum=tr.separation_sum + jnp.where(n > 1, nearest, 0.0),
            speed_sum=tr.speed_sum + jnp.where(active0, speed, 0.0),
            finish_time=jnp.where(tr.finished, tr.finish_time, t),
            episode_return=tr.episode_return + reward,
            steps=tr.steps + 1,
        )
        terminated = jnp.all(tr.finished) | jnp.any(tr.collided)
        truncated = (tr.steps >= cfg.max_steps) & ~terminated
        obs = self._observe(drones, layout, tr, t)
        seen, ob = self._mocap(ob, obs, drones, layout, tr, t, p)
        return state.replace(
            data=data, obs=self._policy_view(seen), critic_obs=self._policy_view(obs).reshape(-1), reward=reward,
            cost=cost, done=(terminated | truncated).astype(jnp.float32), truncated=truncated.astype(jnp.float32),
            tracker=tr, metrics=self._metrics(tr), onboard=ob, filter_obs=seen if self.wide_filter else None,
        )

    # --------------------------------------------------------------- helpers
    def params(self, params: EnvParams | None) -> EnvParams:
        """The parameters a state's ``params`` stand for: ``default_params`` where None."""
        return self.default_params if params is None else params

    def episode_params(self, state: State) -> EnvParams:
        """What this episode flies with: its domain-randomisation draw, or the state's ``params``."""
        return state.onboard.params if state.onboard.params is not None else self.params(state.params)

    @property
    def latency(self) -> bool:
        return self.config.randomize.max_latency > 0

    def _command(self, cmd: jax.Array, earlier: jax.Array, tick: jax.Array, p: EnvParams) -> jax.Array:
        """The velocity command (or setpoint position) the onboard controller holds at ``tick`` of this policy
        step when commands arrive ``p.latency_ticks`` ticks late: this step's, or one of the last two steps'."""
        age = tick - p.latency_ticks  # < 0: still the command of an earlier step
        return jnp.where(age >= 0, cmd, jnp.where(age >= -self.ticks, earlier[0], earlier[1]))

    def _mocap(self, ob: Onboard, obs: jax.Array, drones: DroneState, layout: Layout, tr: Tracker, t,
               p: EnvParams) -> tuple[jax.Array, Onboard]:
        """What the policy sees: the observation built from noisy positions (``p.mocap_noise``), handed over
        ``p.mocap_delay`` policy steps late. Without randomisation, ``obs`` itself."""
        if not self.randomize:
            return obs, ob
        key, k = jax.random.split(ob.key)
        sensed = drones.replace(pos=drones.pos + p.mocap_noise * jax.random.normal(k, drones.pos.shape))
        if self._velocity_weights is not None:
            history = jnp.concatenate([sensed.pos[None], ob.pos_history[:-1]])
            sensed = sensed.replace(vel=jnp.tensordot(self._velocity_weights, history, axes=1))
            ob = ob.replace(pos_history=history)
        fresh = self._observe(sensed, layout, tr, t)
        seen = jnp.concatenate([fresh[None], ob.obs_history])  # [k]: the observation of k steps ago
        delayed = seen[jnp.minimum(p.mocap_delay, ob.obs_history.shape[0]).astype(jnp.int32)]
        return delayed, ob.replace(obs_history=seen[:ob.obs_history.shape[0]], key=key)

    def _policy_view(self, obs: jax.Array) -> jax.Array:
        """The policy's observation [..., n, D] from the filter's: its first D columns (the nearest rows first)."""
        return obs[..., :self.observation_size] if self.wide_filter else obs

    def cylinder_accel(self, state: State) -> jax.Array | None:
        """[..., M] each cylinder's acceleration bound (m/s², 0 if static) for the safety filter; None where no
        cylinder moves (a static choice: those filters trace as they did before the bounds). A batch of states too."""
        if self.config.num_moving == 0:
            return None
        return geo.cylinder_accel_bound(state.layout.cyl_amplitude, state.layout.cyl_omega)

    def applied_command(self, state: State) -> jax.Array:
        """[..., n, 3] the velocity commands the drones fly now (after the command acceleration limit): where the
        next command starts from. A batch of states too."""
        return state.onboard.commands[..., 0, :, :]

    def flying(self, state: State) -> jax.Array:
        """[..., n] bool: drones not finished and released (staggered track starts); the others hover and
        earn neither reward nor cost. Works on a batch of states too."""
        return ~state.tracker.finished & (state.data.time[..., None] >= self._release_time)

    def check_action(self, action) -> None:
        """Raise ``ValueError`` for an action of the wrong shape, or (outside jit) with NaN/Inf."""
        want = (self.num_agents, 3)
        if tuple(np.shape(action)) != want:
            raise ValueError(f"action has shape {tuple(np.shape(action))}: allowed shape is {want} "
                             "(one world-frame velocity command [vx, vy, vz] per drone)")
        if not isinstance(action, jax.core.Tracer) and not np.all(np.isfinite(np.asarray(action))):
            raise ValueError(f"action contains NaN or Inf: {np.asarray(action).tolist()}; allowed: finite m/s")

    def _target_pos(self, layout: Layout, target: jax.Array) -> jax.Array:
        k = jnp.minimum(target, self.num_waypoints - 1)
        return jnp.take_along_axis(layout.waypoints, k[:, None, None], axis=1)[:, 0]

    def _to_go(self, pos: jax.Array, layout: Layout, target: jax.Array,
                params: EnvParams | None = None) -> jax.Array:
        """[n] distance left to each drone's waypoint ``target`` (m).

        Goals: the distance. Gates: ``|along| + lateral_weight * off_axis + wrong_side_weight * past``, in
        the gate's frame (along its direction of passage, off its axis, and the depth past its plane); past the
        plane ``off_axis`` is at least ``wrong_side_clearance``.
        """
        rel = pos - self._target_pos(layout, target)
        if self.kind != "track":
            return jnp.linalg.norm(rel, axis=-1)
        cfg = self.config
        yaw = layout.gate_yaw[jnp.minimum(target, cfg.num_gates - 1)]
        along = rel[:, 0] * jnp.cos(yaw) + rel[:, 1] * jnp.sin(yaw)
        side = -rel[:, 0] * jnp.sin(yaw) + rel[:, 1] * jnp.cos(yaw)
        off_axis = jnp.sqrt(side**2 + rel[:, 2] ** 2 + 1e-12)
        params = self.params(params)
        off_axis = jnp.where(along > 0.0, jnp.maximum(off_axis, params.wrong_side_clearance), off_axis)
        return jnp.abs(along) + params.lateral_weight * off_axis + params.wrong_side_weight * jnp.maximum(along, 0.0)

    def _check(self, prev, pos, t, layout: Layout, normals, tr: Tracker):
        """Advance waypoints and detect collisions after one physics step."""
        cfg = self.config
        r = cfg.cf.collision_radius
        active = ~tr.finished
        if self.kind == "track":
            k = jnp.minimum(tr.target, cfg.num_gates - 1)
            crossed = geo.gate_crossed(prev, pos, layout.gate_pos[k], normals[k], cfg.gate_half_opening)
            target = tr.target + (crossed & active)
            reached = target >= cfg.num_gates
        else:
            target = tr.target
            reached = jnp.linalg.norm(pos - layout.waypoints[:, 0], axis=-1) < cfg.goal_radius
        finished = tr.finished | (reached & active)

        cyl_pos, _ = cylinders_at(layout, t)
        c_cyl = jnp.min(geo.cylinder_clearance(pos, cyl_pos, layout.cyl_radius, layout.cyl_height,
                                               layout.cyl_present, r), -1, initial=geo.FAR)
        c_drone = jnp.min(geo.drone_clearance(pos, active, r), -1, initial=geo.FAR)
        c_gate = jnp.min(geo.gate_clearance(pos, layout.gate_pos, normals, cfg.gate_half_opening, cfg.gate_bar,
                                            r), -1, initial=geo.FAR)
        c_floor = pos[:, 2] - r
        oob = geo.out_of_bounds(pos, cfg.arena_low, cfg.arena_high)
        gaps = jnp.stack([c_cyl, c_drone, c_gate, c_floor], -1)
        hit = jnp.concatenate([gaps < 0, oob[:, None]], -1) & active[:, None]
        kind = jnp.where(jnp.any(hit, -1), jnp.argmax(hit, -1) + 1, col.NONE)
        new = (kind != col.NONE) & ~tr.collided
        tr = tr.replace(
            target=target, finished=finished & ~(tr.collided | new),
            collided=tr.collided | new,
            collision_kind=jnp.where(new, kind, tr.collision_kind),
            min_clearance=jnp.where(active, jnp.minimum(tr.min_clearance, c_cyl), tr.min_clearance),
        )
        return tr, jnp.where(active, jnp.min(gaps, -1), geo.FAR)

    def _cylinder_reach(self, pos, layout: Layout, t, finished) -> jax.Array:
        """Each drone's smallest clearance [n] to the cylinders at the next ``moving_cost_horizon`` s's policy
        periods (their scripted motion), as if the drone stayed at ``pos``; FAR for drones that finished."""
        cfg = self.config
        k = max(1, int(np.ceil(cfg.moving_cost_horizon * cfg.policy_freq - 1e-6)))
        cyl_pos, _ = cylinders_at(layout, t + cfg.moving_cost_horizon * jnp.arange(1, k + 1) / k)  # [k, M, 2]
        gap = geo.cylinder_clearance(pos, cyl_pos, layout.cyl_radius, layout.cyl_height, layout.cyl_present,
                                     cfg.cf.collision_radius)  # [k, n, M]
        return jnp.where(finished, geo.FAR, jnp.min(gap, axis=(0, 2), initial=geo.FAR))

    def _observe(self, drones: DroneState, layout: Layout, tr: Tracker, t) -> jax.Array:
        """Every drone's observation [n, D] (:func:`aswarm.core.observation.observe`, as the flight runtime's), with
        the filter's neighbour rows where it takes more than the policy, and its neighbours' accelerations where it
        takes them (``filter_layout``; ``_policy_view`` cuts the policy's)."""
        cfg = self.config
        if self.kind == "track":
            normals = jnp.broadcast_to(geo.horizontal(layout.gate_yaw), layout.waypoints.shape)
        else:  # goals have no direction of passage
            normals = jnp.zeros_like(layout.waypoints)
        cyl_pos, cyl_vel = cylinders_at(layout, t)
        return observe(drones.pos, drones.quat, drones.vel, drones.ang_vel, layout.waypoints, normals, tr.target,
                       ~tr.finished, cyl_pos, cyl_vel, layout.cyl_radius, layout.cyl_present,
                       cfg.cf.collision_radius, cfg.arena_low, cfg.arena_high, self._observed,
                       cfg.filter_neighbour_accel)

    def _metrics(self, tr: Tracker) -> dict:
        """Episode outcome so far; read it on the step where ``done`` is 1."""
        cfg = self.config
        ok = tr.finished & ~tr.collided
        steps = jnp.maximum(tr.steps, 1).astype(jnp.float32)
        m = {
            "success": jnp.all(ok).astype(jnp.float32),
            "drone_success": jnp.mean(ok.astype(jnp.float32)),
            "collision": jnp.any(tr.collided).astype(jnp.float32),
            "drone_collision": jnp.mean(tr.collided.astype(jnp.float32)),
            "progress": jnp.mean(jnp.where(tr.finished, 1.0, tr.target / self.num_waypoints)),
            "min_clearance": jnp.min(tr.min_clearance),
            "mean_separation": jnp.mean(tr.separation_sum) / steps,
            "mission_time": jnp.max(tr.finish_time),
            "mean_speed": jnp.mean(tr.speed_sum / jnp.maximum(tr.finish_time * cfg.policy_freq, 1.0)),
            "episode_return": jnp.mean(tr.episode_return),
            "episode_length": tr.steps.astype(jnp.float32),
        }
        for kind, name in enumerate(col.KINDS[1:], start=1):
            m[f"collision_{name}"] = jnp.any(tr.collided & (tr.collision_kind == kind)).astype(jnp.float32)
        return m
