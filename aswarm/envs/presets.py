"""The scenario presets: plain data, imported by the config (which validates against it) and the layouts."""

from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class Scenario:
    kind: str  # "track" (gates in order), "crossing" (goal points) or "hover"
    description: str
    preset: dict


SCENARIOS: dict[str, Scenario] = {
    "hover": Scenario(
        "hover", "sanity task: one drone flies to a point within 1 m and stops there",
        dict(num_agents=1, num_obstacles=0, num_gates=0, episode_seconds=6.0,
             arena_low=(-3.0, -3.0, 0.0), arena_high=(3.0, 3.0, 3.0)),
    ),
    "obstacles": Scenario(
        "crossing", "paper Case 1: 4 drones cross an arena through 8 static cylinders to goal points",
        dict(num_agents=4, num_obstacles=8, num_gates=0, episode_seconds=15.0, obstacle_spacing=1.2,
             arena_low=(-5.5, -3.5, 0.0), arena_high=(5.5, 3.5, 3.0)),
    ),
    "race": Scenario(
        "track", "paper Case 2: closed circuit, 4 square gates in order, 8 static cylinders",
        # 60 s: the firmware drone (20 deg tilt limit, rotor lag, a filter fitted to its lag) takes 35-41 s a lap
        # where the geometric one took 24 s, and 40 s timed out 40 % of its episodes (README, issue #12).
        dict(num_agents=4, num_obstacles=8, num_gates=4, episode_seconds=60.0, start_spacing=0.8, start_interval=1.0),
    ),
    "dynamic": Scenario(
        "track", "the race track's gates with 1 to 3 moving cylinders crossing the racing line",
        dict(num_agents=4, num_obstacles=0, num_moving=3, min_moving=1, num_gates=4, episode_seconds=60.0,
             start_spacing=0.8, start_interval=1.0),
    ),
    # gate_clearance 0.7 (0.5 before session 18): at 0.5 a cylinder could stand on a gate's approach, 0.5 m of
    # track before a 0.5 m opening, where the filter's margins to the cylinder and the frame left no line through
    # it; policies stalled there (68 % success) and a longer run collapsed. At 0.7 the 3 cylinders fill the track's
    # 3 slots, jittered inside them, as a fixed course in a real room is (README: "The race among moving cylinders,
    # and the lab room").
    "lab": Scenario(
        "track", "the paper's real flight: 2 drones, 2 gates, 3 cylinders in a 4 x 4 x 2 m room",
        dict(num_agents=2, num_obstacles=3, num_gates=2, track_radii=(1.3, 0.9), episode_seconds=15.0,
             arena_low=(-2.0, -2.0, 0.0), arena_high=(2.0, 2.0, 2.0), obstacle_radius=0.1,
             obstacle_height=2.0, obstacle_spacing=0.8, obstacle_lateral=0.25, gate_clearance=0.7,
             start_spacing=0.4, gate_half_opening=0.25),
    ),
}
