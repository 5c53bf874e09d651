"""The observation layout, shared by the simulator and the flight side (no JAX here, no numpy needed).

Each drone's row is ``[own | cylinders | neighbours]``; the tables give every field's size and
meaning, and :class:`ObsLayout` where it lives.
"""

from __future__ import annotations

import dataclasses

# target_dir is the offset over max(distance, this) (m): finite at the goal itself.
MIN_TARGET_DIST = 1e-3

OWN_FIELDS = (
    ("target_rel", 3, "m, world: drone position minus its current gate centre or goal"),
    ("target_normal", 3, "unit, world: direction of passage of the current gate (0 for a goal)"),
    ("next_target_rel", 3, "m, world: drone position minus the following gate (the current one if last)"),
    ("target_dir", 3, "unit, world: from the drone towards its current gate centre or goal"),
    ("prev_gate_rel", 3, "m, world: drone position minus the gate it passed last (0 before the first gate, goals)"),
    ("prev_gate_normal", 3, "unit, world: direction of passage of that gate (0 when there is none)"),
    ("altitude", 1, "m above the floor"),
    ("quat", 4, "body->world, [w, x, y, z]"),
    ("vel", 3, "m/s, world"),
    ("ang_vel", 3, "rad/s, body"),
    ("wall_clearance", 5, "m: drone centre to the arena's walls at x low, x high, y low, y high, and its ceiling"),
)
CYL_FIELDS = (
    ("rel_xy", 2, "m, world: cylinder centre minus drone position"),
    ("clearance", 1, "m: horizontal gap between drone sphere and cylinder surface"),
    ("vel_xy", 2, "m/s, world: cylinder velocity"),
    ("present", 1, "1 if the cylinder exists this episode, else 0 (all its features are 0)"),
)
NBR_FIELDS = (
    ("rel_pos", 3, "m, world: neighbour position minus drone position"),
    ("rel_vel", 3, "m/s, world: neighbour velocity minus drone velocity"),
    ("present", 1, "1 if the neighbour is still flying, else 0 (all its features are 0)"),
)


@dataclasses.dataclass(frozen=True)
class ObsLayout:
    """Where each part of an observation row lives: ``[own | cylinders | neighbours]``."""

    num_cylinders: int
    num_neighbours: int
    own_dim: int = sum(f[1] for f in OWN_FIELDS)
    cyl_dim: int = sum(f[1] for f in CYL_FIELDS)
    nbr_dim: int = sum(f[1] for f in NBR_FIELDS)

    @property
    def size(self) -> int:
        return self.own_dim + self.num_cylinders * self.cyl_dim + self.num_neighbours * self.nbr_dim

    @property
    def own_slices(self) -> dict[str, slice]:
        out, off = {}, 0
        for name, size, _ in OWN_FIELDS:
            out[name] = slice(off, off + size)
            off += size
        return out

    def split(self, obs):
        """Works on numpy and JAX arrays alike."""
        # [..., size] -> own [..., own_dim], cylinders [..., M, cyl_dim], neighbours [..., n-1, nbr_dim]
        a = self.own_dim
        b = a + self.num_cylinders * self.cyl_dim
        lead = obs.shape[:-1]
        return (obs[..., :a], obs[..., a:b].reshape(*lead, self.num_cylinders, self.cyl_dim),
                obs[..., b:].reshape(*lead, self.num_neighbours, self.nbr_dim))

    def describe(self) -> list[dict]:
        """Field-by-field description with offsets, units and frames (the manifest's ``observation.fields``)."""
        out, off = [], 0
        for group, fields, count in (("own", OWN_FIELDS, 1), ("cylinder", CYL_FIELDS, self.num_cylinders),
                                     ("neighbour", NBR_FIELDS, self.num_neighbours)):
            for k in range(count):
                for name, size, unit in fields:
                    out.append(dict(group=group, index=k, name=name, offset=off, size=size, meaning=unit))
                    off += size
        return out
