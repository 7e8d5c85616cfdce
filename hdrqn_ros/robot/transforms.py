"""Rigid transforms and a tf-like buffer of them, for machines without tf2 (numpy only, no ROS).

A :class:`Transform` is the pose of a child frame in its parent: ``apply`` maps points given
in the child frame into the parent frame. ``translation`` is ``(3,)`` float64 in metres,
``rotation`` a unit quaternion ``(4,)`` ordered x, y, z, w (ROS's order); ``a.compose(b)``
is ``a * b`` (``b`` applied first).

:class:`TransformBuffer` keeps a tree of frames as tf does (REP 105: ``map -> odom ->
base_link``): each frame has at most one parent, each edge parent -> child either static
(one transform, valid at every time) or a time-sorted history of the last ``cache_s``
seconds of the newest sample. ``lookup(target, source, stamp_ns)`` is the transform that
maps points in ``source`` into ``target`` (tf2's ``lookupTransform(target, source, time)``),
walking up from both frames to their common ancestor; between two samples of an edge it
interpolates (linear in translation, slerp in rotation). ``stamp_ns=None`` is tf2's time 0:
the latest time every edge on the chain has. Times are ROS times in integer nanoseconds.
``interpolate(a, b, fraction)`` is that interpolation on its own, ``seconds(ns)`` a time as
the messages write it.

Errors are :class:`TransformError`\\ s: :class:`FrameMissing` (a frame the buffer never
heard of, naming the frames it knows and which of them are connected), its subclass
:class:`NotConnected` (both frames known, in separate trees), and
:class:`ExtrapolationError` (a time outside an edge's history, naming the edge, the time
and the range it has, in seconds). A frame name's one leading ``/`` is dropped, as tf2 does.
The buffer is safe to fill and read from different threads.
"""
from __future__ import annotations

import bisect
import math
import operator
import threading
from dataclasses import dataclass, field

import numpy as np

QUATERNION_TOLERANCE = 0.01
"""How far a quaternion's norm may be from 1 before it is refused (then it is normalised)."""


def _quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product ``a * b`` of quaternions ``(x, y, z, w)``."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _rotate(q: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points`` ``(N, 3)`` rotated by unit quaternion ``q``."""
    u, w = q[:3], q[3]
    uv = np.cross(u, points)
    return points + 2.0 * (w * uv + np.cross(u, uv))


def _readonly(values, shape: tuple[int, ...], what: str) -> np.ndarray:
    array = np.array(values, dtype=np.float64)
    if array.shape != shape or not np.isfinite(array).all():
        raise ValueError(f"{what} must be {shape[0]} finite numbers, got {np.asarray(values).tolist()!r}")
    array.setflags(write=False)
    return array


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    """The heading about z (rad, in ``(-pi, pi]``) of quaternion ``(x, y, z, w)``'s x axis."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@dataclass(frozen=True, eq=False)
class Transform:
    """The pose of a child frame in its parent: ``translation`` ``(3,)`` m, ``rotation`` a unit
    quaternion ``(4,)`` x, y, z, w (normalised here; refused if its norm is off by more than
    :data:`QUATERNION_TOLERANCE`)."""

    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))

    def __post_init__(self):
        translation = _readonly(self.translation, (3,), "translation")
        rotation = np.array(_readonly(self.rotation, (4,), "rotation (x, y, z, w)"))
        norm = float(np.linalg.norm(rotation))
        if abs(norm - 1.0) > QUATERNION_TOLERANCE:
            raise ValueError(f"rotation (x, y, z, w) {rotation.tolist()} is not a unit quaternion (norm {norm:.6g})")
        object.__setattr__(self, "translation", translation)
        object.__setattr__(self, "rotation", _readonly(rotation / norm, (4,), "rotation"))

    @classmethod
    def identity(cls) -> "Transform":
        return cls()

    @classmethod
    def from_xy_yaw(cls, x: float, y: float, yaw: float) -> "Transform":
        """A planar pose: ``(x, y)`` m, ``yaw`` rad about z."""
        return cls((x, y, 0.0), (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0)))

    @property
    def yaw(self) -> float:
        """The heading about z (rad, in ``(-pi, pi]``) of the rotation's x axis."""
        return quaternion_yaw(*self.rotation)

    def compose(self, other: "Transform") -> "Transform":
        """``self * other``: applies ``other`` first, then ``self`` (parent<-mid composed with mid<-child)."""
        return Transform(self.translation + _rotate(self.rotation, other.translation[None])[0],
                         _quat_multiply(self.rotation, other.rotation))

    def inverse(self) -> "Transform":
        """The transform back: ``t.compose(t.inverse())`` is the identity."""
        conjugate = self.rotation * np.array([-1.0, -1.0, -1.0, 1.0])
        return Transform(-_rotate(conjugate, self.translation[None])[0], conjugate)

    def apply(self, points) -> np.ndarray:
        """``points`` ``(N, 3)`` or ``(N, 2)`` (or one point, ``(3,)``/``(2,)``) in the child
        frame, in the parent frame; 2-D points are taken at z = 0 and come back 2-D."""
        points = np.asarray(points, dtype=np.float64)
        if points.ndim not in (1, 2) or points.shape[-1] not in (2, 3):
            raise ValueError(f"points must be (N, 3) or (N, 2), got shape {points.shape}")
        flat = points.reshape(-1, points.shape[-1])
        xyz = flat if flat.shape[1] == 3 else np.column_stack([flat, np.zeros(len(flat))])
        moved = _rotate(self.rotation, xyz) + self.translation
        return moved[:, :points.shape[-1]].reshape(points.shape)

    def almost_equal(self, other: "Transform", atol: float = 1e-9) -> bool:
        """Equal within ``atol`` (the quaternions q and -q are one rotation)."""
        return bool(np.allclose(self.translation, other.translation, atol=atol)
                    and abs(abs(float(np.dot(self.rotation, other.rotation))) - 1.0) <= atol)

    def __repr__(self) -> str:
        return f"Transform(translation={self.translation.tolist()}, rotation={self.rotation.tolist()})"


def interpolate(a: Transform, b: Transform, fraction: float) -> Transform:
    """The transform ``fraction`` of the way from ``a`` (0) to ``b`` (1): linear in
    translation, spherical linear (slerp, the shorter way) in rotation."""
    qa, qb = a.rotation, b.rotation
    dot = float(np.dot(qa, qb))
    if dot < 0.0:
        qb, dot = -qb, -dot
    if dot > 0.9995:
        q = qa + fraction * (qb - qa)
    else:
        theta = math.acos(dot)
        q = (math.sin((1.0 - fraction) * theta) * qa + math.sin(fraction * theta) * qb) / math.sin(theta)
    return Transform(a.translation + fraction * (b.translation - a.translation), q / np.linalg.norm(q))


def seconds(stamp_ns: int) -> str:
    """``stamp_ns`` as exact seconds for a message: ``12.5 s``."""
    sign = "-" if stamp_ns < 0 else ""
    whole, frac = divmod(abs(stamp_ns), 10**9)
    return f"{sign}{whole}.{f'{frac:09d}'.rstrip('0') or '0'} s"


class TransformError(Exception):
    """A transform the buffer cannot give or take."""


class FrameMissing(TransformError):
    """``frame`` is not in the buffer (``None``: not said, e.g. by tf2_ros). ``known``: the
    frames it has; ``trees``: those frames grouped by the tree they are connected in."""

    def __init__(self, message: str, frame: str | None, known: tuple[str, ...] = (),
                 trees: tuple[tuple[str, ...], ...] = ()):
        super().__init__(message)
        self.frame, self.known, self.trees = frame, known, trees


class NotConnected(FrameMissing):
    """Both frames are known but in separate trees (``frame``: the source)."""


class ExtrapolationError(TransformError):
    """``stamp_ns`` is outside edge ``parent -> child``'s history ``[earliest_ns, latest_ns]``
    on the way from ``source`` to ``target`` (the edge ``None`` where tf2_ros did not say)."""

    def __init__(self, message: str, target: str, source: str, stamp_ns: int, parent: str | None = None,
                 child: str | None = None, earliest_ns: int | None = None, latest_ns: int | None = None):
        super().__init__(message)
        self.target, self.source, self.stamp_ns = target, source, stamp_ns
        self.parent, self.child, self.earliest_ns, self.latest_ns = parent, child, earliest_ns, latest_ns


@dataclass
class _Edge:
    """One parent -> child edge: a static transform, or samples sorted by stamp."""

    parent: str
    static: bool
    stamps: list[int] = field(default_factory=list)
    transforms: list[Transform] = field(default_factory=list)

    def at(self, stamp_ns: int | None) -> Transform | None:
        """The transform at ``stamp_ns``; ``None`` outside the history."""
        if self.static:
            return self.transforms[0]
        if stamp_ns is None or not self.stamps[0] <= stamp_ns <= self.stamps[-1]:
            return None
        i = bisect.bisect_left(self.stamps, stamp_ns)
        if self.stamps[i] == stamp_ns:
            return self.transforms[i]
        t0, t1 = self.stamps[i - 1], self.stamps[i]
        return interpolate(self.transforms[i - 1], self.transforms[i], (stamp_ns - t0) / (t1 - t0))


def _stamp(stamp_ns) -> int:
    try:
        return operator.index(stamp_ns)
    except TypeError:
        raise TypeError(f"a stamp must be an integer number of nanoseconds, got {stamp_ns!r}") from None


def _frame(name, role: str) -> str:
    if not isinstance(name, str) or not name.lstrip("/"):
        raise TransformError(f"{role} frame must be a non-empty string, got {name!r}")
    return name[1:] if name.startswith("/") else name


class TransformBuffer:
    """A tree of frames and their transforms over time (see the module docstring);
    non-static edges keep the ``cache_s`` seconds before their newest sample."""

    def __init__(self, cache_s: float = 10.0):
        if not (isinstance(cache_s, (int, float)) and math.isfinite(cache_s) and cache_s > 0):
            raise ValueError(f"cache_s must be a finite number of seconds > 0, got {cache_s!r}")
        self.cache_ns = int(round(cache_s * 1e9))
        self._edges: dict[str, _Edge] = {}  # child -> its edge from its parent
        self._lock = threading.Lock()

    def set_transform(self, parent: str, child: str, stamp_ns: int, transform: Transform, static: bool = False) -> None:
        """Edge ``parent -> child`` is ``transform`` (``child``'s pose in ``parent``) at
        ``stamp_ns``, or at every time if ``static``. A child keeps its first parent and kind
        (static or not); a new parent, a change of kind or an edge closing a cycle is a
        :class:`TransformError`. Samples older than ``cache_s`` before the edge's newest are dropped."""
        parent, child = _frame(parent, "parent"), _frame(child, "child")
        if parent == child:
            raise TransformError(f"a transform from frame {child!r} to itself")
        if not isinstance(transform, Transform):
            raise TypeError(f"transform must be a Transform, got {type(transform).__name__}")
        stamp_ns = _stamp(stamp_ns)
        with self._lock:
            edge = self._edges.get(child)
            if edge is None:
                ancestor = parent
                while ancestor in self._edges:
                    ancestor = self._edges[ancestor].parent
                    if ancestor == child:
                        raise TransformError(f"refused {parent!r} -> {child!r}: {child!r} is already an ancestor of "
                                             f"{parent!r} (the chain would be a cycle)")
                edge = self._edges[child] = _Edge(parent, bool(static))
            elif edge.parent != parent:
                raise TransformError(f"refused {parent!r} -> {child!r}: frame {child!r} already has parent "
                                     f"{edge.parent!r} (a frame has one parent)")
            elif edge.static != bool(static):
                kinds = ("dynamic", "static")
                raise TransformError(f"refused {kinds[bool(static)]} {parent!r} -> {child!r}: the edge is "
                                     f"{kinds[edge.static]} (published on {'/tf_static' if edge.static else '/tf'})")
            if edge.static:
                edge.stamps, edge.transforms = [stamp_ns], [transform]
                return
            i = bisect.bisect_left(edge.stamps, stamp_ns)
            if i < len(edge.stamps) and edge.stamps[i] == stamp_ns:
                edge.transforms[i] = transform
            else:
                edge.stamps.insert(i, stamp_ns)
                edge.transforms.insert(i, transform)
            keep = bisect.bisect_left(edge.stamps, edge.stamps[-1] - self.cache_ns)
            del edge.stamps[:keep], edge.transforms[:keep]

    def clear(self) -> None:
        """Forget every frame (after a jump back in time, as tf2 does)."""
        with self._lock:
            self._edges.clear()

    def frames(self) -> tuple[str, ...]:
        """Every frame the buffer knows (parents and children), sorted."""
        with self._lock:
            return self._frames()

    def latest_common_time(self, target: str, source: str) -> int | None:
        """The newest time (ns) every non-static edge between ``target`` and ``source`` has;
        ``None`` when the chain is all static (valid at any time)."""
        target, source = _frame(target, "target"), _frame(source, "source")
        with self._lock:
            return self._latest(self._chain(target, source))

    def lookup(self, target: str, source: str, stamp_ns: int | None = None) -> Transform:
        """The transform mapping points in ``source`` into ``target`` at ``stamp_ns`` (``None``:
        the latest common time). Errors: :class:`FrameMissing`, :class:`NotConnected`,
        :class:`ExtrapolationError`."""
        target, source = _frame(target, "target"), _frame(source, "source")
        with self._lock:
            up_from_source, up_from_target = self._chain(target, source)
            when = self._latest((up_from_source, up_from_target)) if stamp_ns is None else _stamp(stamp_ns)
            ancestor_from_source = self._compose(up_from_source, when, target, source)
            ancestor_from_target = self._compose(up_from_target, when, target, source)
        return ancestor_from_target.inverse().compose(ancestor_from_source)

    def _frames(self) -> tuple[str, ...]:
        return tuple(sorted(set(self._edges) | {edge.parent for edge in self._edges.values()}))

    def _root(self, frame: str) -> str:
        while frame in self._edges:
            frame = self._edges[frame].parent
        return frame

    def _trees(self) -> tuple[tuple[str, ...], ...]:
        trees: dict[str, list[str]] = {}
        for frame in self._frames():
            trees.setdefault(self._root(frame), []).append(frame)
        return tuple(tuple(frames) for _, frames in sorted(trees.items()))

    def _describe(self) -> str:
        if not self._edges:
            return "the buffer has no frames yet (no transform received)"
        trees = " and ".join("{" + ", ".join(tree) + "}" for tree in self._trees())
        return f"known frames: {', '.join(self._frames())}; connected: {trees}"

    def _check_known(self, frame: str, role: str) -> None:
        if frame not in self._edges and not any(edge.parent == frame for edge in self._edges.values()):
            raise FrameMissing(f"{role} frame {frame!r} does not exist: {self._describe()}", frame,
                               self._frames(), self._trees())

    def _chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """The children on the way up from ``source`` and from ``target`` to their common ancestor."""
        self._check_known(target, "target")
        self._check_known(source, "source")
        up_from_target = [target]
        while up_from_target[-1] in self._edges:
            up_from_target.append(self._edges[up_from_target[-1]].parent)
        depth = {frame: i for i, frame in enumerate(up_from_target)}
        up_from_source = [source]
        while up_from_source[-1] not in depth:
            if up_from_source[-1] not in self._edges:
                raise NotConnected(f"frames {target!r} and {source!r} are not connected: no chain of transforms "
                                   f"joins them ({self._describe()})", source, self._frames(), self._trees())
            up_from_source.append(self._edges[up_from_source[-1]].parent)
        return up_from_source[:-1], up_from_target[:depth[up_from_source[-1]]]

    def _latest(self, chain: tuple[list[str], list[str]]) -> int | None:
        newest = [self._edges[child].stamps[-1] for part in chain for child in part if not self._edges[child].static]
        return min(newest) if newest else None

    def _compose(self, children: list[str], stamp_ns: int | None, target: str, source: str) -> Transform:
        """The pose of ``children[0]`` in the parent of ``children[-1]`` at ``stamp_ns`` (``None``:
        only static edges)."""
        result = Transform.identity()
        for child in children:
            edge = self._edges[child]
            at = edge.at(stamp_ns)
            if at is None:
                late = stamp_ns > edge.stamps[-1]
                by = seconds(stamp_ns - edge.stamps[-1] if late else edge.stamps[0] - stamp_ns)
                raise ExtrapolationError(
                    f"no transform from {source!r} to {target!r} at {seconds(stamp_ns)}: edge {edge.parent!r} -> "
                    f"{child!r} has data from {seconds(edge.stamps[0])} to {seconds(edge.stamps[-1])} only "
                    f"({by} {'after its newest' if late else 'before its oldest'} sample)", target, source, stamp_ns,
                    edge.parent, child, edge.stamps[0], edge.stamps[-1])
            result = at.compose(result)
        return result
