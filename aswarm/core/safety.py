"""The safety filter's settings: one frozen config for the JAX filter, the numpy flight filter and the bundle.

Held in ``TrainConfig.safety_filter``, passed to both ``filter_from_obs`` (``aswarm.agents.cbf_filter``,
``aswarm.flight.cbf``) and written field by field to a bundle's manifest (``safety_filter``), from which
the flight runtime reads it back (:func:`from_manifest`). No JAX here: the flight side imports it.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping


@dataclasses.dataclass(frozen=True)
class SafetyFilterConfig:
    # Kept on top of the collision distance by every barrier (m). 0.13 since issue #12: on the race (firmware drone,
    # randomised) the shipped policy had 0.2 / 0.1 % collision episodes at 0.1 on two seeds of 1000 episodes and
    # 0 / 0.1 % at 0.13, success unchanged (0.16 cost 1 point); the gap rule (min_obstacle_gap 0.45 m) still
    # leaves 2 x (0.06 + 0.13) = 0.38 m passable. Runs from before keep the margin they stored (0.1).
    margin: float = 0.13
    # Class-K gain range (1/s) of the attention-CBF network's output. Above ~2/s a drone commanded at 2 m/s
    # straight at a cylinder still hit it: the filter assumes velocity follows the command at once, the
    # geometric onboard controller takes ~0.25 s (TUNED_LAG; tests/test_safety_filter_env.py).
    gain_min: float = 0.3
    gain_max: float = 2.0
    fixed_gain: float = 1.5  # 1/s, the gain of method fixed_cbf
    # Scale the three gains above by TUNED_LAG / (the drone's measured lag) where it is slower, when a policy is
    # built for a drone (agents.train.Agent.build measures it: analysis.step_response.characterise). The
    # fitted config has this False and the fitted gains, and that is what a run's filter and its export use.
    fit_to_drone: bool = True
    # s: the barriers hold at the look-ahead point p + lookahead * v (horizontal, vertical) rather than at p, so
    # that they are exact for a drone whose velocity lags the command by that time constant
    # (aswarm.core.barriers.obs_rows). 0 is the single-integrator model.
    lookahead_xy: float = 0.0
    lookahead_z: float = 0.0
    # s²: > 0 makes the horizontal look-ahead point second order, p + lookahead_xy v + lookahead_accel a, with a each
    # drone's acceleration from its attitude (aswarm.core.barriers.obs_rows); the filter's observation then carries
    # its neighbours' (EnvConfig.filter_neighbour_accel). lookahead_xy is then this fit's own (not fitted to the
    # drone's lag): on the default firmware drone (0.207, 0.039) leave 0.16 m/s rms between the point's speed and
    # the command, against 0.44 for the best first-order point (experiments/lookahead_model_error.py; README,
    # "The second-order look-ahead"). 0: first order, as runs and bundles from before it.
    lookahead_accel: float = 0.0
    # With fit_to_drone: set the two look-aheads to lookahead_scale times the drone's measured lags (63 % rise
    # times of a 1 m/s step, horizontal and vertical). The rise time is the exact look-ahead for a first-order lag
    # only; the firmware drone behind the command acceleration limit follows a command ramp at most 0.25 s late
    # (its integrators then catch up), plus 0-80 ms of randomised command latency, and on the race 0.9 had fewer
    # gate contacts than 1 (README, "On the firmware drone"). Runs from before the scale read back with 1.
    fit_lookahead: bool = True
    lookahead_scale: float = 0.9
    # Moving cylinders' rows hold against their acceleration bound (the scenario's amplitude ω², given to the filter
    # beside the observation), not only their present velocity (aswarm.core.barriers.obs_rows). Runs and bundles
    # from before read back without it.
    hazard_accel: bool = True
    # Relative degree 2 where the drone's command has an acceleration limit (EnvConfig.command_accel_limit): the QP
    # chooses among the commands the drone can reach this control step, and each cylinder's row is a braking-distance
    # barrier on the command the drone flies now (aswarm.core.barriers.cylinder_braking_rows). Runs and bundles
    # from before read back without it.
    braking: bool = False
    # Braking rows for the neighbours too (aswarm.core.barriers.neighbour_braking_rows), beside their velocity rows:
    # the pair's closing speed must leave room for both drones to brake at the limit, each taking its share.
    # Independent of braking (the cylinders'); either one puts the QP on the reachable commands. Runs and bundles
    # from before read back without it.
    neighbour_braking: bool = False
    # 1/s: the class-K gain of those rows (0: the drone's gain, as every other row). Their barrier is a speed margin
    # that the braking itself keeps, so the gain only sets how fast it may be used up; at the drone's ~1.5/s a
    # follower 0.75 m behind, closing at 1 m/s, may speed up towards its leader at 0.5 m/s² at most. Not fitted to
    # the drone (the lag is in the barrier's look-ahead). Runs and bundles from before read back 0.
    neighbour_braking_gain: float = 0.0
    # Braking rows for the gate frames' bars in place of their velocity rows (aswarm.core.barriers.gate_rows): the
    # drone's speed towards a bar must leave room to brake at the command limit. Independent of the two above; any
    # of the three puts the QP on the reachable commands (reachable_box). Runs and bundles from before: false.
    gate_braking: bool = False
    # Braking barriers for the arena's walls and ceiling, each wall's row the tighter of it and its velocity row
    # (aswarm.core.barriers.wall_rows): a drone that fled a fast cylinder towards a wall must still be able to stop
    # before it at the command limit (the 1.5x moving cells' arena exits: the wall's velocity row turned negative with
    # the QP feasible, the flown command 1-2 m/s behind the filter's). On pretrained:dynamic at 1.5x it left no fewer
    # exits and cost 4-7 points of success (README, "braking rows for the walls"), so nothing stores it. Puts the QP
    # on the reachable commands as the three above do (reachable_box). Runs and bundles from before: false.
    wall_braking: bool = False
    # With braking or neighbour_braking: the QP chooses among the commands the drone can reach this step (the command
    # limit's box around the command it flies now). False: the rows alone, the limit applying after the filter as
    # it does without braking rows. At a braking gain of 10/s the box made two firmware drones head on stop apart on
    # one machine and not on another; at the drone's own top gain (1.47/s) they stop apart with the box or without
    # (tests/test_safety_filter_env.py, README "Braking rows for neighbours"). The box slows the race policy, which
    # was trained without it (mission 30.8 -> 38 s, README). Runs and bundles from before read back true.
    reachable_box: bool = True
    # When no command satisfies every row, the floor, walls, ceiling and gate frames take this share of the shared
    # slack and the cylinders and neighbours all of it (aswarm.core.barriers.slack_weights): 1 spreads it evenly, as
    # runs and bundles from before it do.
    static_slack: float = 0.1
    # m: > 0 also weighs each row's share of that slack by how near its hazard is, clip(h / this, proximity_slack_min,
    # 1) (aswarm.core.barriers.row_slack_weights): when no command satisfies every row, a far hazard's row (a fast
    # cylinder 1.3 m off, whose row already asks the drone to move at its speed) gives way before a near one's (a
    # neighbour 0.3 m off); under equal weights the two gave alike. 1 m flies pretrained:dynamic with no collision
    # over dynamic-3's 10,000 episodes and pretrained over race-8's 2,000, but lets a drone fleeing a fast cylinder
    # leave the arena (README, "Slack weighed by nearness"). 0 (runs and bundles from before it, and new runs): the
    # weights static_slack sets.
    proximity_slack: float = 0.0
    proximity_slack_min: float = 0.1  # the least factor a near row's weight takes under proximity_slack
    # Deadlock escape: where the QP leaves a drone less than escape_stuck of the speed the policy asked for along
    # its direction, and a nearby hazard (barrier under escape_near m) faces that direction, the QP is solved again
    # from the same speed along that hazard's horizontal tangent, on the side away from the other nearby hazards
    # (aswarm.core.barriers.escape_nominal). Only the nominal command changes, every row still holds: a drone
    # wedged between a cylinder and a wall (16 drones) or a gate frame (lab) slides around it instead of hovering
    # there. Off in runs and bundles from before it.
    escape: bool = False
    escape_stuck: float = 0.25
    escape_near: float = 0.3
    # A cap (1/s) on the gain of the moving cylinders' rows alone (0: none, their rows take the drone's gain as
    # every other row does): a per-hazard gain, conservative towards the hazards that move and as permissive as the
    # network likes towards the rest. Scaled with the other gains to the drone (fitted). It needs hazard_accel, whose
    # bounds tell the moving cylinders (bound > 0) from the static ones. Runs and bundles from before read back 0.
    moving_gain_max: float = 0.0
    # m: the moving cylinders' rows alone (bound > 0, as above) keep this much more than margin. Their row binds that
    # much sooner: the drone's command reaches the filter's only at the command acceleration limit, and in the one
    # collision of pretrained:dynamic over dynamic-2's 2,000 episodes the cylinder's row turned negative 0.45 s before
    # contact while the flown command lagged the filter's by up to 2.1 m/s (README, "A margin for what moves").
    # 0.05 or 0.1 m clear that collision, but at 1.5x the cylinders' speed they cost 4-10 points of success and more
    # collision episodes, so no shipped policy stores it. Not scaled to the drone (a distance). It needs hazard_accel.
    # Runs and bundles from before read back 0.
    moving_margin: float = 0.0
    # s: the moving cylinders' rows also keep this many seconds of the drone's closing speed on each (max(0, closing
    # speed) x this, m): the margin the command limit needs grows with how fast the drone and the cylinder close, so
    # a margin that only a closing pair keeps. 0.04 s clears dynamic-2's collision at no mission time but is no clear
    # gain at 1.5x (README), so no shipped policy stores it. Not scaled to the drone. It needs hazard_accel. Runs and
    # bundles from before read back 0.
    moving_margin_time: float = 0.0
    # m/s, 0 = off: the moving cylinders move on straight lines (a rail, a sweep), so each one's acceleration lies
    # along its velocity and its bound enters a drone's row as bound x |n . v_c/|v_c||, not the whole bound in the
    # worst direction; where a cylinder is slower than this (it turns, or its observed velocity's direction is
    # noise) any direction. A drone beside a sweep then need not keep off the acceleration that only pushes the
    # cylinder along it: the 1.5x cells' drones waited ~1.4 m off a band crossing a gate's exit (README, "Moving on
    # rails"). On pretrained:dynamic it trades collisions for success at 1.5x; pretrained:dynamic-rail, fine-tuned
    # under it (0.2), stores it. Not scaled to the drone. It needs hazard_accel. Runs and bundles from before read 0.
    rail_speed: float = 0.0
    # Share of a pair's gap each drone closes (reciprocal split; 1 treats neighbours as moving obstacles).
    neighbour_share: float = 0.5
    # m/s: > 0 splits each pair of drones by how fast each one closes on the other (its velocity towards the other),
    # softened by this speed, in place of neighbour_share (aswarm.core.barriers.closing_share): a drone that a
    # follower closes on (a leader braking for a gate frame) keeps less of the pair's row, so the row no longer
    # pushes it on into the frame, and the follower more. Both drones compute the same split from the velocities
    # both see, so their rows still add up to the pair condition; applied only where the filter sees the whole
    # swarm. Off by default: on the race it flew slower with more gate contacts (README, "Splitting a pair by
    # closing speed"). 0 (runs and bundles from before): neighbour_share.
    closing_split: float = 0.0
    closing_share_min: float = 0.1  # the least share either drone of a pair keeps under closing_split
    # Scale λ of the neighbours' rows' reference velocity (aswarm.core.barriers.neighbour_rows): 1 takes each pair's
    # current velocities (ORCA-style: a drone a follower closes on is asked to move on); 0 the classic form, where a
    # drone may always brake to rest along the pair's normal and each closes on the other at no more than its share
    # of γ h, whatever the other's speed away. Any λ keeps the pair's rows adding up. 0 flew the shipped race
    # policy with no collision and no infeasible QP, but stalled its column at 8 drones (README, "The classic
    # reference"). Runs and bundles from before read back 1.
    neighbour_reference: float = 1.0
    # m/s: > 0 lowers that scale with how fast each pair closes, to neighbour_reference · max(0, 1 − c / this) at
    # closing speed c (the same for both drones, so the rows still add up): a column at one speed keeps the current
    # velocities as reference (a follower may keep pace, where the classic form stalled the 8-drone race), a pair
    # closing fast the classic form (a leader braking for a gate frame may brake, its follower must). 0.5 flew the
    # shipped race policy with no collision over 10,000 race episodes and 1 in 2,000 at 8 drones (README, "Releasing
    # the reference as a pair closes").
    # 0 (runs and bundles from before, which read back 0): the scale stays neighbour_reference.
    neighbour_release: float = 0.5
    floor_z: float = 0.0  # m, the floor's height (the floor barrier keeps floor_z + drone radius + margin)
    # The QP: weight of the shared slack, budget of active-set steps, feasibility tolerance (m/s). 16 steps
    # left no problem unfinished in 20 000 dense random scenes where 12 left 4 (agents/cbf_filter.py).
    rho: float = 1e6
    max_iter: int = 16
    tol: float = 1e-6

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if f.name in _FLAGS:
                if not isinstance(v, bool):
                    raise ValueError(f"invalid safety_filter.{f.name}={v!r}: allowed: true or false")
                continue
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise ValueError(f"invalid safety_filter.{f.name}={v!r}: allowed: a finite number")
        if not 0 < self.gain_min < self.gain_max:
            raise ValueError(f"invalid gain_min={self.gain_min}, gain_max={self.gain_max}: need 0 < min < max")
        for name in ("static_slack", "proximity_slack_min"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"invalid safety_filter.{name}={getattr(self, name)!r}: allowed: (0, 1]")
        for name in ("fixed_gain", "rho", "max_iter", "tol"):
            if getattr(self, name) <= 0:
                raise ValueError(f"invalid safety_filter.{name}={getattr(self, name)!r}: allowed: > 0")
        for name in ("moving_gain_max", "moving_margin", "moving_margin_time", "rail_speed", "neighbour_braking_gain",
                     "margin", "lookahead_xy", "lookahead_z", "lookahead_accel", "lookahead_scale", "escape_stuck",
                     "escape_near", "closing_split", "neighbour_release", "proximity_slack"):
            if getattr(self, name) < 0:
                raise ValueError(f"invalid safety_filter.{name}={getattr(self, name)!r}: allowed: >= 0")
        for name in ("moving_gain_max", "moving_margin", "moving_margin_time", "rail_speed"):
            if getattr(self, name) > 0 and not self.hazard_accel:  # the bounds are what tell a moving cylinder
                raise ValueError(f"invalid safety_filter.{name}={getattr(self, name)!r} with hazard_accel=false: "
                                 "allowed: 0, or hazard_accel=true")
        if self.lookahead_accel > 0 and self.lookahead_xy <= 0:  # the fit's c1 is not the drone's lag
            raise ValueError(f"invalid safety_filter.lookahead_accel={self.lookahead_accel!r} with lookahead_xy="
                             f"{self.lookahead_xy!r}: allowed: lookahead_accel 0, or lookahead_xy > 0 (its fit's c1, "
                             "e.g. 0.207 with 0.039)")
        if not 0 < self.neighbour_share <= 1:
            raise ValueError(f"invalid safety_filter.neighbour_share={self.neighbour_share!r}: allowed: (0, 1]")
        if not 0 <= self.neighbour_reference <= 1:
            raise ValueError(f"invalid safety_filter.neighbour_reference={self.neighbour_reference!r}: allowed: [0, 1]")
        if not 0 < self.closing_share_min <= 0.5:
            raise ValueError(f"invalid safety_filter.closing_share_min={self.closing_share_min!r}: allowed: (0, 0.5]")


    def brakes(self, command_rate: tuple[float, float] | None) -> bool:
        """Whether the filter takes braking rows (and, with ``reachable_box``, the reachable box) for a drone whose
        command changes at most ``command_rate[0]`` m/s² (every ``command_rate[1]`` s): ``braking``,
        ``neighbour_braking``, ``gate_braking`` or ``wall_braking`` on and a limit to brake at (none: no)."""
        return bool((self.braking or self.neighbour_braking or self.gate_braking or self.wall_braking) and command_rate
                    and command_rate[0] > 0)

    def fitted(self, lag_xy: float, lag_z: float) -> SafetyFilterConfig:
        """The filter for a drone whose velocity reaches 63 % of a step in ``lag_xy`` s horizontally and ``lag_z``
        vertically: gains scaled by TUNED_LAG / lag_xy where the drone is slower than the one they were tuned on,
        and with ``fit_lookahead`` the look-aheads set to ``lookahead_scale`` times the lags (the horizontal one
        kept where ``lookahead_accel`` > 0: a second-order fit's own; everything unchanged if ``fit_to_drone`` is
        off)."""
        if not self.fit_to_drone:
            return self
        scale = min(1.0, TUNED_LAG / lag_xy)
        k = self.lookahead_scale
        ahead = {"lookahead_xy": k * lag_xy, "lookahead_z": k * lag_z} if self.fit_lookahead else {}
        if self.lookahead_accel > 0:
            ahead.pop("lookahead_xy", None)
        return dataclasses.replace(self, gain_min=self.gain_min * scale, gain_max=self.gain_max * scale,
                                   fixed_gain=self.fixed_gain * scale, moving_gain_max=self.moving_gain_max * scale,
                                   fit_to_drone=False, **ahead)


# The config's true/false fields; every other field is a number.
_FLAGS = ("fit_to_drone", "fit_lookahead", "hazard_accel", "braking", "neighbour_braking", "gate_braking",
          "wall_braking", "reachable_box", "escape")


# s: the velocity lag of the drone the default gains were tuned on (the geometric controller's, 63 % of a step)
TUNED_LAG = 0.25

# Flat TrainConfig fields of runs written before the nested config (config.json, sweep files, flags),
# and the field of SafetyFilterConfig each became.
LEGACY_FIELDS = {"gain_min": "gain_min", "gain_max": "gain_max", "fixed_gain": "fixed_gain",
                 "filter_margin": "margin"}


def nest_legacy(fields: Mapping) -> dict:
    """TrainConfig arguments with the old flat names (:data:`LEGACY_FIELDS`) moved into ``safety_filter``.

    ``safety_filter`` in ``fields`` may be a SafetyFilterConfig or absent (it stays one), or a dict of its
    fields as config.json holds them (it stays one); a field given both ways in a dict is a ValueError.
    """
    out = dict(fields)
    flat = {LEGACY_FIELDS[k]: out.pop(k) for k in list(out) if k in LEGACY_FIELDS}
    if not flat:
        return out
    nested = out.get("safety_filter")
    if nested is None or isinstance(nested, SafetyFilterConfig):
        out["safety_filter"] = dataclasses.replace(nested or SafetyFilterConfig(), **flat)
        return out
    both = sorted(set(flat) & set(nested))
    if both:
        raise ValueError(f"invalid safety_filter.{both[0]}: given both flat and nested; allowed: one of the two")
    out["safety_filter"] = {**nested, **flat}
    return out


def manifest_fields(config: SafetyFilterConfig) -> dict:
    """The config as a bundle manifest's ``safety_filter`` entries (the field names, as numbers)."""
    return dataclasses.asdict(config)


def from_manifest(safety: Mapping) -> SafetyFilterConfig:
    """The config a manifest's ``safety_filter`` section holds. Every field has been written since format 1
    (bundles from before this config have them too), so a missing one is an error, not a default."""
    # Bundles from before these fields hold fitted (or hand-set) gains for a single-integrator filter.
    safety = {"fit_to_drone": False, "fit_lookahead": False, "lookahead_xy": 0.0, "lookahead_z": 0.0,
              "lookahead_accel": 0.0,
              "lookahead_scale": 1.0, "hazard_accel": False, "static_slack": 1.0, "braking": False,
              "neighbour_braking": False, "neighbour_braking_gain": 0.0, "gate_braking": False, "wall_braking": False,
              "reachable_box": True,
              "escape": False, "escape_stuck": 0.25, "escape_near": 0.3, "moving_gain_max": 0.0, "moving_margin": 0.0,
              "moving_margin_time": 0.0, "rail_speed": 0.0,
              "closing_split": 0.0, "closing_share_min": 0.1,
              "neighbour_reference": 1.0, "neighbour_release": 0.0, "proximity_slack": 0.0, "proximity_slack_min": 0.1,
              **safety}
    missing = [f.name for f in dataclasses.fields(SafetyFilterConfig) if f.name not in safety]
    if missing:
        raise ValueError(f"invalid manifest safety_filter: missing {', '.join(missing)}; allowed: a bundle from "
                         "aswarm export (re-export the checkpoint)")
    kinds = {f.name: f.type for f in dataclasses.fields(SafetyFilterConfig)}
    cast = {"int": int, "bool": bool}  # the annotations are strings (from __future__ import annotations)
    return SafetyFilterConfig(**{k: cast.get(kinds[k], float)(safety[k]) for k in kinds})
