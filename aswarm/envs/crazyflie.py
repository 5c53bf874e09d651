"""Crazyflie 2.x physical constants and the motor mixing they imply.

Values follow gym-pybullet-drones' ``cf2x.urdf`` (see ``shared/crazyflie.md``).
Motor order and spin, X configuration seen from above:

====== ================ ==================
motor  position (x, y)  spin
====== ================ ==================
0      (+, -) front-right counter-clockwise
1      (-, -) rear-right  clockwise
2      (-, +) rear-left   counter-clockwise
3      (+, +) front-left  clockwise
====== ================ ==================
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class CrazyflieParams:
    mass: float = 0.027  # kg
    arm_length: float = 0.0397  # m, centre to motor
    inertia: tuple[float, float, float] = (1.4e-5, 1.4e-5, 2.17e-5)  # kg m^2
    kf: float = 3.16e-10  # N / RPM^2
    km: float = 7.94e-12  # N m / RPM^2
    thrust_to_weight: float = 2.25
    gravity: float = 9.8  # m/s^2, as gym-pybullet-drones uses
    collision_radius: float = 0.06  # m, radius of the collision sphere
    body_half_height: float = 0.0125  # m, for drawing only
    # First-order lag of each rotor's speed towards its command (s); 0: speeds change at once. 0.136 s is
    # 1 / 7.356, the spin-up coefficient the crazyflow team identified for the Crazyflie 2.x (package
    # `drone-models` 0.1.0, params.toml [cf2x_L250] rotor_dyn_coef[0], d rpm/dt = k (cmd - rpm)).
    motor_tau: float = 0.136
    # Slowing down, the same identification finds the rotors faster and quadratic in speed: rotor_dyn_coef[3]
    # = 2.444e-4 / (s RPM) in d rpm/dt = k (cmd^2 - rpm^2), a time constant 1 / (2 k rpm) = 0.108 s about its
    # hover speed (18,968 RPM for its 31.9 g drone); here the time constant about SPIN_DOWN_REFERENCE_RPM.
    # 0: slowing down follows motor_tau as well (every run before session 22).
    motor_tau_down: float = 0.108
    # Linear rotor drag (gym-pybullet-drones' DRAG): F = -drag * v_body * sum(2 pi rpm / 60), per body axis
    # (N s / m per rad/s). 0 leaves it out; gym-pybullet-drones' values are (9.1785e-7, 9.1785e-7, 10.311e-7).
    drag: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def weight(self) -> float:
        return self.mass * self.gravity

    @property
    def hover_rpm(self) -> float:
        return math.sqrt(self.weight / (4.0 * self.kf))

    @property
    def max_rpm(self) -> float:
        return math.sqrt(self.thrust_to_weight * self.weight / (4.0 * self.kf))

    @property
    def max_motor_thrust(self) -> float:
        return self.kf * self.max_rpm**2

    @property
    def motor_positions(self) -> np.ndarray:
        """[4, 2] motor (x, y) in the body frame, in motor order."""
        a = self.arm_length / math.sqrt(2.0)
        return np.array([[a, -a], [-a, -a], [-a, a], [a, a]])

    @property
    def motor_spin(self) -> np.ndarray:
        """[4] +1 counter-clockwise, -1 clockwise (seen from above)."""
        return np.array([1.0, -1.0, 1.0, -1.0])

    def mixer(self) -> np.ndarray:
        """[4, 4] maps per-motor thrusts f to [T, tau_x, tau_y, tau_z] (body frame).

        A counter-clockwise rotor pushes the body clockwise, hence ``-spin``.
        """
        xy = self.motor_positions
        return np.stack([
            np.ones(4),
            xy[:, 1],  # tau_x = sum(y_i f_i)
            -xy[:, 0],  # tau_y = -sum(x_i f_i)
            -self.motor_spin * self.km / self.kf,
        ])


# The speed cf.motor_tau_down is the spin-down time constant about: the default drone's hover speed (14,468 RPM). A
# constant, not the configured drone's hover speed, because the braking is the rotor's own: a heavier drone (or a
# randomised mass) hovers at another speed with the same rotors.
SPIN_DOWN_REFERENCE_RPM: float = CrazyflieParams().hover_rpm
