"""Objects of the synthetic street: shapes made of convex primitives, textures, motions.

A primitive is the intersection of a few slabs (``lo <= p[axis] <= hi``) and axis-aligned
quadrics (``sum_i (k_i (p_i - c_i))^2 <= 1``: an ellipsoid, or an elliptic cylinder where
one ``k_i`` is 0) in its own frame; a ray meets it on ``[max t_in, min t_out]``, exactly
and in closed form.  Cars are a body (box with rounded edges = box cut by two
cylinders) + cabin + wheels; trucks a cargo box + cab + chassis + wheels; people are
ellipsoids (head, torso, hips, swinging legs and arms).  None fills its bounding box.

Object frame: x right, y DOWN, z forward (the object's heading); origin on the ground
below the centre of its bounding box.  Object textures live in primitive coordinates,
so they move with the object and look the same from both cameras.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .textures import material_texture


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Rotation about the (down) y axis by heading ``a``: object z -> world (sin a, 0, cos a)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


_BIG = 1e30


@dataclass
class Prim:
    slabs: list[tuple[int, float, float]]  # at most one per axis
    quads: list[tuple[np.ndarray, np.ndarray]]  # (centre (3,), k (3,)); at most two
    lo: np.ndarray  # conservative bounding box in the primitive frame
    hi: np.ndarray
    material: int = 0
    gain: float = 1.0
    R: np.ndarray = field(default_factory=lambda: np.eye(3))  # primitive -> object rotation
    c: np.ndarray = field(default_factory=lambda: np.zeros(3))  # primitive origin in the object frame

    def __post_init__(self) -> None:
        if len(self.quads) > 2 or len({a for a, _, _ in self.slabs}) != len(self.slabs):
            raise ValueError("a primitive has at most one slab per axis and two quadrics")

    def arrays(self) -> dict[str, np.ndarray]:
        """Constraints padded to 3 slabs + 2 quadrics (absent = always satisfied)."""
        slo = np.full(3, -_BIG)
        shi = np.full(3, _BIG)
        for a, l, h in self.slabs:
            slo[a], shi[a] = l, h
        qc = np.zeros((2, 3))
        qk2 = np.zeros((2, 3))
        qv = np.zeros(2, bool)
        for j, (c, k) in enumerate(self.quads):
            qc[j] = c
            qk2[j] = np.asarray(k, float) ** 2
            qv[j] = True
        lo, hi = self.lo, self.hi
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        return {"slo": slo, "shi": shi, "qc": qc, "qk2": qk2, "qv": qv, "corners": corners}

    def posed(self, R: np.ndarray, c: np.ndarray) -> "Prim":
        return Prim(self.slabs, self.quads, self.lo, self.hi, self.material, self.gain, R, c)


def rounded_box(lo, hi, k_side: float, k_end: float, material: int, gain: float = 1.0) -> Prim:
    """Box ``[lo, hi]`` with its edges along z rounded by ``k_side`` and along x by ``k_end``.

    ``k`` > 1 is how much larger than the box the cutting elliptic cylinder is (1.41 would
    leave the box untouched); smaller = rounder.
    """
    lo = np.asarray(lo, float)
    hi = np.asarray(hi, float)
    c = (lo + hi) / 2
    h = (hi - lo) / 2
    quads = []
    if k_side:
        quads.append((c.copy(), np.array([1 / (h[0] * k_side), 1 / (h[1] * k_side), 0.0])))
    if k_end:
        quads.append((c.copy(), np.array([0.0, 1 / (h[1] * k_end), 1 / (h[2] * k_end)])))
    slabs = [(i, float(lo[i]), float(hi[i])) for i in range(3)]
    return Prim(slabs, quads, lo, hi, material, gain)


def ellipsoid(centre, radii, material: int, gain: float = 1.0) -> Prim:
    c = np.asarray(centre, float)
    r = np.asarray(radii, float)
    return Prim([], [(c, 1.0 / r)], c - r, c + r, material, gain)


def wheel(x0: float, x1: float, z: float, r: float, material: int) -> Prim:
    c = np.array([0.0, -r, z])
    return Prim([(0, x0, x1)], [(c, np.array([0.0, 1 / r, 1 / r]))], np.array([x0, -2 * r, z - r]), np.array([x1, 0.0, z + r]), material)


# ---------------------------------------------------------------------------------------------


@dataclass(eq=False)
class Material:
    """A small tileable texture (albedo 0..1) and the size of one texel in metres."""

    image: np.ndarray
    texel: float


@dataclass(eq=False)
class Shape:
    label: str  # COCO class name
    size: tuple[float, float, float]  # width (x), height, length (z) in metres
    materials: list[Material]
    rigid: list[Prim] = field(default_factory=list)
    animate: Callable[[float], list[Prim]] | None = None  # phase -> primitives (people)
    _const: dict[str, np.ndarray] | None = field(default=None, repr=False)

    def prims(self, phase: float) -> list[Prim]:
        return self.animate(phase) if self.animate is not None else self.rigid

    @property
    def radius(self) -> float:
        w, h, l = self.size
        return 0.5 * float(np.sqrt(w * w + h * h + l * l)) + 0.6  # covers the contact shadow too

    def const(self) -> dict[str, np.ndarray]:
        """Stacked constraint arrays of the primitives (same for every animation phase)."""
        if self._const is None:  # built whole, then published: the two views render in threads
            prims = self.prims(0.0)
            arrs = [p.arrays() for p in prims]
            const = {k: np.stack([a[k] for a in arrs]) for k in arrs[0]}
            const["mat"] = np.array([p.material for p in prims], np.int64)
            const["gain"] = np.array([p.gain for p in prims], np.float32)
            if self.animate is None:
                const["R"] = np.stack([p.R for p in prims])
                const["c"] = np.stack([p.c for p in prims])
            self._const = const
        return self._const

    def pose_arrays(self, phase: float) -> tuple[np.ndarray, np.ndarray]:
        """(R (p, 3, 3) primitive -> object, c (p, 3)) for an animation phase."""
        k = self.const()
        if self.animate is None:
            return k["R"], k["c"]
        prims = self.animate(phase)
        return np.stack([p.R for p in prims]), np.stack([p.c for p in prims])


def _mat(rng: np.random.Generator, base: float, kind: str, texel: float) -> Material:
    return Material(material_texture(rng, base, kind, 128), texel)


def make_car(rng: np.random.Generator, shared: dict[str, Material]) -> Shape:
    W = float(rng.uniform(1.7, 1.9))
    L = float(rng.uniform(3.9, 4.8))
    H = float(rng.uniform(1.40, 1.60))
    paint = _mat(rng, float(rng.choice([rng.uniform(0.1, 0.3), rng.uniform(0.45, 0.9)])), "paint", 0.03)
    mats = [paint, shared["glass"], shared["tire"]]
    body_top = 0.95
    prims = [
        rounded_box((-W / 2, -body_top, -L / 2), (W / 2, -0.22, L / 2), 1.12, 1.10, 0),
        rounded_box(
            (-W / 2 * 0.84, -H, -0.34 * L), (W / 2 * 0.84, -body_top + 0.08, 0.18 * L), 1.22, 1.14, 1
        ),
    ]
    r = 0.32
    for z in (-(L / 2 - 0.75), L / 2 - 0.8):
        prims.append(wheel(W / 2 - 0.24, W / 2 + 0.01, z, r, 2))
        prims.append(wheel(-W / 2 - 0.01, -W / 2 + 0.24, z, r, 2))
    return Shape("car", (W, H, L), mats, prims)


def make_truck(rng: np.random.Generator, shared: dict[str, Material], livery: bool = False) -> Shape:
    """A box truck: cargo box, cab, chassis, six wheels.  ``livery`` prints an advertising
    graphic (logo, company name, lettering) on the rear door -- delivery trucks' rears
    are the most textured thing in a city street."""
    W = 2.5
    L = float(rng.uniform(8.0, 9.5))
    H = float(rng.uniform(3.4, 3.8))
    cargo = _mat(rng, float(rng.uniform(0.55, 0.85)), "cargo", 0.035)
    cab = _mat(rng, float(rng.uniform(0.3, 0.7)), "paint", 0.03)
    mats = [cargo, cab, shared["glass"], shared["tire"]]
    cab_len = 2.2
    prims = [
        rounded_box((-W / 2, -H, -L / 2), (W / 2, -1.05, L / 2 - cab_len - 0.15), 1.28, 1.3, 0),
        rounded_box((-W / 2 * 0.97, -3.0, L / 2 - cab_len), (W / 2 * 0.97, -0.55, L / 2), 1.15, 1.12, 1),
        rounded_box((-W / 2 * 0.85, -1.95 - 0.9, L / 2 - 0.35), (W / 2 * 0.85, -1.95, L / 2 + 0.02), 1.2, 0.0, 2),
        rounded_box((-W / 2 * 0.9, -1.1, -L / 2 + 0.1), (W / 2 * 0.9, -0.5, L / 2 - cab_len), 1.25, 0.0, 3, 1.6),
    ]
    r = 0.5
    for z in (-L / 2 + 1.3, -L / 2 + 2.4, L / 2 - 1.3):
        prims.append(wheel(W / 2 - 0.35, W / 2 - 0.02, z, r, 3))
        prims.append(wheel(-W / 2 + 0.02, -W / 2 + 0.35, z, r, 3))
    if livery:
        # the rear door: a flat panel 2 cm proud of the cargo box, its own frame starting
        # at the panel's top-left corner so that one tile of the poster covers it exactly
        pw, ph = W - 0.24, H - 1.05 - 0.3
        sub = np.random.default_rng(rng.integers(0, 2**63))  # one draw from rng, the poster's own stream
        mats.append(Material(material_texture(sub, float(sub.choice([sub.uniform(0.08, 0.3), sub.uniform(0.7, 0.92)])), "poster", 128), pw / 128))
        panel = Prim([(0, 0.0, pw), (1, 0.0, ph), (2, 0.0, 0.03)], [], np.zeros(3), np.array([pw, ph, 0.03]), len(mats) - 1)
        prims.append(panel.posed(np.eye(3), np.array([-pw / 2, -H + 0.15, -L / 2 - 0.02])))
        # rear end below the door: tail lights, number plate, under-run bar
        mats.append(Material(material_texture(sub, 0.9, "skin", 128), 0.01))
        lamp, zr = len(mats) - 1, -L / 2 + 0.1 - 0.03
        for x0 in (-W / 2 * 0.9 + 0.05, W / 2 * 0.9 - 0.35):
            prims.append(Prim([(0, x0, x0 + 0.3), (1, -1.02, -0.88), (2, zr, zr + 0.05)], [], np.array([x0, -1.02, zr]), np.array([x0 + 0.3, -0.88, zr + 0.05]), lamp))
        mats.append(Material(material_texture(sub, 0.9, "plate", 128), 0.52 / 128))
        plate = Prim([(0, 0.0, 0.52), (1, 0.0, 0.11), (2, 0.0, 0.02)], [], np.zeros(3), np.array([0.52, 0.11, 0.02]), len(mats) - 1)
        prims.append(plate.posed(np.eye(3), np.array([-0.26, -0.85, zr - 0.01])))
        prims.append(rounded_box((-W / 2 * 0.88, -0.56, -L / 2 - 0.05), (W / 2 * 0.88, -0.44, -L / 2 + 0.1), 1.3, 0.0, 3))
    return Shape("truck", (W, H, L), mats, prims)


def make_person(rng: np.random.Generator, shared: dict[str, Material]) -> Shape:
    Hp = float(rng.uniform(1.55, 1.9))
    shirt = _mat(rng, float(rng.uniform(0.1, 0.9)), "cloth", 0.01)
    trousers = _mat(rng, float(rng.uniform(0.1, 0.6)), "cloth", 0.01)
    mats = [shirt, trousers, shared["skin"]]
    Ll = 0.47 * Hp  # leg length
    sh_y = -(Hp - 0.27)  # shoulder height (y down)
    head = ellipsoid((0, -(Hp - 0.115), 0), (0.095, 0.115, 0.105), 2)
    torso = ellipsoid((0, -(Ll + 0.08 + (Hp - 0.25 - Ll - 0.08) / 2), 0), (0.2, (Hp - 0.25 - Ll - 0.08) / 2 + 0.04, 0.12), 0)
    hips = ellipsoid((0, -(Ll + 0.02), 0), (0.17, 0.13, 0.115), 1)
    leg = ellipsoid((0, Ll / 2, 0), (0.075, Ll / 2 + 0.02, 0.085), 1)
    arm = ellipsoid((0, 0.3, 0), (0.055, 0.31, 0.06), 0)

    def animate(phase: float) -> list[Prim]:
        swing = 0.42 * np.sin(phase)
        return [
            head,
            torso,
            hips,
            leg.posed(rot_x(swing), np.array([0.095, -Ll, 0.0])),
            leg.posed(rot_x(-swing), np.array([-0.095, -Ll, 0.0])),
            arm.posed(rot_x(-0.8 * swing), np.array([0.255, sh_y, 0.0])),
            arm.posed(rot_x(0.8 * swing), np.array([-0.255, sh_y, 0.0])),
        ]

    return Shape("person", (0.6, Hp, 0.4), mats, animate=animate)


def shared_materials(rng: np.random.Generator) -> dict[str, Material]:
    return {
        "glass": _mat(rng, 0.15, "glass", 0.03),
        "tire": _mat(rng, 0.08, "tire", 0.02),
        "skin": _mat(rng, float(rng.uniform(0.45, 0.75)), "skin", 0.01),
    }


# ---------------------------------------------------------------------------------------------
# motions: t (seconds) -> (x, z, heading, travelled distance); map frame


class Motion:
    def state(self, t: float) -> tuple[float, float, float, float]:
        raise NotImplementedError

    def speed(self, t: float, dt: float = 0.05) -> float:
        x0, z0, _, _ = self.state(t - dt)
        x1, z1, _, _ = self.state(t + dt)
        return float(np.hypot(x1 - x0, z1 - z0) / (2 * dt))

    def moves_between(self, t0: float, t1: float) -> bool:
        """Whether the object moves at some time in [t0, t1]."""
        return True


@dataclass
class Parked(Motion):
    x: float
    z: float
    heading: float

    def state(self, t: float):
        return self.x, self.z, self.heading, 0.0

    def moves_between(self, t0: float, t1: float) -> bool:
        return False


@dataclass
class OnContour(Motion):
    """Follows the ring contour at offset ``d``: arc length ``s(t)``; ``backwards`` drives against the ring."""

    ring: object
    d: float
    s_of_t: Callable[[float], float]
    backwards: bool = False

    def state(self, t: float):
        s = self.s_of_t(t)
        x, z, th = self.ring.contour(s, self.d)  # type: ignore[attr-defined]
        th = float(th) + (np.pi if self.backwards else 0.0)
        return float(x), float(z), th, abs(s - self.s_of_t(0.0))


@dataclass
class Across(Motion):
    """Moves along ``d`` across the ring at ``(side, sigma)``: from d0 to d1 at speed v, starting at t0."""

    ring: object
    side: int
    sigma: float
    d0: float
    d1: float
    v: float
    t0: float

    def state(self, t: float):
        span = abs(self.d1 - self.d0)
        trav = float(np.clip((t - self.t0) * self.v, 0.0, span))
        d = self.d0 + np.sign(self.d1 - self.d0) * trav
        x, z = self.ring.side_point(self.side, self.sigma, d)  # type: ignore[attr-defined]
        th_side = float(self.ring.heading[self.side])  # type: ignore[attr-defined]
        # moving to larger d = away from the block = against the 'right' vector
        th = th_side - np.pi / 2 if self.d1 > self.d0 else th_side + np.pi / 2
        return float(x), float(z), th, trav

    def moves_between(self, t0: float, t1: float) -> bool:
        end = self.t0 + abs(self.d1 - self.d0) / self.v
        return self.t0 < t1 and end > t0


@dataclass
class SceneObject:
    id: int
    shape: Shape
    motion: Motion
    stride: float = 1.5  # metres per walking cycle (people)

    @property
    def label(self) -> str:
        return self.shape.label

    def pose(self, t: float, ground_y: float) -> tuple[np.ndarray, np.ndarray, float]:
        """(R object->map, origin in map (x, ground_y, z), animation phase)."""
        x, z, th, trav = self.motion.state(t)
        return rot_y(th), np.array([x, ground_y, z]), 2 * np.pi * trav / self.stride
