"""Synthetic scenes: photo-textured rooms and street grids with a body trajectory and a rig.

:func:`make_scene` builds a :class:`Scene`: static quads, optional moving boxes, the texture atlas,
the body :class:`~vings_core.sim.trajectory.Motion` and the camera-to-body extrinsic ``T_bc``.
Frames: world z up (gravity along -z), body x forward / y left / z up, camera optical (x right,
y down, z forward); the camera looks along the body's x axis, slightly rotated and offset.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from ..errors import ConfigError
from ..geometry import np_pose, np_so3_exp
from ..types import CameraModel
from .quads import QuadSet, box_quads, face_shade, make_quads
from .textures import TextureAtlas, load_atlas
from .trajectory import (ROOM_ROUTES, ROUTE_MIN_DURATION_S, DriveMotion, Motion, RetraceMotion, SineSum,
                         plan_drive, random_handheld, route_handheld)

SCENES = ("room", "street")

# camera optical axes in the body frame: x_c = -y_b, y_c = -z_b, z_c = +x_b
_R_BC_NOMINAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# a small mounting error and lever arm, like a real rig (non-identity on purpose)
T_BC_DEFAULT = np_pose(np_so3_exp(np.array([0.021, -0.034, 0.015])) @ _R_BC_NOMINAL,
                       np.array([0.062, -0.031, 0.024]))


def default_camera(width: int = 376, height: int = 240) -> CameraModel:
    """Pinhole camera with EuRoC-like field of view (fx = fy = 0.609 * width, ~79 deg horizontal),
    principal point at the image centre (pixel-centre convention), no distortion."""
    if width < 8 or height < 8:
        raise ConfigError(f"image size {width}x{height} too small (min 8x8)")
    f = 229.0 * width / 376.0
    return CameraModel(width=int(width), height=int(height), fx=f, fy=f, cx=(width - 1) / 2.0,
                       cy=(height - 1) / 2.0)


@dataclass
class MovingBox:
    """A box with its own smooth motion: ``center(t)`` (3,) m and ``yaw(t)`` rad, one callable of
    ``t`` (s, scalar or array) per coordinate (:class:`SineSum`, or a :class:`RouteAhead`
    coordinate for the street's lead car). ``local`` holds its quads in the box frame."""

    local: QuadSet
    cx: Callable
    cy: Callable
    cz: Callable
    yaw: Callable

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        y = float(self.yaw(t))
        c, s = np.cos(y), np.sin(y)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        return R, np.array([float(self.cx(t)), float(self.cy(t)), float(self.cz(t))])

    def quads_at(self, t: float) -> QuadSet:
        R, p = self.pose(t)
        q = self.local.transformed(R, p)
        # shading follows the face's current normal (still view-independent)
        base = self.local.tint / face_shade(self.local.normal)[:, None]
        q.tint = base * face_shade(q.normal)[:, None]
        return q


@dataclass
class Scene:
    """A synthetic scene. ``static``: quads that never move; ``movers``: moving boxes (their quads
    have ``obj`` = their index); ``motion``: the body trajectory; ``T_bc``: camera-to-body;
    ``sky``: rays that miss everything see a sky gradient (else black); ``info``: a summary;
    ``revisit``: for a street loop with a retrace, the times (s, sequence clock) of its first pass
    and of its second pass (set by :func:`~vings_core.sim.sequence.build_scene`), else None."""

    name: str
    seed: int
    static: QuadSet
    movers: list[MovingBox]
    atlas: TextureAtlas
    motion: Motion
    T_bc: np.ndarray
    sky: bool
    info: dict = field(default_factory=dict)
    revisit: Optional[dict] = None

    def quads_at(self, t: float = 0.0) -> QuadSet:
        """Every quad at time ``t`` (s): static ones then the moving boxes posed at ``t``."""
        if not self.movers:
            return self.static
        return QuadSet.concat([self.static] + [m.quads_at(t) for m in self.movers])

    def T_wb(self, t) -> np.ndarray:
        """(N, 4, 4) body poses at times ``t`` (s)."""
        return self.motion.T_wb(t)

    def T_wc(self, t) -> np.ndarray:
        """(N, 4, 4) camera poses ``T_wb @ T_bc`` at times ``t`` (s)."""
        return self.motion.T_wb(t) @ self.T_bc


class RouteAhead:
    """A place on the ego vehicle's own route ahead of it, for the street's lead car: at time ``t``
    (s, the scene's clock) the point of the route the ego body reaches ``gap`` seconds later, and at
    least ``min_ahead_m`` m of route ahead of where the ego is at ``t``.

    ``gap`` (a :class:`SineSum`, s) is evaluated on the route's own clock (the
    :class:`~vings_core.sim.trajectory.DriveMotion` under any re-timing:
    :meth:`~vings_core.sim.trajectory.Motion.route_clock`), and so is the look-ahead: with a speed
    factor or a slow start the lead car keeps the same distance (m) to the ego as without. It reads
    ``scene.motion`` at every call (``scene`` is set once the :class:`Scene` exists), so it follows
    whatever motion the scene ends up with. A loop's route goes round again; an open route goes on
    along its planned continuation (the route is planned past the length it is cut at) and, past
    that, straight on. :meth:`coord` gives the per-coordinate callables :class:`MovingBox` takes.
    """

    def __init__(self, gap: SineSum, min_ahead_m: float, height_m: float):
        self.gap = gap
        self.min_ahead_m = float(min_ahead_m)
        self.height_m = float(height_m)
        self.scene: Optional["Scene"] = None

    def state(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(x, y, heading)`` (m, m, rad; each shaped like ``t``) of the lane centre ahead."""
        if self.scene is None:
            raise RuntimeError("RouteAhead.scene is not set")
        t = np.asarray(t, np.float64)
        m, tb = self.scene.motion.route_clock(t.reshape(-1))
        if not isinstance(m, DriveMotion):
            raise TypeError(f"RouteAhead follows a DriveMotion, got {type(m).__name__}")
        ta = tb + self.gap(tb)
        if m.closed:                    # a loop: the route goes round again
            T, L = m.duration, m.route_length
            n_e, n_a = np.floor(tb / T), np.floor(ta / T)
            s_ego = m.arc(tb - n_e * T)[0] + n_e * L
            s_ahead = m.arc(ta - n_a * T)[0] + n_a * L
        else:
            s_ego = m.arc(tb)[0]
            s_ahead = m.arc(np.minimum(ta, m.route_end_s))[0]
        s = np.maximum(s_ahead, s_ego + self.min_ahead_m)
        if m.closed:
            s = np.mod(s, m.route_length)
        pos, th, _ = m.geometry(s)
        return pos[:, 0].reshape(t.shape), pos[:, 1].reshape(t.shape), th.reshape(t.shape)

    def coord(self, i: int) -> "_RouteCoord":
        """The callable ``t -> x`` (``i`` = 0), ``y`` (1), the box centre's height ``height_m`` (2) or
        the heading (3)."""
        return _RouteCoord(self, i)


@dataclass
class _RouteCoord:
    ahead: RouteAhead
    i: int

    def __call__(self, t) -> np.ndarray:
        if self.i == 2:
            return np.full(np.shape(t), self.ahead.height_m)
        return self.ahead.state(t)[(0, 1, None, 2)[self.i]]


def make_scene(name: str, seed: int = 0, **kw) -> Scene:
    """Build scene ``name`` ('room' or 'street') deterministically from ``seed``.

    room: ``dynamic`` (bool), ``route`` (one of :data:`ROOM_ROUTES`: ``'handheld'``, the default,
    wanders around the room; ``'return'`` walks a lap back to the start pose; ``'oneway'`` turns
    round at one end of the room and walks to the other, see
    :func:`~vings_core.sim.trajectory.route_handheld`),
    ``route_duration_s`` (s, return/oneway only: when the walk ends, default
    :data:`ROOM_ROUTE_DURATION_DEFAULT_S`, at least 5 s).
    street: ``length_m`` (route length, m, default 400), ``loop`` (bool: closed route back to the
    start), ``retrace`` (with ``loop``: fraction in (0, 1] of the loop driven a second time, see
    :class:`~vings_core.sim.trajectory.RetraceMotion`), ``dynamic`` (bool).
    """
    if name == "room":
        allowed = {"dynamic", "route", "route_duration_s"}
    elif name == "street":
        allowed = {"dynamic", "length_m", "loop", "retrace"}
    else:
        raise ConfigError(f"unknown scene {name!r}; expected one of {SCENES}")
    bad = set(kw) - allowed
    if bad:
        raise ConfigError(f"scene {name!r} does not take option(s) {sorted(bad)}; "
                          f"it takes {sorted(allowed)}")
    if name == "room":
        return _make_room(seed, dynamic=bool(kw.get("dynamic", False)), route=kw.get("route"),
                          route_duration_s=kw.get("route_duration_s"))
    return _make_street(seed, length_m=kw.get("length_m"), loop=bool(kw.get("loop", False)),
                        dynamic=bool(kw.get("dynamic", False)), retrace=kw.get("retrace"))


def check_retrace(retrace: Optional[float], loop: bool) -> Optional[float]:
    """``retrace`` as a float in (0, 1] (or None); it needs a closed route (``loop``)."""
    if retrace is None:
        return None
    try:
        f = float(retrace)
    except (TypeError, ValueError):
        raise ConfigError(f"retrace must be a number in (0, 1], got {retrace!r}") from None
    if not (np.isfinite(f) and 0.0 < f <= 1.0):
        raise ConfigError(f"retrace must be in (0, 1] (the fraction of the loop driven again), got {retrace}")
    if not loop:
        raise ConfigError("--retrace needs --loop (it drives the closed loop a second time)")
    return f


def check_route(route: Optional[str]) -> str:
    """The room route ``route`` (None: ``'handheld'``), one of :data:`ROOM_ROUTES`."""
    if route is None:
        return "handheld"
    if route not in ROOM_ROUTES:
        raise ConfigError(f"unknown room route {route!r}; expected one of {ROOM_ROUTES}")
    return route


# ------------------------------------------------------------------------------------ room

ROOM_SIZE = (6.0, 5.0, 3.0)
ROOM_ROUTE_DURATION_DEFAULT_S = 14.95    # s: 300 frames at 20 Hz


def _make_room(seed: int, dynamic: bool, route: Optional[str] = None,
               route_duration_s: Optional[float] = None) -> Scene:
    route = check_route(route)
    if route == "handheld":
        if route_duration_s is not None:
            raise ConfigError("route_duration_s applies to the room's 'return' and 'oneway' routes only")
    else:
        d = ROOM_ROUTE_DURATION_DEFAULT_S if route_duration_s is None else float(route_duration_s)
        if not (np.isfinite(d) and d >= ROUTE_MIN_DURATION_S):
            raise ConfigError(f"room route {route!r} needs at least {ROUTE_MIN_DURATION_S:g} s of "
                              f"motion, got {route_duration_s} s")
        route_duration_s = d
    rng = np.random.default_rng(seed)
    atlas = load_atlas()
    T = atlas.index
    sx, sy, sz = ROOM_SIZE
    # shell: +x, -x, +y, -y walls, ceiling, floor (all facing inwards)
    shell = box_quads((0, 0, sz / 2), ROOM_SIZE, 0.0,
                      [T("astronaut"), T("coffee"), T("chelsea"), T("rocket"), T("moon"),
                       T("gravel")], 1.5, rng, bottom=True, inward=True)
    shell.tile[:4] = [[1.6, 1.6], [1.4, 1.4], [1.3, 1.3], [1.7, 1.7]]
    shell.tile[4] = [2.0, 2.0]
    shell.tile[5] = [1.1, 1.1]
    furniture = [
        # center, size, yaw, textures (+x, -x, +y, -y, top), tile, tint
        ((2.2, 1.4, 0.375), (1.2, 0.8, 0.75), 0.0, "ihc", 0.8, (1.0, 0.95, 0.9)),
        ((-2.75, 0.2, 1.0), (0.4, 1.6, 2.0), 0.0, "text", 0.7, (1.0, 1.0, 1.0)),
        ((0.3, -2.05, 0.4), (2.0, 0.8, 0.8), 0.0, "motorcycle", 0.9, (1.0, 1.0, 1.0)),
        ((2.65, -1.2, 0.6), (0.6, 0.9, 1.2), 0.0, "brick", 0.6, (1.0, 1.0, 1.0)),
        ((-1.9, 1.75, 0.9), (0.35, 0.35, 1.8), 0.3, "grass", 0.5, (1.0, 1.0, 1.0)),
        ((2.0, 1.3, 0.9), (0.3, 0.3, 0.3), 0.5, "coins", 0.3, (1.0, 1.0, 1.0)),
        ((2.975, -0.3, 1.7), (0.05, 1.2, 0.8), 0.0, "hubble", 0.9, (1.0, 1.0, 1.0)),
        ((-0.8, 2.475, 1.5), (1.0, 0.05, 0.7), 0.0, "retina", 0.7, (1.0, 1.0, 1.0)),
        ((-2.5, -1.9, 0.25), (0.7, 0.7, 0.5), 0.6, "clock", 0.5, (1.0, 1.0, 1.0)),
    ]
    parts = [shell]
    for c, s, yaw, tex, tile, tint in furniture:
        parts.append(box_quads(c, s, yaw, T(tex), tile, rng, tint=tint))
    static = QuadSet.concat(parts)

    movers: list[MovingBox] = []
    if dynamic:
        def ss(c, amps, freqs):
            return SineSum(float(c), np.asarray(amps, float), np.asarray(freqs, float),
                           rng.uniform(0, 2 * np.pi, len(amps)))
        person = box_quads((0, 0, 0), (0.45, 0.3, 1.7), 0.0, T("astronaut"), 0.9, rng, obj=0)
        movers.append(MovingBox(person, ss(-0.1, [1.4], [0.5]), ss(1.85, [0.0], [0.0]),
                                ss(0.85, [0.0], [0.0]), ss(0.0, [0.15], [0.5])))
        cube = box_quads((0, 0, 0), (0.35, 0.35, 0.35), 0.0, T("chelsea"), 0.35, rng, obj=1)
        movers.append(MovingBox(cube, ss(-2.1, [0.15], [1.3]), ss(-0.2, [1.0], [0.7]),
                                ss(0.6, [0.25], [1.1]), ss(0.0, [1.2], [0.6])))
    if route == "handheld":
        motion = random_handheld(rng, center=(0.0, 0.0), half_range=(1.4, 0.9), z_mean=1.4, speed=1.45)
    else:
        motion = route_handheld(rng, route, route_duration_s, center=(0.0, 0.0), half_range=(1.4, 0.9),
                                z_mean=1.4)
    info = {"room_size_m": list(ROOM_SIZE), "quads": len(static), "moving_objects": len(movers),
            "route": route}
    if route != "handheld":
        info["route_duration_s"] = route_duration_s
    return Scene(name="room", seed=seed, static=static, movers=movers, atlas=atlas, motion=motion,
                 T_bc=T_BC_DEFAULT.copy(), sky=False, info=info)


# ------------------------------------------------------------------------------------ street

BLOCK = 80.0          # m between street centrelines
ROAD_HALF = 5.0       # m, asphalt half width
SIDEWALK = 2.5        # m
LANE = 1.75           # m, ego lane offset to the right of the centreline
STREET_LENGTH_DEFAULT = 400.0
STREET_MAX_LENGTH_M = 50000.0       # longest street route (m)


def _street_params(block: float) -> dict:
    """Geometry and motion parameters for a grid of spacing ``block`` (scaled down for short loops)."""
    k = min(block / BLOCK, 1.0)
    return {"block": block, "road_half": ROAD_HALF * k, "sidewalk": SIDEWALK * k, "lane": LANE * k,
            "turn_length": 22.0 * k, "ramp_length": 25.0 * k}


def _v_limits(p: dict) -> tuple[float, tuple[float, float]]:
    """Turn speed (lateral accel <= 4 m/s^2, <= 5.5 m/s) and cruise range (ramp accel <= 4 m/s^2)."""
    kmax = (np.pi / 2) * 1.875 / p["turn_length"]
    v_turn = float(min(5.5, np.sqrt(4.0 / kmax)))
    v_max = float(np.sqrt(v_turn ** 2 + 4.0 * 2 * p["ramp_length"] / 1.875))
    lo, hi = min(8.5, 0.8 * v_max), min(11.5, v_max)
    return v_turn, (lo, hi)


def _right(e: np.ndarray) -> np.ndarray:
    return np.array([e[1], -e[0]])


def _route_open(rng: np.random.Generator, length: float, p: dict):
    """Random walk on the grid: centreline nodes (K, 2) and lane corners for :func:`plan_drive`."""
    S = p["block"]
    dirs = [np.array([1.0, 0.0]), np.array([0.0, 1.0]), np.array([-1.0, 0.0]), np.array([0.0, -1.0])]
    di = 0
    node = np.array([0.0, 0.0])
    nodes = [np.array([-0.5 * S, 0.0]), node.copy()]   # start mid-street
    total = 0.5 * S
    turned_last = False
    while total < length + 1.5 * S:
        r = rng.random()
        if not turned_last and r < 0.3:
            di = (di + (1 if r < 0.15 else -1)) % 4
            turned_last = True
        else:
            turned_last = False
        node = node + S * dirs[di]
        nodes.append(node.copy())
        total += S
    nodes = np.array(nodes)
    return nodes, _lane_corners(nodes, p["lane"], closed=False)


def _lane_corners(nodes: np.ndarray, lane: float, closed: bool) -> np.ndarray:
    """Lane-offset corner points where the route turns (and start/end for open routes)."""
    K = len(nodes)
    out = []
    for i in range(K):
        if closed:
            a, b, c = nodes[i - 1], nodes[i], nodes[(i + 1) % K]
        else:
            if i == 0:
                e = nodes[1] - nodes[0]
                out.append(nodes[0] + lane * _right(e / np.linalg.norm(e)))
                continue
            if i == K - 1:
                e = nodes[-1] - nodes[-2]
                out.append(nodes[-1] + lane * _right(e / np.linalg.norm(e)))
                continue
            a, b, c = nodes[i - 1], nodes[i], nodes[i + 1]
        e1 = (b - a) / np.linalg.norm(b - a)
        e2 = (c - b) / np.linalg.norm(c - b)
        if abs(e1 @ e2) > 0.5:          # straight through: not a corner
            continue
        out.append(b + lane * (_right(e1) + _right(e2)))
    return np.array(out)


def _route_loop(length: float) -> tuple[np.ndarray, dict]:
    """Closed rectangle of m x n blocks whose centreline perimeter is close to ``length``."""
    if length >= 4 * BLOCK:
        k = max(int(round(length / (2 * BLOCK))), 2)
        m = (k + 1) // 2
        n = k - m
        block = BLOCK
    else:
        m = n = 1
        block = length / 4.0
    nodes = np.array([[0.0, 0.0], [m * block, 0.0], [m * block, n * block], [0.0, n * block]])
    return nodes, _street_params(block)


def _make_street(seed: int, length_m: Optional[float], loop: bool, dynamic: bool,
                 retrace: Optional[float] = None) -> Scene:
    retrace = check_retrace(retrace, loop)
    rng = np.random.default_rng(seed)
    atlas = load_atlas()
    T = atlas.index
    length = STREET_LENGTH_DEFAULT if length_m is None else float(length_m)
    if not np.isfinite(length) or length < 50.0:
        raise ConfigError(f"street length_m must be >= 50 m, got {length_m}")
    if length > STREET_MAX_LENGTH_M:
        raise ConfigError(f"street length_m must be <= {STREET_MAX_LENGTH_M / 1000:g} km, got {length_m}")
    if loop:
        nodes, p = _route_loop(length)
        corners = _lane_corners(nodes, p["lane"], closed=True)
        v_turn, v_cruise = _v_limits(p)
        motion = plan_drive(corners, True, rng, turn_length=p["turn_length"], v_turn=v_turn,
                            v_cruise=v_cruise, ramp_length=p["ramp_length"])
        seg_nodes = np.vstack([nodes, nodes[:1]])
        loop_length = float(motion.total_length)
        if retrace is not None:
            motion = RetraceMotion(motion, retrace)
    else:
        p = _street_params(BLOCK)
        nodes, corners = _route_open(rng, length, p)
        v_turn, v_cruise = _v_limits(p)
        motion = plan_drive(corners, False, rng, turn_length=p["turn_length"], v_turn=v_turn,
                            v_cruise=v_cruise, ramp_length=p["ramp_length"], total_length=length)
        seg_nodes = nodes
    S = p["block"]
    static, cells = _city(rng, atlas, seg_nodes, p)
    movers = _cars(rng, atlas, seg_nodes, p) if dynamic else []
    lead = None
    if dynamic:
        lead, lead_info = _lead_car(rng, atlas, p, obj=len(movers))
        lead_info["mover"] = len(movers)
        movers.append(lead)
    info = {"block_m": S, "loop": loop, "route_length_m": motion.total_length,
            "blocks": len(cells), "quads": len(static), "moving_objects": len(movers),
            "v_turn_mps": v_turn, "v_cruise_mps": list(v_cruise)}
    if lead is not None:
        info["lead_car"] = lead_info
    if loop:
        info.update(loop_length_m=loop_length, retrace=retrace)
    scene = Scene(name="street", seed=seed, static=static, movers=movers, atlas=atlas, motion=motion,
                  T_bc=T_BC_DEFAULT.copy(), sky=True, info=info)
    if lead is not None:
        lead.cx.ahead.scene = scene
    return scene


def _city(rng, atlas: TextureAtlas, seg_nodes: np.ndarray, p: dict):
    """Ground plane, sidewalk slabs and buildings for every block within one block of the route."""
    T = atlas.index
    S, rh, sw = p["block"], p["road_half"], p["sidewalk"]
    k = S / BLOCK
    cells = set()
    for a, b in zip(seg_nodes[:-1], seg_nodes[1:]):
        n = max(int(round(np.linalg.norm(b - a) / S)), 1)
        for j in range(n + 1):
            q = a + (b - a) * j / n
            ci, cj = int(np.floor(q[0] / S + 0.5)), int(np.floor(q[1] / S + 0.5))
            for di in range(-2, 2):
                for dj in range(-2, 2):
                    cells.add((ci + di, cj + dj))
    cells = sorted(cells)
    facades = [T(n) for n in atlas.names if n.startswith("facade_")]
    parts = []
    xs = np.array([c[0] for c in cells], float)
    ys = np.array([c[1] for c in cells], float)
    x0, x1 = xs.min() * S - 150, (xs.max() + 1) * S + 150
    y0, y1 = ys.min() * S - 150, (ys.max() + 1) * S + 150
    ground = make_quads([[x0, y1, 0.0]], [[0, -1.0, 0]], [[1.0, 0, 0]], [[y1 - y0, x1 - x0]],
                        T("asphalt"), (2.5, 2.5), (0.0, 0.0), face_shade(np.array([[0, 0, 1.0]])))
    parts.append(ground)
    curb = 0.15
    for (i, j) in cells:
        cx, cy = (i + 0.5) * S, (j + 0.5) * S
        side = S - 2 * rh
        parts.append(box_quads((cx, cy, curb / 2), (side, side, curb), 0.0, T("brick"), 1.2 * k,
                               rng, tint=(0.8, 0.8, 0.8)))
        inner = side - 2 * sw
        nx, ny = rng.integers(2, 4), rng.integers(2, 4)
        wx = inner / nx
        wy = inner / ny
        for a in range(nx):
            for b in range(ny):
                gap = rng.uniform(0.0, 2.5) * k
                bx, by = wx - gap, wy - gap
                if bx < 2 or by < 2:
                    continue
                h = rng.uniform(8.0, 32.0) * min(1.0, 0.3 + k)
                bc = (cx - inner / 2 + (a + 0.5) * wx, cy - inner / 2 + (b + 0.5) * wy,
                      curb + h / 2)
                f = int(rng.choice(facades))
                tex = [f, f, f, f, T("gravel")]
                tint = rng.uniform(0.8, 1.05, 3)
                parts.append(box_quads(bc, (bx, by, h), 0.0, tex, 9.0 * k, rng, tint=tint))
    return QuadSet.concat(parts), cells


def _cars(rng, atlas: TextureAtlas, seg_nodes: np.ndarray, p: dict) -> list[MovingBox]:
    """Cars driving back and forth on street segments at or next to the route (either lane, kept
    away from intersections so they never cross the ego vehicle's path)."""
    T = atlas.index
    S, rh, lane = p["block"], p["road_half"], p["lane"]
    k = S / BLOCK
    size = np.array([4.4, 1.8, 1.5]) * max(k, 0.4)
    A = S / 2 - (rh + size[0] / 2 + 4.0 * k)
    if A <= 0.5:
        return []
    used = _traversals(seg_nodes, S)
    segs = set()
    for (a, b) in used:
        for n in (a, b):
            for d in ((1, 0), (0, 1), (-1, 0), (0, -1)):
                segs.add(tuple(sorted([n, (n[0] + d[0], n[1] + d[1])])))
    movers = []
    texs = [T("rocket"), T("camera"), T("coins"), T("motorcycle")]
    for (a, b) in sorted(segs):
        if rng.random() > 0.35:
            continue
        pa, pb = np.array(a, float) * S, np.array(b, float) * S
        e = (pb - pa) / S
        side = float(rng.choice([-1.0, 1.0]))
        dirs = used.get((a, b), set())
        if len(dirs) == 2:
            continue                    # the ego drives both ways here: no free lane
        if dirs:
            side = -float(next(iter(dirs)))   # left of the ego's direction: the oncoming lane
        mid = 0.5 * (pa + pb) + side * lane * _right(e)
        amp = rng.uniform(0.5, 1.0) * A
        w = rng.uniform(5.0, 9.0) * max(k, 0.3) / amp
        ph = rng.uniform(0, 2 * np.pi)
        yaw = float(np.arctan2(e[1], e[0]))
        obj = len(movers)
        local = box_quads((0, 0, 0), size, 0.0, int(rng.choice(texs)), 2.0 * k, rng,
                          tint=rng.uniform(0.5, 1.1, 3), obj=obj)
        movers.append(MovingBox(
            local,
            SineSum(mid[0], np.array([amp * e[0]]), np.array([w]), np.array([ph])),
            SineSum(mid[1], np.array([amp * e[1]]), np.array([w]), np.array([ph])),
            SineSum(size[2] / 2 + 0.1 * k, np.zeros(1), np.zeros(1), np.zeros(1)),
            SineSum(yaw, np.zeros(1), np.zeros(1), np.zeros(1))))
    return movers


LEAD_SIZE = (4.6, 1.9, 1.7)     # m: the lead car (an SUV-sized box)
LEAD_GAP_S = (0.6, 2.0)         # s: range of its time gap ahead of the ego vehicle
LEAD_GAP_PERIOD_S = (14.0, 20.0)   # s: range of the period of the gap's oscillation
LEAD_REAR_MIN_M = 3.0           # m: least route length between the ego body and the lead's rear


def _lead_car(rng, atlas: TextureAtlas, p: dict, obj: int) -> tuple[MovingBox, dict]:
    """A car driving ahead of the ego vehicle in its lane along its route (a :class:`RouteAhead`):
    the time gap oscillates in :data:`LEAD_GAP_S` (``c + a sin(w t + phi)``, seeded period and
    phase), and the lead's rear is always at least :data:`LEAD_REAR_MIN_M` of route ahead of the
    ego body (so at low speed, in turns and from a standing start, it keeps that distance)."""
    T = atlas.index
    k = p["block"] / BLOCK
    size = np.array(LEAD_SIZE) * max(k, 0.4)
    lo, hi = LEAD_GAP_S
    w = 2 * np.pi / rng.uniform(*LEAD_GAP_PERIOD_S)
    gap = SineSum(0.5 * (lo + hi), np.array([0.5 * (hi - lo)]), np.array([w]),
                  np.array([rng.uniform(0, 2 * np.pi)]))
    min_ahead = float(size[0] / 2 + LEAD_REAR_MIN_M)
    ahead = RouteAhead(gap, min_ahead, height_m=float(size[2] / 2 + 0.1 * k))
    texs = [T("rocket"), T("camera"), T("coins"), T("motorcycle")]
    local = box_quads((0, 0, 0), size, 0.0, int(rng.choice(texs)), 2.0 * k, rng,
                      tint=rng.uniform(0.6, 1.1, 3), obj=obj)
    box = MovingBox(local, ahead.coord(0), ahead.coord(1), ahead.coord(2), ahead.coord(3))
    info = {"size_m": [round(float(v), 3) for v in size], "gap_s": [lo, hi],
            "gap_period_s": round(float(2 * np.pi / w), 3), "min_ahead_m": round(min_ahead, 3)}
    return box, info


def _traversals(seg_nodes: np.ndarray, S: float) -> dict:
    """Grid edges ((i, j), (i', j')) (sorted node pair) the route centreline drives along, with the
    set of directions (+1: from the first node to the second, -1: back)."""
    used: dict = {}
    for a, b in zip(seg_nodes[:-1], seg_nodes[1:]):
        n = max(int(np.ceil(np.linalg.norm(b - a))), 1)
        e = (b - a) / np.linalg.norm(b - a)
        for f in (np.arange(n) + 0.5) / n:
            q = a + (b - a) * f
            if abs(e[0]) > 0.5:          # along x on the street y = j S
                j = int(round(q[1] / S))
                i = int(np.floor(q[0] / S))
                key, sgn = ((i, j), (i + 1, j)), int(np.sign(e[0]))
            else:
                i = int(round(q[0] / S))
                j = int(np.floor(q[1] / S))
                key, sgn = ((i, j), (i, j + 1)), int(np.sign(e[1]))
            used.setdefault(key, set()).add(sgn)
    return used
