"""Domain randomisation: per-episode parameters drawn inside ``reset``, so a policy trains for the drone that
flies rather than for one exact simulated drone.

Every range is ``(low, high)``, drawn uniformly per world at each reset (auto-reset included), inside the
jitted program. Scales multiply the nominal value (``EnvConfig``'s): mass (and inertia with it), the thrust
constant (more or less thrust at the speed the firmware commands), the yaw-torque constant, the rotor time
constant and every gain of the onboard controller (one factor per world). Latency delays the velocity command
by whole onboard-controller ticks (``1 / ctrl_freq``, 10 ms at the firmware's 100 Hz); its range is in policy
steps. Motion capture adds Gaussian noise (standard deviation drawn per episode, in metres) to every position
the policy and its filter see, and can hand over poses whole policy steps old; with ``velocity_window`` the
velocities they see are estimated from those noisy positions as the flight runtime estimates them.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class Randomization:
    enabled: bool = True
    mass: tuple[float, float] = (0.9, 1.1)  # scale
    thrust_constant: tuple[float, float] = (0.9, 1.1)  # scale of kf
    torque_constant: tuple[float, float] = (0.9, 1.1)  # scale of km
    motor_tau: tuple[float, float] = (0.7, 1.3)  # scale of cf.motor_tau
    gains: tuple[float, float] = (0.9, 1.1)  # scale of every gain of the onboard controller
    latency: tuple[float, float] = (0.0, 2.0)  # policy steps, rounded down to onboard-controller ticks
    mocap_noise: tuple[float, float] = (0.0, 0.005)  # m, standard deviation
    # Policy steps. Off by default: the command latency above already spans 0-80 ms of loop delay, and the two
    # together (up to 120 ms) cost the race policy its success (README, issue #12).
    mocap_delay: tuple[int, int] = (0, 0)
    # Poses (>= 2) of the least-squares line the policy's velocities are fitted to, from the noisy positions at
    # the policy rate, as the flight runtime estimates them (its default window is 4); 0: the true velocities.
    velocity_window: int = 0

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            if f.name == "enabled":
                if not isinstance(self.enabled, bool):
                    raise ValueError(f"invalid randomize.enabled={self.enabled!r}: allowed: true or false")
                continue
            if f.name == "velocity_window":
                w = self.velocity_window
                if isinstance(w, bool) or not isinstance(w, int) or w == 1 or w < 0:
                    raise ValueError(f"invalid randomize.velocity_window={w!r}: allowed: 0 (true velocities) or "
                                     "an integer >= 2")
                continue
            v = getattr(self, f.name)
            name = f"randomize.{f.name}"
            if not (isinstance(v, tuple) and len(v) == 2 and all(isinstance(x, (int, float)) and
                                                                 not isinstance(x, bool) for x in v)):
                raise ValueError(f"invalid {name}={v!r}: allowed: a (low, high) pair of numbers")
            lo, hi = v
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                raise ValueError(f"invalid {name}={v!r}: allowed: finite numbers with low <= high")
            scale = f.name in ("mass", "thrust_constant", "torque_constant", "motor_tau", "gains")
            if scale and lo <= 0:
                raise ValueError(f"invalid {name}={v!r}: allowed: scales > 0 (a fraction of the nominal value)")
            if not scale and lo < 0:
                raise ValueError(f"invalid {name}={v!r}: allowed: values >= 0")
            if f.name == "mocap_delay" and not all(float(x).is_integer() for x in v):
                raise ValueError(f"invalid {name}={v!r}: allowed: whole policy steps")

    @property
    def max_delay(self) -> int:
        """Policy steps of observations the env keeps (the compiled shape)."""
        return int(self.mocap_delay[1]) if self.enabled else 0

    @property
    def velocity_samples(self) -> int:
        """Noisy positions the env keeps for the velocity estimate (the compiled shape); 0: none."""
        return self.velocity_window if self.enabled else 0

    @property
    def max_latency(self) -> float:
        return float(self.latency[1]) if self.enabled else 0.0


OFF = Randomization(enabled=False)


def _uniform(key: jax.Array, bounds: tuple[float, float]) -> jax.Array:
    lo, hi = bounds
    return jax.random.uniform(key, (), minval=lo, maxval=hi)


def sample(key: jax.Array, nominal, r: Randomization, ticks_per_step: int):
    """``nominal`` (:class:`~aswarm.envs.params.EnvParams`) with one world's draw of every range of ``r``."""
    keys = jax.random.split(key, 8)
    mass = _uniform(keys[0], r.mass)
    kf = _uniform(keys[1], r.thrust_constant)
    cf = nominal.cf
    lag = _uniform(keys[3], r.motor_tau)  # one rotor, slower or faster both ways
    cf = cf.replace(
        mass=cf.mass * mass, inertia=cf.inertia * mass, kf=cf.kf * kf,
        # The speed limit of a motor is its own; its thrust there scales with kf.
        max_motor_thrust=cf.max_motor_thrust * kf,
        km_scale=cf.km_scale * _uniform(keys[2], r.torque_constant),
        motor_tau=cf.motor_tau * lag, motor_tau_down=cf.motor_tau_down * lag,
    )
    gain = _uniform(keys[4], r.gains)
    pid = nominal.pid.replace(**{name: getattr(nominal.pid, name) * gain for name in GAIN_FIELDS})
    mellinger = nominal.mellinger.replace(**{name: getattr(nominal.mellinger, name) * gain
                                            for name in MELLINGER_GAIN_FIELDS})
    # Whole ticks; the nudge keeps a range of one value (SITL's) from flooring 0.7 * 10 = 6.9999995 to 6.
    latency = jnp.floor(_uniform(keys[5], r.latency) * ticks_per_step + 1e-4)
    delay = jax.random.randint(keys[7], (), int(r.mocap_delay[0]), int(r.mocap_delay[1]) + 1)
    return nominal.replace(cf=cf, pid=pid, mellinger=mellinger, latency_ticks=latency,
                           mocap_noise=_uniform(keys[6], r.mocap_noise), mocap_delay=delay.astype(jnp.float32))


# The controller's gains (FirmwarePid fields) that the gain factor scales; limits and the thrust map stay.
GAIN_FIELDS = ("vel_xy_kp", "vel_xy_ki", "vel_z_kp", "vel_z_ki", "att_kp", "att_ki", "yaw_kp", "yaw_ki", "yaw_kd",
               "rate_kp", "rate_ki", "rate_kd", "yaw_rate_kp", "yaw_rate_ki")
# The same for controller_mellinger (FirmwareMellinger fields): the feed-forward mass, gravity, the force-to-PWM
# factor and the integrators' ranges stay.
MELLINGER_GAIN_FIELDS = ("kp_xy", "kd_xy", "ki_xy", "kp_z", "kd_z", "ki_z", "kr_xy", "kw_xy", "ki_m_xy", "kr_z", "kw_z",
                         "ki_m_z", "kd_omega_rp")
