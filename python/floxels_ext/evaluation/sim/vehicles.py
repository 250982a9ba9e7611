"""Vehicle shapes built from axis-aligned parts in the vehicle's own frame.

Why: a vehicle that is one box shows the lidar flat, featureless sides. When such a side slides
along itself, the distance-transform loss has no gradient along the motion (the aperture
problem), so box-shaped cars make the motion along the car's length much harder to recover than
it is on real vehicles, whose wheels, wheel arches, mirrors, window recesses, pillars, hood and
trunk steps, pickup beds and trailer gaps give the surface structure along its length.

Every part is a box aligned with the vehicle (same yaw), so the whole vehicle moves rigidly with
its actor pose: the ground-truth flow of a hit point is still the exact rigid motion of the
actor. Parts are ``(P, 6)`` arrays ``(cx, cy, cz, hx, hy, hz)``: centre relative to the actor's
box centre (at mid-height) and half extents; x forward, y left, z up. Shapes are a deterministic
function of the actor's size, class and instance id (no random numbers), so switching the detail
on or off leaves the scene layout and the lidar noise draws unchanged.
"""

from __future__ import annotations

import numpy as np

from floxels_ext.evaluation.sim.scene import CAR, OTHER_VEHICLE, Actor

__all__ = ["vehicle_parts", "vehicle_kind", "parts_extent"]


class _Parts:
    """Collects parts given as ground-based extents: x in [-L/2, L/2], y in [-W/2, W/2], z in [0, H]."""

    def __init__(self, size):
        self.L, self.W, self.H = size
        self.rows: list[tuple[float, ...]] = []

    def add(self, x0, x1, y0, y1, z0, z1):
        self.rows.append(((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2 - self.H / 2,
                          abs(x1 - x0) / 2, abs(y1 - y0) / 2, abs(z1 - z0) / 2))

    def sym(self, x0, x1, y_in, y_out, z0, z1):
        """A pair of parts mirrored about the centre line (y from y_in to y_out on each side)."""
        self.add(x0, x1, y_in, y_out, z0, z1)
        self.add(x0, x1, -y_out, -y_in, z0, z1)

    def wheels(self, axles, r, width=0.22, inset=0.05):
        for xa in axles:
            self.sym(xa - 0.85 * r, xa + 0.85 * r, self.W / 2 - inset - width, self.W / 2 - inset, 0.0, 2 * r)

    def array(self) -> np.ndarray:
        return np.asarray(self.rows, dtype=np.float64)


def vehicle_kind(actor: Actor) -> str | None:
    """'sedan', 'hatchback', 'pickup', 'van', 'bus', 'truck', or None (not a vehicle: keeps its box).

    Cars cycle through sedan / sedan / hatchback / pickup by instance id; other vehicles are told
    apart by size (the scene builders' vans are shorter than 7 m, trucks taller than 3.45 m).
    """
    L, _, H = actor.size
    if actor.cls == CAR:
        return ("sedan", "sedan", "hatchback", "pickup")[actor.instance % 4]
    if actor.cls == OTHER_VEHICLE:
        if L < 7.0:
            return "van"
        return "truck" if H >= 3.45 else "bus"
    return None


def _lower_body(p: _Parts, axles, r, clearance, arch_top, belt):
    """Sills and bumpers at full width with wheel arches cut out, a narrower core behind the
    arches (so they are recesses, not holes), the wheels, and the body band above the arches."""
    L, W = p.L, p.W
    p.add(-L / 2 + 0.1, L / 2 - 0.1, -W / 2 + 0.25, W / 2 - 0.25, clearance, belt)  # core
    gap = r + 0.1
    edges = sorted([-L / 2] + [x for xa in axles for x in (xa - gap, xa + gap)] + [L / 2])
    for x0, x1 in zip(edges[::2], edges[1::2]):  # segments between the arches
        if x1 - x0 > 0.05:
            p.add(x0, x1, -W / 2, W / 2, clearance + 0.08, arch_top)
    p.add(-L / 2 + 0.06, L / 2 - 0.06, -W / 2, W / 2, arch_top, belt)  # band above the arches, bumpers stick out
    p.wheels(axles, r)


def _greenhouse(p: _Parts, x0, x1, belt, top, pillars, glass_inset=0.14, pillar_inset=0.07):
    """Cabin with its glass set back from the body side and pillars standing proud of the glass."""
    W = p.W
    p.add(x0, x1, -W / 2 + glass_inset, W / 2 - glass_inset, belt, top)
    for xc, w in pillars:
        p.add(xc - w / 2, xc + w / 2, -W / 2 + pillar_inset, W / 2 - pillar_inset, belt, top - 0.04)


def _mirrors(p: _Parts, x, z):
    p.sym(x - 0.07, x + 0.07, p.W / 2 - 0.1, p.W / 2 + 0.17, z, z + 0.15)


def _car_parts(p: _Parts, kind: str) -> None:
    L, W, H = p.L, p.W, p.H
    r, clearance = 0.31, 0.17
    axles = (L / 2 - 0.9, -L / 2 + 0.95)
    belt = 0.6 * H
    _lower_body(p, axles, r, clearance, 2 * r + 0.1, belt)
    hood = 0.27 * L
    if kind == "sedan":
        cab0 = -L / 2 + 0.2 * L
    elif kind == "hatchback":
        cab0 = -L / 2 + 0.08
    else:  # pickup: short cabin and an open bed (floor, side walls, tailgate) behind it
        cab0 = -L / 2 + 0.45 * L
        bed0 = -L / 2 + 0.06
        p.sym(bed0, cab0 - 0.1, W / 2 - 0.08, W / 2, belt, belt + 0.28)
        p.add(bed0, bed0 + 0.08, -W / 2, W / 2, belt, belt + 0.28)
    cab1 = L / 2 - hood
    mid = (cab0 + cab1) / 2
    pillars = [(cab1 - 0.1, 0.18), (cab0 + 0.1, 0.2)] + ([(mid, 0.12)] if cab1 - cab0 > 1.6 else [])
    _greenhouse(p, cab0, cab1, belt, H, pillars)
    _mirrors(p, cab1 - 0.1, belt + 0.02)


def _van_parts(p: _Parts) -> None:
    L, W, H = p.L, p.W, p.H
    axles = (L / 2 - 0.95, -L / 2 + 1.0)
    belt = 0.45 * H
    _lower_body(p, axles, 0.35, 0.2, 0.8, belt)
    cab0, cab1 = -L / 2 + 0.06, L / 2 - 0.18 * L
    pillars = [(cab1 - 0.1, 0.18), (cab1 - 1.4, 0.15), (cab0 + 0.15, 0.25)]
    _greenhouse(p, cab0, cab1, belt, H, pillars, glass_inset=0.1, pillar_inset=0.05)
    _mirrors(p, cab1 - 0.1, belt + 0.05)


def _bus_parts(p: _Parts) -> None:
    L, W, H = p.L, p.W, p.H
    axles = (L / 2 - 2.6, -L / 2 + 3.0)
    belt = 1.25
    _lower_body(p, axles, 0.5, 0.3, 1.12, belt)
    p.add(-L / 2, L / 2, -W / 2, W / 2, H - 0.35, H)  # roof band
    n = max(int((L - 0.4) / 1.4), 2)  # window pillars every ~1.4 m
    xs = np.linspace(-L / 2 + 0.2, L / 2 - 0.2, n + 1)
    _greenhouse(p, -L / 2 + 0.05, L / 2 - 0.05, belt, H - 0.35, [(float(x), 0.16) for x in xs],
                glass_inset=0.06, pillar_inset=0.0)
    _mirrors(p, L / 2 - 0.25, H - 1.2)


def _truck_parts(p: _Parts) -> None:
    """Cab with its own wheels, a gap with the chassis and fifth wheel, and a raised trailer
    with side ribs, tandem rear wheels and landing gear."""
    L, W, H = p.L, p.W, p.H
    r = 0.5
    cab1, cab0 = L / 2, L / 2 - 2.3
    trl1 = cab0 - 0.6
    p.add(cab0, cab1, -W / 2, W / 2, 0.55, 1.9)  # cab lower body
    p.add(cab0, cab1 - 0.1, -W / 2 + 0.08, W / 2 - 0.08, 1.9, 3.1)  # cab upper, glass set back
    p.add(cab0, cab0 + 0.25, -W / 2 + 0.02, W / 2 - 0.02, 1.9, 3.0)  # cab rear pillar
    p.wheels([cab1 - 1.0], r)
    _mirrors(p, cab1 - 0.05, 2.0)
    p.add(-L / 2 + 0.5, cab0, -0.5, 0.5, 0.5, 1.0)  # chassis rails under the whole length
    p.add(-L / 2, trl1, -W / 2, W / 2, 1.2, H)  # trailer box
    for x in np.arange(-L / 2 + 0.6, trl1 - 0.3, 1.5):  # vertical ribs standing 3 cm proud
        p.add(float(x) - 0.05, float(x) + 0.05, -W / 2 - 0.03, W / 2 + 0.03, 1.25, H - 0.05)
    p.wheels([-L / 2 + 1.4, -L / 2 + 2.7], r)
    p.wheels([cab0 - 0.9], r)  # tractor drive axle under the trailer's front
    p.sym(trl1 - 2.0, trl1 - 1.8, W / 2 - 0.6, W / 2 - 0.45, 0.1, 1.2)  # landing gear legs


def vehicle_parts(actor: Actor) -> np.ndarray | None:
    """The actor's parts ``(P, 6)`` (see the module docstring), or None to keep its plain box."""
    kind = vehicle_kind(actor)
    if kind is None:
        return None
    p = _Parts(actor.size)
    if kind in ("sedan", "hatchback", "pickup"):
        _car_parts(p, kind)
    elif kind == "van":
        _van_parts(p)
    elif kind == "bus":
        _bus_parts(p)
    else:
        _truck_parts(p)
    return p.array()


def parts_extent(parts: np.ndarray) -> np.ndarray:
    """Half extents (3,) of a box centred on the actor that holds all its parts."""
    return (np.abs(parts[:, :3]) + parts[:, 3:]).max(axis=0)
