"""Centralized MAPPO with the attention-CBF network (Algorithm 1), as pure functions.

``make_train(config)`` returns ``train(key) -> (TrainState, metrics)`` that runs
the whole budget in one ``jit``; the host loop in ``runner.py`` instead calls
``init`` and ``update_chunk`` so it can checkpoint, log and draw progress
between chunks. Both produce the same numbers for the same key.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax
from brax.training.acme import running_statistics
from brax.training.distribution import NormalTanhDistribution
from flax import struct

from aswarm import envs
from aswarm.agents import cbf_filter, hparams, losses
from aswarm.agents.config import TrainConfig
from aswarm.agents.networks import CRITICS, Actor, AttentionCBF, CentralCritic, PooledCritic, hazard_mask
from aswarm.core.layout import OBS_NORM_CLIP


class Transition(NamedTuple):
    obs: jax.Array  # [B, n, D] raw
    final_obs: jax.Array  # [B, n, D] raw obs reached by the step, before any auto-reset
    raw_action: jax.Array  # [B, n, 3] pre-tanh sample
    log_prob: jax.Array  # [B, n]
    reward: jax.Array  # [B, n] the env's reward minus the correction penalty
    penalty: jax.Array  # [B, n] that correction penalty
    cost: jax.Array  # [B, n]
    done: jax.Array  # [B]
    truncated: jax.Array  # [B]
    intervened: jax.Array  # [B, n] the safety filter changed the command
    correction: jax.Array  # [B, n] m/s, size of that change
    episode: dict  # metrics summed over the episodes that ended, and their count


@struct.dataclass
class TrainState:
    params: dict
    opt_state: optax.OptState
    obs_norm: running_statistics.RunningStatisticsState
    env_state: envs.State
    key: jax.Array
    update: jax.Array  # [] int32, updates done
    env_steps: jax.Array  # [] float32 (int32 would overflow past 2^31)
    # Swept value-only hyperparameters ({field: [] float32}, see hparams.py); empty for a plain run, so
    # plain checkpoints keep their layout.
    hparams: dict = struct.field(default_factory=dict)
    # Target critics ({"critic", "cost_critic"}) when config.target_tau > 0; empty otherwise, so checkpoints
    # without them keep their layout.
    target: dict = struct.field(default_factory=dict)


def fit_safety_filter(config: TrainConfig, env: envs.SwarmEnv) -> TrainConfig:
    """``config`` with its filter's gains fitted to ``env``'s drone (``SafetyFilterConfig.fitted``), measured
    once per drone and process; unchanged where the filter is already fitted."""
    sf = config.safety_filter
    if not (sf.fit_to_drone and config.uses_filter):
        return config
    from aswarm.analysis.step_response import characterise

    drone = characterise(env.config)
    return dataclasses.replace(config, safety_filter=sf.fitted(drone.lag_xy, drone.lag_z))


@dataclasses.dataclass(frozen=True)
class Agent:
    """The networks and how to run them: shared by training, evaluation and export."""

    config: TrainConfig
    env: envs.SwarmEnv
    actor: Actor
    critic: CentralCritic | PooledCritic
    cost_critic: CentralCritic | PooledCritic
    cbf: AttentionCBF
    dist: NormalTanhDistribution

    @classmethod
    def build(cls, config: TrainConfig, env: envs.SwarmEnv | None = None) -> Agent:
        """The agent of ``config`` on ``env``; its ``config`` has the safety filter fitted to the drone."""
        env = env or make_env(config)
        # (checked on the env the agent flies, which an evaluation may override: not on config.env)
        if config.uses_filter and config.safety_filter.lookahead_accel > 0 and not env.filter_layout.neighbour_accel:
            raise ValueError(f"invalid safety_filter.lookahead_accel={config.safety_filter.lookahead_accel!r} with "
                             "env filter_neighbour_accel=false: allowed: lookahead_accel 0, or --env "
                             "filter_neighbour_accel=true (the filter's observation then carries the neighbours' "
                             "accelerations)")
        config = fit_safety_filter(config, env)
        n = env.num_agents
        return cls(
            config=config, env=env,
            actor=Actor(hidden=config.actor_hidden),
            critic=CRITICS[config.critic](num_agents=n, hidden=config.critic_hidden),
            cost_critic=CRITICS[config.critic](num_agents=n, hidden=config.critic_hidden),
            cbf=AttentionCBF(layout=env.obs_layout, embed=config.cbf_embed, hidden=config.cbf_hidden,
                             state_hidden=config.cbf_state_hidden, penalty_max=config.penalty_max,
                             gain_min=config.safety_filter.gain_min,
                             gain_max=config.safety_filter.gain_max),
            dist=NormalTanhDistribution(event_size=env.action_size, var_scale=config.action_std_scale),
        )

    def init_params(self, key: jax.Array) -> dict:
        d = self.env.observation_size
        n = self.env.num_agents
        layout = self.env.obs_layout
        k = jax.random.split(key, 4)
        obs = jnp.zeros((n, d))
        return {
            "actor": self.actor.init(k[0], obs),
            "critic": self.critic.init(k[1], obs.reshape(-1)),
            "cost_critic": self.cost_critic.init(k[2], obs.reshape(-1)),
            "cbf": self.cbf.init(k[3], obs, jnp.ones((n, layout.num_cylinders + layout.num_neighbours), bool)),
            "lagrange": jnp.asarray(self.config.lagrange_init, jnp.float32),
        }

    def normalize(self, obs_norm, obs: jax.Array) -> jax.Array:
        return running_statistics.normalize(obs, obs_norm, max_abs_value=OBS_NORM_CLIP)

    def policy(self, params: dict, obs_norm, obs: jax.Array, key: jax.Array | None):
        """Velocity commands [.., n, 3] before the filter; stochastic with ``key``, the mean without.

        Returns (command, raw pre-tanh action, log-prob).
        """
        p = self.actor.apply(params["actor"], self.normalize(obs_norm, obs))
        if key is None:
            raw = self.dist.create_dist(p).loc
        else:
            raw = self.dist.sample_no_postprocessing(p, key)
        cmd = self.dist.postprocess(raw) * self.env.config.max_speed
        return cmd, raw, self.dist.log_prob(p, raw)

    def cbf_params(self, params: dict, obs_norm, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
        """theta [.., n, 2] = (penalty, gain) and attention weights [.., n, M + n - 1]."""
        return self.cbf.apply(params["cbf"], self.normalize(obs_norm, obs), hazard_mask(self.env.obs_layout, obs))

    def filter_gain(self, params: dict, obs_norm, obs: jax.Array) -> jax.Array:
        """The class-K gain [.., n] (1/s) the filter applies to each drone's rows: the attention-CBF network's output
        where the method has it, else the fixed gain."""
        if self.config.uses_attention:
            return self.cbf_params(params, obs_norm, obs)[0][..., 1]
        return jnp.full(obs.shape[:-1], self.config.safety_filter.fixed_gain)

    def filter_commands(self, params: dict, obs_norm, obs: jax.Array, cmd: jax.Array,
                        cyl_accel: jax.Array | None = None, filter_obs: jax.Array | None = None,
                        applied: jax.Array | None = None) -> cbf_filter.FilterResult:
        """The CBF safety filter's whole result on commands [.., n, 3] (its slack, convergence, active rows);
        a method without a filter passes the commands through, with no slack, no row and nothing changed.
        ``cyl_accel`` [.., M]: the cylinders' acceleration bounds (``SwarmEnv.cylinder_accel``); ``filter_obs``: the
        rows' observation where the filter takes more neighbours than the policy (``State.filter_obs``; None:
        ``obs``). The gain comes from the policy's own observation either way. ``applied`` [.., n, 3]: the commands
        the drones fly now (``SwarmEnv.applied_command``), for a filter with ``braking``."""
        if not self.config.uses_filter:
            zeros = jnp.zeros(cmd.shape[:-1])
            return cbf_filter.FilterResult(u=cmd, slack=zeros, intervened=zeros.astype(bool), correction_norm=zeros,
                                           active=jnp.zeros(cmd.shape[:-1] + (0,), bool),
                                           converged=jnp.ones(cmd.shape[:-1], bool), escaped=zeros.astype(bool))
        gain = self.filter_gain(params, obs_norm, obs)
        ec = self.env.config
        layout, rows_obs = (self.env.obs_layout, obs) if filter_obs is None else (self.env.filter_layout, filter_obs)
        return cbf_filter.filter_from_obs(layout, rows_obs, cmd, gain, ec.max_speed, ec.cf.collision_radius,
                                          self.config.safety_filter, ec.gate_half_opening, ec.gate_bar,
                                          cyl_accel, applied, (ec.command_accel_limit, 1.0 / ec.policy_freq))

    def safe_command(self, params: dict, obs_norm, obs: jax.Array, cmd: jax.Array,
                     cyl_accel: jax.Array | None = None, filter_obs: jax.Array | None = None,
                     applied: jax.Array | None = None):
        """Apply the CBF safety filter (where the method has one) to commands [.., n, 3].

        Returns (filtered commands, intervened [.., n], correction norm [.., n] m/s: the training's reward
        charges it); :meth:`filter_commands` has the rest of the filter's result (slack, convergence).
        """
        res = self.filter_commands(params, obs_norm, obs, cmd, cyl_accel, filter_obs, applied)
        return res.u, res.intervened, res.correction_norm

    def act(self, params: dict, obs_norm, obs: jax.Array, cyl_accel: jax.Array | None = None,
            filter_obs: jax.Array | None = None, applied: jax.Array | None = None) -> jax.Array:
        """Deterministic, filtered commands: what evaluation and export run."""
        cmd, _, _ = self.policy(params, obs_norm, obs, None)
        return self.safe_command(params, obs_norm, obs, cmd, cyl_accel, filter_obs, applied)[0]


def make_env(config: TrainConfig) -> envs.SwarmEnv:
    """The run's own environment, as resolved when it started (``config.env``), not rebuilt from a preset."""
    return envs.SwarmEnv(config.env)


def make_optimizer(config: TrainConfig, h: dict | None = None) -> optax.GradientTransformation:
    """``h`` (from ``hparams.resolve``) may hold traced rates: Adam's state does not store them, so the
    optimizer state has the same layout either way."""
    h = h or hparams.resolve(config, {})
    # One count per minibatch step; the rates fall linearly to 0 over the run when annealed. At a constant
    # actor LR of 2e-3 the race policy reached 100 % and then collapsed (entropy and return falling
    # from update ~400 of 610, README).
    steps = config.num_updates * config.num_epochs * config.num_minibatches

    def adam(lr):
        rate = optax.linear_schedule(lr, 0.0, steps) if config.anneal_lr else lr
        return optax.chain(optax.clip_by_global_norm(h["max_grad_norm"]), optax.adam(rate))

    labels = {"actor": "actor", "critic": "critic", "cost_critic": "critic", "cbf": "cbf", "lagrange": "cbf"}
    return optax.multi_transform(
        {"actor": adam(h["actor_lr"]), "critic": adam(h["critic_lr"]), "cbf": adam(h["cbf_lr"])},
        lambda params: {k: jax.tree.map(lambda _, lab=labels[k]: lab, v) for k, v in params.items()},
    )


@dataclasses.dataclass(frozen=True)
class Trainer:
    """The trainer's pure, jittable pieces (:func:`make_trainer`).

    ``update`` is ``learn(rollout(...))``: the two halves are kept apart so a profile can time each
    (``aswarm bench --profile``); ``update_chunk`` and ``train`` are what the host loop and tests run.
    """

    agent: Agent
    init: Callable  # (key[, values]) -> TrainState
    rollout: Callable  # (ts, key) -> (env_state, Transition [T, B, ...])
    learn: Callable  # (ts, env_state, transitions, permutation key) -> (TrainState, metrics)
    update_chunk: Callable  # (ts, n) -> (TrainState, metrics [n])
    train: Callable  # (key[, values]) -> (TrainState, metrics [num_updates])
    hparams: Callable  # (values) -> every value hyperparameter the update reads (hparams.resolve, gains fitted)


def make_train(config: TrainConfig, sweep_fields: tuple[str, ...] = (), shard_rows=None):
    """``(agent, init, update_chunk, train)`` of :func:`make_trainer`."""
    t = make_trainer(config, sweep_fields, shard_rows)
    return t.agent, t.init, t.update_chunk, t.train


def make_trainer(config: TrainConfig, sweep_fields: tuple[str, ...] = (), shard_rows=None) -> Trainer:
    """The trainer of ``config``; its functions are pure and jittable.

    ``init(key) -> TrainState``; ``update_chunk(state, n) -> (state, metrics [n])``;
    ``train(key)`` runs ``config.num_updates`` updates from ``init``.
    With ``sweep_fields`` (value-only hyperparameters, see ``hparams.py``) ``init(key, values)`` takes
    ``{field: scalar}`` and the trainer reads those fields from the state, so it can be vmapped over them.
    ``shard_rows`` (``sharding.rows_constraint``) lays each minibatch's rows out over devices, so the
    gradient is computed data-parallel and averaged by an all-reduce.
    """
    sweep_fields = hparams.check_fields(sweep_fields)
    shard_rows = shard_rows or (lambda x: x)
    agent = Agent.build(config)
    env = agent.env
    # The network's gain range is the fitted one (Agent.build); its target and any swept bounds must be too. Until
    # session 30 they were the config's: on the firmware drone the target (2.0 where no cost followed) lay above the
    # network's reach (1.47), which pinned its output at the top of its range in every state (README).
    gain_scale = agent.config.safety_filter.gain_max / config.safety_filter.gain_max

    def resolve(values) -> dict:
        return hparams.resolve(config, values, gain_scale)

    wenv = envs.wrap_for_training(env, config.num_envs)
    n, d = env.num_agents, env.observation_size
    b = config.num_envs

    def agent_for(h: dict) -> Agent:
        # The CBF network scales its outputs by these bounds: rebuild it with the traced ones when swept.
        if not set(hparams.NETWORK_FIELDS) & set(sweep_fields):
            return agent
        cbf = agent.cbf.clone(**{f: h[f] for f in hparams.NETWORK_FIELDS})
        return dataclasses.replace(agent, cbf=cbf)

    def init(key: jax.Array, values: dict | None = None) -> TrainState:
        values = hparams.check_values(sweep_fields, values)
        k_param, k_env, k_run = jax.random.split(key, 3)
        params = agent.init_params(k_param)
        if "lagrange_init" in values:
            params["lagrange"] = jnp.asarray(values["lagrange_init"], jnp.float32)
        obs_norm = running_statistics.init_state(jax.ShapeDtypeStruct((d,), jnp.float32))
        optimizer = make_optimizer(config, resolve(values))
        target = {k: params[k] for k in ("critic", "cost_critic")} if config.target_tau > 0 else {}
        ts = TrainState(params=params, opt_state=optimizer.init(params), obs_norm=obs_norm,
                        env_state=wenv.reset(k_env), key=k_run, update=jnp.zeros((), jnp.int32),
                        env_steps=jnp.zeros((), jnp.float32), hparams=values, target=target)
        # Strongly typed leaves only: a state restored from a checkpoint (numpy, never weakly typed) then has a
        # fresh one's types, and a resumed run reuses the compiled update instead of compiling a second one.
        return jax.tree.map(lambda x: jnp.asarray(x).astype(jnp.asarray(x).dtype), ts)

    def rollout(ts: TrainState, key: jax.Array):
        h = resolve(ts.hparams)
        ag = agent_for(h)

        def step(env_state, k):
            obs = env_state.obs
            cmd, raw, logp = ag.policy(ts.params, ts.obs_norm, obs, k)
            safe, intervened, corr = ag.safe_command(ts.params, ts.obs_norm, obs, cmd, env.cylinder_accel(env_state),
                                                     env_state.filter_obs, env.applied_command(env_state))
            nxt = wenv.step(env_state, safe)
            done = nxt.done
            episode = {k_: jnp.sum(v * done) for k_, v in nxt.metrics.items()}
            episode["episodes"] = jnp.sum(done)
            # The training reward also charges the filter's correction (the env's reward, and so the
            # logged return, does not).
            penalty = h["correction_penalty"] * env.config.dt * corr * env.flying(env_state)
            return nxt, Transition(obs, nxt.info["final_obs"], raw, logp, nxt.reward - penalty, penalty, nxt.cost,
                                   done, nxt.truncated, intervened, corr, episode)

        return jax.lax.scan(step, ts.env_state, jax.random.split(key, config.rollout_steps))

    def values(params, obs_norm, obs):
        joint = agent.normalize(obs_norm, obs).reshape(*obs.shape[:-2], n * d)
        return agent.critic.apply(params["critic"], joint), agent.cost_critic.apply(params["cost_critic"], joint)

    def loss_fn(params, obs_norm, mb, h):
        obs, raw, old_logp, adv, cost_adv, targets, cost_targets, excess, gain_tgt = mb
        nobs = agent.normalize(obs_norm, obs)
        p = agent.actor.apply(params["actor"], nobs)
        logp = agent.dist.log_prob(p, raw)
        entropy = jnp.mean(agent.dist.create_dist(p).entropy().sum(-1))
        # Reward advantages are normalized; cost advantages only centred: costs are mostly zero, and
        # scaling them to unit variance blew their noise up to the size of the reward signal.
        a = losses.normalize(adv)
        aux = {}
        if config.uses_attention:
            theta, _ = agent_for(h).cbf.apply(params["cbf"], nobs, hazard_mask(env.obs_layout, obs))
            penalty, gain = theta[..., 0], theta[..., 1]
            a = losses.penalized_advantage(a, cost_adv - jnp.mean(cost_adv), penalty)
            pen_loss = losses.penalty_loss(penalty, cost_adv, excess)
            cbf_loss = jnp.mean((gain - gain_tgt) ** 2)
            aux.update(penalty=jnp.mean(penalty), gain=jnp.mean(gain), cbf_loss=cbf_loss)
        elif config.method == "mappo_lagrangian":
            lam = jax.nn.softplus(params["lagrange"])
            a = losses.penalized_advantage(a, cost_adv - jnp.mean(cost_adv), lam)
            pen_loss, cbf_loss = losses.penalty_loss(lam, jnp.zeros(()), excess), jnp.zeros(())
            aux.update(penalty=lam)
        else:
            pen_loss = cbf_loss = jnp.zeros(())
        if config.method == "a2c":
            actor_loss = losses.policy_gradient_loss(logp, a)
        else:
            actor_loss = losses.ppo_clip_loss(logp, old_logp, a, h["clip"])
        v, vc = values(params, obs_norm, obs)
        v_loss = losses.value_loss(v, targets)
        vc_loss = losses.value_loss(vc, cost_targets) if config.uses_cost else jnp.zeros(())
        total = (actor_loss + h["value_coef"] * (v_loss + vc_loss) + pen_loss + h["cbf_coef"] * cbf_loss
                 - h["entropy_coef"] * entropy)
        approx_kl = jnp.mean(old_logp - logp)
        aux.update(actor_loss=actor_loss, value_loss=v_loss, cost_value_loss=vc_loss, entropy=entropy,
                   approx_kl=approx_kl, loss=total)
        return total, aux

    def learn(ts: TrainState, env_state, tr: Transition, k_perm: jax.Array):
        """The update after its rollout (which reached ``env_state``): GAE, the epochs of minibatch steps over
        permutations drawn from ``k_perm``, the metrics. The state's key is left to the caller."""
        h = resolve(ts.hparams)
        optimizer = make_optimizer(config, h)
        critics = {**ts.params, **ts.target}  # the target critics, where there are any, bootstrap GAE
        v, vc = values(critics, ts.obs_norm, tr.obs)
        nv, nvc = values(critics, ts.obs_norm, tr.final_obs)
        adv, targets = losses.gae(tr.reward, v, nv, tr.done, tr.truncated, h["gamma"], h["gae_lambda"])
        cadv, ctargets = losses.gae(tr.cost, vc, nvc, tr.done, tr.truncated, h["gamma"], h["gae_lambda"])
        excess = jnp.mean(ctargets) - h["cost_limit"]
        gain_tgt = losses.gain_target(ctargets, h["gain_min"], h["gain_max"])
        flat = lambda x: x.reshape((config.rollout_steps * b,) + x.shape[2:])  # noqa: E731
        data = (flat(tr.obs), flat(tr.raw_action), flat(tr.log_prob), flat(adv), flat(cadv), flat(targets),
                flat(ctargets), excess, flat(gain_tgt))

        def epoch(carry, k):
            params, opt_state = carry
            perm = jax.random.permutation(k, config.rollout_steps * b)
            shuffled = [x if x.ndim == 0 else shard_rows(x[perm].reshape((config.num_minibatches, -1) + x.shape[1:]))
                        for x in data]

            def minibatch(c, i):
                prm, ost = c
                mb = [x if x.ndim == 0 else x[i] for x in shuffled]
                (_, aux), grads = jax.value_and_grad(loss_fn, has_aux=True)(prm, ts.obs_norm, mb, h)
                upd, ost = optimizer.update(grads, ost, prm)
                aux["grad_norm"] = optax.tree.norm(grads)
                return (optax.apply_updates(prm, upd), ost), aux

            return jax.lax.scan(minibatch, (params, opt_state), jnp.arange(config.num_minibatches))

        (params, opt_state), aux = jax.lax.scan(epoch, (ts.params, ts.opt_state),
                                                jax.random.split(k_perm, config.num_epochs))
        obs_norm = running_statistics.update(ts.obs_norm, flat(tr.obs).reshape(-1, d))
        eps = jnp.maximum(tr.episode["episodes"].sum(), 1.0)
        metrics = {f"episode/{k_}": v_.sum() / eps for k_, v_ in tr.episode.items() if k_ != "episodes"}
        metrics["episodes"] = tr.episode["episodes"].sum()
        metrics.update({f"train/{k_}": jnp.mean(v_) for k_, v_ in aux.items()})
        metrics["train/explained_variance"] = 1.0 - jnp.var(targets - v) / jnp.maximum(jnp.var(targets), 1e-8)
        metrics["train/step_reward"] = jnp.mean(tr.reward)
        metrics["train/step_cost"] = jnp.mean(tr.cost)
        metrics["safety/intervention_rate"] = jnp.mean(tr.intervened)
        metrics["safety/mean_correction"] = jnp.sum(tr.correction) / jnp.maximum(jnp.sum(tr.intervened), 1.0)
        metrics["safety/correction_penalty"] = jnp.mean(tr.penalty)
        metrics["train/cost_excess"] = excess
        target = jax.tree.map(lambda t, p: config.target_tau * p + (1 - config.target_tau) * t, ts.target,
                              {k: params[k] for k in ts.target})
        ts = ts.replace(params=params, opt_state=opt_state, obs_norm=obs_norm, env_state=env_state,
                        update=ts.update + 1, env_steps=ts.env_steps + config.steps_per_update, target=target)
        return ts, metrics

    def update(ts: TrainState, _):
        key, k_roll, k_perm = jax.random.split(ts.key, 3)
        env_state, tr = rollout(ts, k_roll)
        ts, metrics = learn(ts, env_state, tr, k_perm)
        return ts.replace(key=key), metrics

    def update_chunk(ts: TrainState, num_updates: int):
        return jax.lax.scan(update, ts, None, length=num_updates)

    def train(key: jax.Array, values: dict | None = None):
        return update_chunk(init(key, values), config.num_updates)

    return Trainer(agent, init, rollout, learn, update_chunk, train, resolve)
