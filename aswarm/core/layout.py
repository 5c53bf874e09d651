"""The observation layout, shared by the simulator and the flight side (no JAX here, no numpy needed).

Each drone's row is ``[own | cylinders | neighbours]``; the tables give every field's size and
meaning, :class:`ObsLayout` where each group lives in a row, and :data:`OWN`, :data:`CYL`, :data:`NBR`
where each field lives in its group's rows. Code reads fields by name only (``CYL.get(cyl, "clearance")``,
``NBR.present(nbr)``), never by column number, so reordering or resizing a field is one edit of a table.
"""

from __future__ import annotations

import dataclasses

# target_dir is the offset over max(distance, this) (m): finite at the goal itself.
MIN_TARGET_DIST = 1e-3
# The policy sees observations normalised by running statistics and clipped to +-this (brax's
# running_statistics.normalize max_abs_value), in training and in the flight runtime alike.
OBS_NORM_CLIP = 10.0

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

# The safety filter's columns after the neighbour rows where its look-ahead is second order
# (``SafetyFilterConfig.lookahead_accel``, ``EnvConfig.filter_neighbour_accel``): one row per neighbour row, in
# their order. The policy never reads them (they follow every column it reads).
NBR_ACCEL_FIELDS = (
    ("tilt_accel", 2, "m/s², world, horizontal: the neighbour's acceleration from its attitude, "
                      "g (R e_z)_xy / (R e_z)_z (aswarm.core.geometry.tilt_accel; 0 when absent)"),
)


# Presence flags are exactly 0 or 1 in the raw observation; tested against the midpoint so that no
# round-off (float32, a normaliser's round trip) can flip one.
PRESENT_THRESHOLD = 0.5


@dataclasses.dataclass(frozen=True)
class FieldGroup:
    """Named columns of one field group's rows (the last axis of ``own`` [..., own_dim], ``cyl`` [..., M, 6]
    or ``nbr`` [..., K, 7] as :meth:`ObsLayout.split` gives them). Works on numpy and JAX arrays alike."""

    name: str
    fields: tuple[tuple[str, int, str], ...]

    def __post_init__(self) -> None:
        # Every field's slice and column, built once: the flight runtime reads fields by name at every control
        # step (not dataclass fields, so equality and hashing still see only the table).
        slices, columns, off = {}, {}, 0
        for field, size, _ in self.fields:
            slices[field] = slice(off, off + size)
            columns[field] = off if size == 1 else slices[field]
            off += size
        object.__setattr__(self, "_slices", slices)
        object.__setattr__(self, "_columns", columns)

    @property
    def dim(self) -> int:
        return sum(size for _, size, _ in self.fields)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(name for name, _, _ in self.fields)

    def _unknown(self, name: str) -> KeyError:
        return KeyError(f"invalid {self.name} field {name!r}: allowed: {', '.join(self.names)}")

    def slice(self, name: str) -> slice:
        """Columns of field ``name`` (a slice, also for a field of one number)."""
        try:
            return self._slices[name]
        except KeyError:
            raise self._unknown(name) from None

    def column(self, name: str) -> int | slice:
        """Index of field ``name``: an int for a field of one number (reading it drops the axis), else a slice."""
        try:
            return self._columns[name]
        except KeyError:
            raise self._unknown(name) from None

    def get(self, rows, name: str):
        """Field ``name`` of ``rows`` [..., dim]: [..., size], or [...] for a field of one number."""
        return rows[..., self.column(name)]

    def present(self, rows):
        """[...] bool: the presence flag of ``rows`` [..., dim] (cylinder and neighbour groups)."""
        return self.get(rows, "present") > PRESENT_THRESHOLD


OWN = FieldGroup("own", OWN_FIELDS)
CYL = FieldGroup("cylinder", CYL_FIELDS)
NBR = FieldGroup("neighbour", NBR_FIELDS)
NBR_ACCEL = FieldGroup("neighbour_accel", NBR_ACCEL_FIELDS)


def neighbour_slots(num_agents: int, max_neighbours: int, filter_neighbours: int = 0) -> tuple[int, int]:
    """(neighbour rows of the policy's observation, neighbour rows the safety filter takes) for a swarm of
    ``num_agents`` (``EnvConfig.max_neighbours`` and ``filter_neighbours``). The policy sees every other drone
    (``max_neighbours`` 0) or its K nearest; the filter sees as many, or, when ``filter_neighbours`` is larger than
    K, the ``filter_neighbours`` nearest (at most every other drone): an observation built with more nearest rows
    begins with the policy's own, nearest first, so the policy reads a prefix of the filter's."""
    others = max(num_agents - 1, 0)
    policy = max_neighbours or others
    if not max_neighbours or filter_neighbours <= policy:
        return policy, policy
    return policy, max(policy, min(filter_neighbours, others))


def observed_neighbours(num_agents: int, max_neighbours: int, filter_neighbours: int = 0) -> int:
    """``observe``'s ``max_neighbours`` for the observation the simulator and the flight runtime build: the filter's
    nearest rows where it takes more than the policy (:func:`neighbour_slots`), else ``max_neighbours`` itself (0:
    every other drone in index order)."""
    policy, wide = neighbour_slots(num_agents, max_neighbours, filter_neighbours)
    return wide if wide > policy else max_neighbours


@dataclasses.dataclass(frozen=True)
class ObsLayout:
    """Where each part of an observation row lives: ``[own | cylinders | neighbours]``, and with
    ``neighbour_accel`` (the safety filter's observation only) ``[... | neighbours' accelerations]``."""

    num_cylinders: int
    num_neighbours: int
    own_dim: int = OWN.dim
    cyl_dim: int = CYL.dim
    nbr_dim: int = NBR.dim
    neighbour_accel: bool = False

    @property
    def size(self) -> int:
        return self._neighbours_end + (self.num_neighbours * NBR_ACCEL.dim if self.neighbour_accel else 0)

    @property
    def _neighbours_end(self) -> int:
        return self.own_dim + self.num_cylinders * self.cyl_dim + self.num_neighbours * self.nbr_dim

    @property
    def own_slices(self) -> dict[str, slice]:
        """Every own field's columns, as slices (also for a field of one number)."""
        return {name: OWN.slice(name) for name in OWN.names}

    @property
    def presence_columns(self) -> tuple[int, ...]:
        """Columns of a whole row holding the presence flags of the M cylinders, then of the neighbours."""
        c, k = CYL.column("present"), NBR.column("present")
        cyl0 = self.own_dim
        nbr0 = cyl0 + self.num_cylinders * self.cyl_dim
        return (tuple(cyl0 + i * self.cyl_dim + c for i in range(self.num_cylinders))
                + tuple(nbr0 + i * self.nbr_dim + k for i in range(self.num_neighbours)))

    def split(self, obs):
        """Works on numpy and JAX arrays alike."""
        # [..., size] -> own [..., own_dim], cylinders [..., M, cyl_dim], neighbours [..., n-1, nbr_dim]
        a = self.own_dim
        b = a + self.num_cylinders * self.cyl_dim
        lead = obs.shape[:-1]
        nbr = obs[..., b:self._neighbours_end] if self.neighbour_accel else obs[..., b:]
        return (obs[..., :a], obs[..., a:b].reshape(*lead, self.num_cylinders, self.cyl_dim),
                nbr.reshape(*lead, self.num_neighbours, self.nbr_dim))

    def neighbour_accels(self, obs):
        """[..., K, NBR_ACCEL.dim] the neighbours' accelerations (rows of :data:`NBR_ACCEL`), in the order of their
        rows; a layout without them raises. Works on numpy and JAX arrays alike."""
        if not self.neighbour_accel:
            raise ValueError("this observation layout has no neighbour accelerations: allowed: a layout with "
                             "neighbour_accel=True (EnvConfig.filter_neighbour_accel)")
        return obs[..., self._neighbours_end:].reshape(*obs.shape[:-1], self.num_neighbours, NBR_ACCEL.dim)

    def describe(self) -> list[dict]:
        """Field-by-field description with offsets, units and frames (the manifest's ``observation.fields``)."""
        out, off = [], 0
        groups = [("own", OWN_FIELDS, 1), ("cylinder", CYL_FIELDS, self.num_cylinders),
                  ("neighbour", NBR_FIELDS, self.num_neighbours)]
        if self.neighbour_accel:
            groups.append((NBR_ACCEL.name, NBR_ACCEL_FIELDS, self.num_neighbours))
        for group, fields, count in groups:
            for k in range(count):
                for name, size, unit in fields:
                    out.append(dict(group=group, index=k, name=name, offset=off, size=size, meaning=unit))
                    off += size
        return out
