"""Scenarios: the camera's drive and the objects' motions, as a :class:`Plan`.

Every scenario drives the stereo rig along the ring road (right-hand traffic, the block
on the right, right turns at the corners, about 32 km/h on the straights -- ``convoy``
22 km/h -- and 16 km/h in the turns) through the same seeded city, with parked cars
along both curbs and people on the sidewalks.  What differs is the traffic:

``static``    parked cars, a parked truck and standing people; nothing moves.
``crossing``  the rig stops at the zebra crossing before the intersection and waits 6 s
              while a group of people crosses right in front of it and a queue of cars
              and a truck crawls through the congested intersection behind them (moving
              objects are most of what the standing camera sees); people also cross
              mid-block and at the far zebra, timed to clear the rig's lane before it
              arrives.  Starts 23 m before the first stop line: brakes from frame ~9,
              stands still from frame ~41 to ~101, then pulls away.
``convoy``    a box truck with an advertising livery on its rear door drives 4.5 m ahead
              of the rig at the rig's speed (22 km/h, dense city traffic), filling ~31 %
              of the view and 30-40 % of the ORB features for the whole sequence: the
              case that breaks SLAM without masks (it is pulled toward "standing still").
``oncoming``  cars and a truck in the opposite lane drive towards the rig and pass it.
``loop``      one full lap of the ~390 m ring (the rig returns to its start pose) and on
              over the first 60 m again, with oncoming traffic, crossing and walking
              people: loop closure.
``mixed``     all of it: crossings, oncoming traffic, a car ahead, walkers, parked cars.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from .objects import (
    Across,
    OnContour,
    Parked,
    SceneObject,
    make_car,
    make_person,
    make_truck,
    shared_materials,
)
from .world import World

FPS = 10.0


@dataclass
class Plan:
    """What happens in a sequence (map frame, see :mod:`.world`)."""

    scenario: str
    frames: int
    dt: float
    cam_d: float
    cam_s: Callable[[float], float]  # arc length on the contour cam_d at time t
    objects: list[SceneObject]
    ring: object = field(repr=False, default=None)

    def camera(self, index: int) -> tuple[float, float, float]:
        """(x, z, heading) of the left camera at frame ``index``."""
        s = self.cam_s(index * self.dt)
        x, z, th = self.ring.contour(s, self.cam_d)  # type: ignore[attr-defined]
        return float(x), float(z), float(th)


class _Drive:
    """Camera arc length s(t) on the contour ``d``: fast on straights, slow in the corners.

    ``stops``: (arc length, seconds) where the rig comes to a halt and waits (at a stop
    line): it brakes over ``brake`` metres and pulls away over ``pull_away`` metres
    (constant deceleration / acceleration), standing exactly still in between.
    """

    def __init__(
        self,
        world: World,
        d: float,
        s0: float,
        v_straight: float,
        v_turn: float,
        duration: float,
        stops: Sequence[tuple[float, float]] = (),
        brake: float = 15.0,
        pull_away: float = 20.0,
    ):
        self.ring = world.ring
        self.d = d
        ramp = 15.0
        ds = 0.05
        length = v_straight * (duration + 5.0) + 10.0
        s = s0 + np.arange(0.0, length + ds, ds)
        seg, local = world.ring.segment_of(s, d)
        side_len = world.ring.side_len[seg // 2]
        dist = np.minimum(local, side_len - local)
        wgt = np.where(seg % 2 == 1, 1.0, np.where(dist < ramp, 0.5 * (1 + np.cos(np.pi * np.minimum(dist, ramp) / ramp)), 0.0))
        v = v_straight + (v_turn - v_straight) * wgt
        stops = sorted((float(a), float(w)) for a, w in stops if s0 < a < s[-1])
        for s_stop, _ in stops:  # v = sqrt(2 a x) towards and away from the stop line
            x = np.where(s < s_stop, (s_stop - s) / brake, (s - s_stop) / pull_away)
            v = v * np.sqrt(np.clip(x, 1e-4, 1.0))
        t = np.concatenate([[0.0], np.cumsum(ds / (0.5 * (v[1:] + v[:-1])))])
        for s_stop, wait in stops:  # stand still: the stop line's sample twice, ``wait`` apart
            k = int(np.searchsorted(s, s_stop))
            ts = float(np.interp(s_stop, s, t))
            s = np.concatenate([s[:k], [s_stop, s_stop], s[k:]])
            t = np.concatenate([t[:k], [ts, ts + wait], t[k:] + wait])
        self.t_tab = t
        self.s_tab = s
        self.stops = stops

    def s(self, t: float) -> float:
        return float(np.interp(t, self.t_tab, self.s_tab))

    def t_at(self, s: float) -> float:
        """Time when the camera reaches arc length ``s`` (inf if never; the arrival at a stop line)."""
        if s > self.s_tab[-1]:
            return float("inf")
        k = int(np.searchsorted(self.s_tab, s, side="left"))
        if k < len(self.s_tab) and self.s_tab[k] == s:
            return float(self.t_tab[k])
        return float(np.interp(s, self.s_tab, self.t_tab))

    def stopped(self, s_stop: float) -> tuple[float, float]:
        """(arrival, departure) times at the stop line ``s_stop``."""
        k = int(np.searchsorted(self.s_tab, s_stop, side="left"))
        return float(self.t_tab[k]), float(self.t_tab[k + 1])


class _Builder:
    def __init__(self, world: World, rng: np.random.Generator):
        self.w = world
        self.p = world.params
        self.ring = world.ring
        self.rng = rng
        self.mats = shared_materials(rng)
        self.objects: list[SceneObject] = []

    def _add(self, shape, motion, stride: float = 1.5) -> SceneObject:
        if len(self.objects) >= 255:
            raise RuntimeError("at most 255 objects per sequence (uint8 instance masks)")
        ob = SceneObject(len(self.objects) + 1, shape, motion, stride)
        self.objects.append(ob)
        return ob

    def car(self):
        return make_car(self.rng, self.mats)

    def truck(self, livery: bool = False):
        return make_truck(self.rng, self.mats, livery=livery)

    def person(self):
        return make_person(self.rng, self.mats)

    # -- static population
    def parked(self, sides=(0, 1, 2, 3), density: float = 0.75, trucks: int = 0, keepout=()) -> None:
        """Cars (and ``trucks`` trucks) along both parking strips; none near the intersections
        or within 2 m of a ``keepout`` (side, sigma) where people will cross."""
        p, ring, rng = self.p, self.ring, self.rng
        for side in sides:
            L = float(ring.side_len[side])
            mid = L / 2
            th = float(ring.heading[side])
            for d, heading in ((p.d_park_in, th), (p.d_park_out, th + np.pi)):
                sg = float(rng.uniform(3.0, 6.0))
                while sg < L - 3.0:
                    use_truck = trucks > 0 and rng.random() < 0.15
                    shape = self.truck() if use_truck else self.car()
                    half = shape.size[2] / 2
                    c = sg + half
                    if c + half > L - 3.0:
                        break
                    if abs(c - mid) < p.gap / 2 + 5.5 + half:
                        sg = mid + p.gap / 2 + 5.5
                        continue
                    blocked = any(ks == side and abs(c - kg) < half + 2.0 for ks, kg, *_ in keepout)
                    if rng.random() < density and not blocked:
                        if use_truck:
                            trucks -= 1
                        x, z = ring.side_point(side, c, d + float(rng.uniform(-0.15, 0.15)))
                        self._add(shape, Parked(float(x), float(z), heading + float(rng.normal(0, 0.03))))
                    sg = c + half + float(rng.uniform(0.8, 3.5))

    def standing(self, n_per_side: int = 3, sides=(0, 1, 2, 3)) -> None:
        p, ring, rng = self.p, self.ring, self.rng
        for side in sides:
            L = float(ring.side_len[side])
            for _ in range(n_per_side):
                sg = float(rng.uniform(4.0, L - 4.0))
                if abs(sg - L / 2) < p.gap / 2 + 4.0:  # not in the mouth of a side street
                    sg = L / 2 + np.sign(sg - L / 2 + 1e-9) * (p.gap / 2 + 4.0 + float(rng.uniform(0, 3)))
                d = float(rng.choice([rng.uniform(0.6, 1.1), rng.uniform(18.9, 19.4)]))  # by the facades
                x, z = ring.side_point(side, sg, d)
                self._add(self.person(), Parked(float(x), float(z), float(rng.uniform(0, 2 * np.pi))))

    def walkers(self, drive: _Drive, n: int, duration: float) -> None:
        p, ring, rng = self.p, self.ring, self.rng
        for _ in range(n):
            d = float(rng.choice([rng.uniform(1.8, 3.2), rng.uniform(16.8, 18.2)]))
            # somewhere the camera will pass: ahead of it, at a random time
            t_see = float(rng.uniform(0.0, max(duration - 3.0, 0.5)))
            s_cam = drive.s(t_see) + float(rng.uniform(15.0, 40.0))
            s_obj = float(ring.s_of_phi(ring.phi(s_cam, drive.d), d))
            v = float(rng.uniform(1.1, 1.6))
            back = bool(rng.random() < 0.5)
            sgn = -1.0 if back else 1.0
            s_at = (lambda s_obj, v, sgn, t_see: (lambda t: s_obj + sgn * v * (t - t_see)))(s_obj, v, sgn, t_see)
            self._add(self.person(), OnContour(ring, d, s_at, backwards=back), stride=1.4)

    # -- traffic
    def crossing_person(self, drive: _Drive, side: int, sigma: float, inward: bool | None = None, offset: float | None = None) -> float:
        """A person crossing at (side, sigma), clear of the camera's lane when it arrives; returns t_arr."""
        p, ring, rng = self.p, self.ring, self.rng
        t_arr = self._arrival(drive, side, sigma)
        if not np.isfinite(t_arr):
            return t_arr
        v = float(rng.uniform(1.2, 1.7))
        if inward is None:
            inward = bool(rng.random() < 0.5)
        if inward:  # from the far sidewalk towards the block: still in the oncoming lane at arrival
            d0, d1 = 18.5, 1.5
            d_arr = float(rng.uniform(11.8, 14.0))
        else:  # from the block side outwards: already past the camera's lane
            d0, d1 = 1.5, 18.5
            d_arr = float(rng.uniform(12.0, 16.5))
        t0 = t_arr - abs(d_arr - d0) / v
        off = float(rng.uniform(-0.8, 0.8)) if offset is None else offset
        self._add(self.person(), Across(ring, side, sigma + off, d0, d1, v, t0), stride=1.4)
        return t_arr

    def crossing_car(self, drive: _Drive, side: int) -> float:
        p, ring, rng = self.p, self.ring, self.rng
        mid = float(ring.side_len[side]) / 2
        t_arr = self._arrival(drive, side, mid - p.gap / 2)
        if not np.isfinite(t_arr):
            return t_arr
        shape = self.car()
        half = shape.size[2] / 2
        v = float(rng.uniform(5.0, 7.5))
        if rng.random() < 0.5:  # out of the dead-end street, across, into the side street
            d0, d1, sig = -(p.inner_depth - 8.0), p.d_outer_wall + p.outer_depth - 8.0, mid + 2.0
            d_clear = p.d_centre + half + 1.8
        else:
            d0, d1, sig = p.d_outer_wall + p.outer_depth - 8.0, -(p.inner_depth - 8.0), mid - 2.0
            d_clear = p.d_inner_curb - half - 1.8
        t0 = t_arr - 1.2 - abs(d_clear - d0) / v
        self._add(shape, Across(ring, side, sig, d0, d1, v, t0))
        return t_arr

    def oncoming(self, drive: _Drive, t_meet: float, truck: bool = False) -> None:
        p, ring, rng = self.p, self.ring, self.rng
        v = float(rng.uniform(8.0, 11.0))
        s_m = float(ring.s_of_phi(ring.phi(drive.s(t_meet), drive.d), p.d_lane_out))
        f = (lambda s_m, v, t_meet: (lambda t: s_m - v * (t - t_meet)))(s_m, v, t_meet)
        self._add(self.truck() if truck else self.car(), OnContour(ring, p.d_lane_out + float(rng.uniform(-0.2, 0.2)), f, backwards=True))

    def ahead(self, drive: _Drive, gap: float, dv: float = 0.0, truck: bool = False, livery: bool = False) -> SceneObject:
        shape = self.truck(livery) if truck else self.car()
        g = gap + shape.size[2] / 2
        f = (lambda g, dv: (lambda t: drive.s(t) + g + dv * t))(g, dv)
        return self._add(shape, OnContour(self.ring, drive.d, f))

    def finalize(self, horizon: float) -> list[SceneObject]:
        """Drop objects that would run into another one (the later-added of each pair), renumber.

        Footprints are discs (people) or rows of discs (vehicles), checked every 0.2 s.
        """
        objs = self.objects
        ts = np.arange(0.0, horizon + 1e-9, 0.2)
        owner, radius, centres = [], [], []
        moving = np.array([ob.motion.moves_between(0.0, horizon) for ob in objs])
        for j, ob in enumerate(objs):
            W, _, L = ob.shape.size
            if ob.label == "person":
                offs, r = [0.0], 0.3
            else:
                k = 3 if L < 6 else 5
                offs, r = list(np.linspace(-L / 2 + W / 2, L / 2 - W / 2, k)), W / 2 + 0.15
            states = [ob.motion.state(float(t)) for t in (ts if moving[j] else ts[:1])]
            st = np.array(states)
            if not moving[j]:
                st = np.repeat(st, len(ts), 0)
            fx, fz = np.sin(st[:, 2]), np.cos(st[:, 2])
            for o in offs:
                owner.append(j)
                radius.append(r)
                centres.append(np.stack([st[:, 0] + o * fx, st[:, 1] + o * fz], 1))
        owner_a = np.array(owner)
        rad = np.array(radius)
        C = np.stack(centres, 1)  # (T, circles, 2)
        limit = rad[:, None] + rad[None, :]
        care = (owner_a[:, None] < owner_a[None, :]) & (moving[owner_a][:, None] | moving[owner_a][None, :])
        pairs = set()
        for a in range(0, len(ts), 64):
            c = C[a : a + 64]
            d = np.sqrt(((c[:, :, None, :] - c[:, None, :, :]) ** 2).sum(-1))
            hit = np.any(d < limit[None], axis=0) & care
            for i, k in zip(*np.nonzero(hit)):
                pairs.add((int(owner_a[i]), int(owner_a[k])))
        dropped: set[int] = set()
        for i, k in sorted(pairs, key=lambda p: (p[1], p[0])):
            if i not in dropped and k not in dropped:
                dropped.add(k)
        keep = [ob for j, ob in enumerate(objs) if j not in dropped]
        for n, ob in enumerate(keep, start=1):
            ob.id = n
        self.objects = keep
        return keep

    def _arrival(self, drive: _Drive, side: int, sigma: float) -> float:
        return drive.t_at(self.s_ahead(drive, side, sigma))

    def s_ahead(self, drive: _Drive, side: int, sigma: float) -> float:
        """Arc length (on the camera's contour) of the next pass at (side, sigma)."""
        ring = self.ring
        ph = 2 * side + sigma / float(ring.side_len[side])
        s0 = drive.s(0.0)
        ph0 = float(ring.phi(s0, drive.d))
        while ph < ph0:
            ph += 8
        return float(ring.s_of_phi(ph, drive.d))

    # -- the rig waiting at a zebra crossing before an intersection
    def crowd(self, side: int, zc: float, t_arr: float, t_dep: float) -> None:
        """A group of people crossing the zebra at ``zc`` while the rig waits before it.

        Most come from the far sidewalk towards the block (they cross the oncoming lane,
        then the rig's), a few the other way; they walk in files 0.75 m apart across the
        zebra, 0.8 m behind one another, each file at one pace (no overtaking), and all
        have left the rig's lane 0.5 s before it pulls away.
        """
        p, ring, rng = self.p, self.ring, self.rng
        lo, hi = p.d_park_in + p.parking / 2 - 0.6, p.d_centre + 0.6  # the rig's lane + margin
        d_mid = p.d_lane_in
        files = [(-1.15, True), (-0.4, True), (0.35, True), (1.1, False)]
        for j, (off, inward) in enumerate(files):
            rows = int(rng.integers(2, 4)) if inward else int(rng.integers(1, 3))
            v = float(rng.uniform(1.15, 1.6))
            # the file's first walker passes the lane centre at t_mid
            t_mid = float(rng.uniform(t_arr + 0.3, t_arr + 2.0)) if inward else float(rng.uniform(t_arr + 0.8, t_arr + 3.0))
            last_clear = t_mid + ((rows - 1) * 0.8 + (d_mid - lo if inward else hi - d_mid)) / v
            if last_clear > t_dep - 0.5:
                t_mid -= last_clear - (t_dep - 0.5)
            sig = zc + off + float(rng.uniform(-0.05, 0.05))
            back = 0.8 * (rows - 1)
            for k in range(rows):  # the whole file starts and stops together, 0.8 m apart
                if inward:
                    d0, d1 = p.d_outer_curb + 1.0 + 0.8 * k, p.d_inner_curb - 1.2 - back + 0.8 * k
                    t0 = t_mid - (p.d_outer_curb + 1.0 - d_mid) / v
                else:
                    d0, d1 = p.d_inner_curb - 1.0 - 0.8 * k, p.d_outer_curb + 1.2 + back - 0.8 * k
                    t0 = t_mid - (d_mid - (p.d_inner_curb - 1.0)) / v
                self._add(self.person(), Across(ring, side, sig, d0, d1, v, t0), stride=1.4)

    def queue(self, side: int, mid: float, t_arr: float, t_dep: float, truck: bool) -> None:
        """Congested cross street: a queue of vehicles (the second one a truck if ``truck``)
        crawls through the intersection in its near lane, bumper to bumper at 1.6-2.4 m/s,
        while the rig waits at the zebra before it.  The head passed the rig's lane 3-5 s
        before the rig stopped; the tail clears the lane 2 s after the rig pulls away
        (before it reaches the intersection); each vehicle stops at its own place in the
        dead-end street."""
        p, ring, rng = self.p, self.ring, self.rng
        lane_d = p.d_lane_in
        v = float(rng.uniform(1.6, 2.4))
        t_head = t_arr - float(rng.uniform(3.0, 5.0))  # the head's front at lane_d
        shapes: list = []
        offsets: list[float] = []  # head front -> this vehicle's front, metres
        room = p.inner_depth - 1.0  # they park one behind the other in the dead-end street
        while True:
            sh = self.truck() if (truck and len(shapes) == 1) else self.car()
            off = 0.0 if not shapes else offsets[-1] + shapes[-1].size[2] + float(rng.uniform(1.5, 3.0))
            # its rear leaves the rig's lane (+0.5 m) at t_head + (off + length + lane/2 + 0.5) / v
            if shapes and (t_head + (off + sh.size[2] + p.lane / 2 + 0.5) / v > t_dep + 2.0 or off + sh.size[2] > room):
                break
            shapes.append(sh)
            offsets.append(off)
        for sh, off in zip(shapes, offsets):
            d0 = lane_d + v * t_head + off + sh.size[2] / 2  # centre at t = 0, moving to smaller d
            d1 = -room + off + sh.size[2] / 2
            self._add(sh, Across(ring, side, mid - 2.0, d0, d1, v, 0.0))

    def events_ahead(self, drive: _Drive, duration: float):
        """(side, sigma, t_arr) of the intersections the camera reaches within ``duration``."""
        out = []
        for side, mid in self.w.intersections:
            t = self._arrival(drive, side, mid)
            if t < duration + 2.0:
                out.append((side, mid, t))
        return sorted(out, key=lambda e: e[2])

    def spots_ahead(self, drive: _Drive, duration: float, spacing: float):
        """Mid-block crossing spots (side, sigma, t_arr) every ~spacing metres of the drive."""
        ring, p, rng = self.ring, self.p, self.rng
        out = []
        s = drive.s(0.0) + float(rng.uniform(20.0, 28.0))
        while True:
            t = drive.t_at(s)
            if not t < duration + 1.0:
                break
            seg, local = ring.segment_of(s, drive.d)
            seg = int(seg)
            if seg % 2 == 0:
                side = seg // 2
                L = float(ring.side_len[side])
                if 8.0 < local < L - 8.0 and abs(local - L / 2) > p.gap / 2 + 8.0:
                    out.append((side, float(local), t))
            s += spacing * float(rng.uniform(0.7, 1.3))
        return out


def _meet_times(rng: np.random.Generator, duration: float, first: float, every: tuple[float, float], busy: list[float]) -> list[float]:
    out = []
    t = first
    while t < duration + 4.0:
        if all(abs(t - b) > 3.5 for b in busy):
            out.append(t)
        t += float(rng.uniform(*every))
    return out


# ---------------------------------------------------------------------------------------------


def _start(world: World, side: int, sigma: float, d: float) -> float:
    return world.ring.s_of_side(side, sigma, d)


def _static(world: World, rng, frames: int, horizon: int) -> Plan:
    b = _Builder(world, rng)
    d = world.params.d_lane_in
    T = horizon / FPS
    drive = _Drive(world, d, _start(world, 1, 5.0, d), 9.0, 4.5, T)
    b.parked(density=0.8, trucks=2)
    b.standing(4)
    return Plan("static", frames, 1 / FPS, d, drive.s, b.finalize(T), world.ring)


WAIT = 6.0  # seconds the rig waits at a zebra crossing before an intersection (crossing)
STOP_BACK = 2.5  # metres from the camera to the zebra's near edge when it waits


def _crossing(world: World, rng, frames: int, horizon: int) -> Plan:
    b = _Builder(world, rng)
    p = world.params
    d = p.d_lane_in
    T = horizon / FPS
    s0 = _start(world, 1, 20.0, d)
    # the rig stops before the near zebra of every intersection it reaches
    plain = _Drive(world, d, s0, 9.0, 4.5, T)
    lines = {}
    for side, mid, _ in b.events_ahead(plain, T):
        zc = mid - p.gap / 2 - 2.2
        lines[(side, mid)] = (zc, b.s_ahead(plain, side, zc - 1.5 - STOP_BACK))
    drive = _Drive(world, d, s0, 9.0, 4.5, T, stops=[(sl, WAIT) for _, sl in lines.values()])
    spots = b.spots_ahead(drive, T, 35.0)
    b.parked(density=0.6, keepout=spots)
    b.standing(2)
    for n_event, (side, mid, t) in enumerate(b.events_ahead(drive, T)):
        zc, s_line = lines.get((side, mid), (None, None))
        if s_line is None:
            continue
        t_arr, t_dep = drive.stopped(s_line)
        b.crowd(side, zc, t_arr, t_dep)
        b.queue(side, mid, t_arr, t_dep, truck=n_event % 2 == 0)
        b.crossing_person(drive, side, mid + p.gap / 2 + 2.2)  # the far zebra: clear before the rig comes
    for side, sg, t in spots:
        b.crossing_person(drive, side, sg)
    return Plan("crossing", frames, 1 / FPS, d, drive.s, b.finalize(T), world.ring)


CONVOY_GAP = 4.5  # metres from the camera to the lead truck's rear (slow, dense city traffic)
CONVOY_SPEED = 6.0  # m/s on the straights (22 km/h)


def _convoy(world: World, rng, frames: int, horizon: int) -> Plan:
    b = _Builder(world, rng)
    p = world.params
    d = p.d_lane_in
    T = horizon / FPS
    drive = _Drive(world, d, _start(world, 1, 5.0, d), CONVOY_SPEED, 4.5, T)
    b.ahead(drive, gap=CONVOY_GAP, truck=True, livery=True)
    b.parked(density=0.6)
    b.standing(2)
    for t in _meet_times(rng, T, 3.0, (4.0, 8.0), []):
        b.oncoming(drive, t)
    return Plan("convoy", frames, 1 / FPS, d, drive.s, b.finalize(T), world.ring)


def _oncoming(world: World, rng, frames: int, horizon: int) -> Plan:
    b = _Builder(world, rng)
    p = world.params
    d = p.d_lane_in
    T = horizon / FPS
    drive = _Drive(world, d, _start(world, 1, 5.0, d), 9.0, 4.5, T)
    b.parked(density=0.6)
    b.standing(2)
    times = _meet_times(rng, T, 2.5, (2.5, 5.0), [])
    truck_at = int(rng.integers(1, max(2, len(times))))
    for i, t in enumerate(times):
        b.oncoming(drive, t, truck=(i == truck_at))
    return Plan("oncoming", frames, 1 / FPS, d, drive.s, b.finalize(T), world.ring)


# the loop scenario drives this far past its start again: the loop is then seen from the
# places of the first pass (close points), as when a car drives round a block twice
LOOP_OVERLAP_M = 60.0


def _loop_frames(world: World) -> int:
    d = world.params.d_lane_in
    drive = _Drive(world, d, _start(world, 1, 10.0, d), 10.0, 4.5, 120.0)
    s_end = drive.s(0.0) + world.ring.length(d) + LOOP_OVERLAP_M
    return int(np.ceil(drive.t_at(s_end) * FPS)) + 1


def _loop(world: World, rng, frames: int, horizon: int) -> Plan:
    b = _Builder(world, rng)
    p = world.params
    d = p.d_lane_in
    T = horizon / FPS
    drive = _Drive(world, d, _start(world, 1, 10.0, d), 10.0, 4.5, T)
    events = b.events_ahead(drive, T)
    spots = b.spots_ahead(drive, T, 90.0)
    b.parked(density=0.65, trucks=1, keepout=spots)
    b.standing(2)
    busy = []
    for side, mid, t in events:
        if rng.random() < 0.6:
            busy.append(b.crossing_person(drive, side, mid - p.gap / 2 - 2.2))
    for side, sg, t in spots:
        busy.append(b.crossing_person(drive, side, sg))
    for t in _meet_times(rng, T, 3.0, (5.0, 10.0), busy):
        b.oncoming(drive, t)
    b.walkers(drive, max(2, int(T / 8)), T)
    return Plan("loop", frames, 1 / FPS, d, drive.s, b.finalize(T), world.ring)


def _mixed(world: World, rng, frames: int, horizon: int) -> Plan:
    b = _Builder(world, rng)
    p = world.params
    d = p.d_lane_in
    T = horizon / FPS
    drive = _Drive(world, d, _start(world, 0, 5.0, d), 9.0, 4.5, T)
    events = b.events_ahead(drive, T)
    spots = b.spots_ahead(drive, T, 45.0)
    b.parked(density=0.7, trucks=1, keepout=spots)
    b.standing(2)
    b.ahead(drive, gap=14.0, dv=1.2)
    busy = []
    for i, (side, mid, t) in enumerate(events):
        busy.append(b.crossing_person(drive, side, mid - p.gap / 2 - 2.2))
        if i % 2 == 0:
            busy.append(b.crossing_car(drive, side))
    for side, sg, t in spots:
        busy.append(b.crossing_person(drive, side, sg))
    for t in _meet_times(rng, T, 2.0, (3.0, 7.0), busy):
        b.oncoming(drive, t, truck=bool(rng.random() < 0.15))
    b.walkers(drive, max(3, int(T / 5)), T)
    return Plan("mixed", frames, 1 / FPS, d, drive.s, b.finalize(T), world.ring)


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    default_frames: int | None  # None: computed from the world (loop)
    build: Callable[[World, np.random.Generator, int, int], Plan]

    def frames_for(self, world: World) -> int:
        return self.default_frames if self.default_frames is not None else _loop_frames(world)


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("static", "parked cars, a parked truck and standing people; nothing moves", 150, _static),
        Scenario("crossing", "the rig waits at a zebra while people cross right in front and a queue of cars and a truck crawls through the intersection", 200, _crossing),
        Scenario("convoy", "a box truck with a printed rear door 4.5 m ahead drives at the rig's speed and fills ~30% of the view", 200, _convoy),
        Scenario("oncoming", "cars and a truck in the opposite lane drive towards the rig and pass it", 200, _oncoming),
        Scenario("loop", "one lap of the ~390 m ring and 60 m past the start again, with traffic and pedestrians", None, _loop),
        Scenario("mixed", "crossings, oncoming traffic, a car ahead, walkers and parked cars together", 300, _mixed),
    )
}


def make_plan(world: World, scenario: str, frames: int | None, seed: int) -> Plan:
    sc = SCENARIOS[scenario]
    default = sc.frames_for(world)
    n = frames if frames is not None else default
    # the scene is planned over at least the default length, so a shorter sequence is a
    # prefix of the default one (same objects, same motions)
    rng = np.random.default_rng([seed, 2, list(SCENARIOS).index(scenario)])
    return sc.build(world, rng, n, max(n, default))


__all__ = ["SCENARIOS", "Scenario", "Plan", "make_plan", "FPS"]
