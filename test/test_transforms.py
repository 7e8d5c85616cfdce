"""The package's own tf buffer (hdrqn_ros.robot.transforms): rigid transforms checked against
4x4 matrices built independently from the quaternions, the frame tree, interpolation,
static edges, pruning and the errors' text."""
from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from hdrqn_ros.robot.transforms import (ExtrapolationError, FrameMissing, NotConnected, Transform, TransformBuffer,
                                        TransformError, interpolate)

S = 10**9
QUICK = dict(deadline=None, max_examples=150)

coordinate = st.floats(-10.0, 10.0, allow_nan=False)


@st.composite
def quaternions(draw):
    q = np.array(draw(st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=4, max_size=4)))
    assume(np.linalg.norm(q) > 0.1)
    return q / np.linalg.norm(q)


@st.composite
def transforms(draw):
    return Transform(draw(st.lists(coordinate, min_size=3, max_size=3)), draw(quaternions()))


def matrix(t: Transform) -> np.ndarray:
    """The homogeneous 4x4 matrix of ``t`` (the textbook rotation matrix of a unit quaternion)."""
    x, y, z, w = t.rotation
    m = np.eye(4)
    m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    m[:3, 3] = t.translation
    return m


def rotation_angle(qa: np.ndarray, qb: np.ndarray) -> float:
    """The angle (rad) of the rotation taking ``qa`` to ``qb``."""
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(qa, qb)))))


@st.composite
def trees(draw):
    """A random frame tree: ``(buffer, edges, stamps)``; frame ``fi``'s parent is some ``fj``,
    j < i; each edge is static or has samples at the common ``stamps`` (ns)."""
    n = draw(st.integers(2, 7))
    stamps = sorted(draw(st.sets(st.integers(0, 10**12), min_size=1, max_size=4)))
    buffer, edges = TransformBuffer(cache_s=10_000.0), {}
    for i in range(1, n):
        parent, static = f"f{draw(st.integers(0, i - 1))}", draw(st.booleans())
        values = [draw(transforms()) for _ in ([0] if static else stamps)]
        edges[f"f{i}"] = (parent, static, values)
        for stamp, value in zip(stamps, values):
            buffer.set_transform(parent, f"f{i}", stamp, value, static=static)
    return buffer, edges, stamps


def root_matrix(edges, frame: str, k: int) -> np.ndarray:
    """``frame``'s pose in the root ``f0`` at sample ``k``, from the edges' matrices."""
    m = np.eye(4)
    while frame != "f0":
        parent, static, values = edges[frame]
        m = matrix(values[0 if static else k]) @ m
        frame = parent
    return m


@given(trees(), st.data())
@settings(**QUICK)
def test_a_lookup_equals_the_chain_of_its_edges_and_its_reverse_is_the_inverse(tree, data):
    buffer, edges, stamps = tree
    frames = ["f0", *edges]
    a, b = data.draw(st.sampled_from(frames)), data.draw(st.sampled_from(frames))
    k = data.draw(st.integers(0, len(stamps) - 1))
    a_from_b = buffer.lookup(a, b, stamps[k])
    expected = np.linalg.inv(root_matrix(edges, a, k)) @ root_matrix(edges, b, k)
    assert np.allclose(matrix(a_from_b), expected, atol=1e-9)
    assert a_from_b.compose(buffer.lookup(b, a, stamps[k])).almost_equal(Transform.identity(), atol=1e-9)
    points = np.array(data.draw(st.lists(st.lists(coordinate, min_size=3, max_size=3), min_size=1, max_size=5)))
    assert np.allclose(a_from_b.apply(points), (expected @ np.column_stack([points, np.ones(len(points))]).T).T[:, :3],
                       atol=1e-9)


@given(st.lists(transforms(), min_size=1, max_size=6))
@settings(**QUICK)
def test_a_chain_of_frames_composes_its_edges_in_order(chain):
    buffer = TransformBuffer()
    for i, edge in enumerate(chain):
        buffer.set_transform(f"c{i}", f"c{i + 1}", 5 * S, edge)
    composed = Transform.identity()
    for edge in chain:
        composed = composed.compose(edge)
    assert buffer.lookup("c0", f"c{len(chain)}").almost_equal(composed, atol=1e-9)
    assert buffer.lookup("c0", f"c{len(chain)}", 5 * S).almost_equal(composed, atol=1e-9)


@given(st.lists(st.tuples(st.integers(0, 10**15), transforms()), min_size=1, max_size=8,
                unique_by=lambda sample: sample[0]))
@settings(**QUICK)
def test_a_lookup_at_a_sample_time_returns_that_sample_in_any_insertion_order(samples):
    buffer = TransformBuffer(cache_s=10**7)
    for stamp, value in samples:
        buffer.set_transform("odom", "base_link", stamp, value)
    for stamp, value in samples:
        assert buffer.lookup("odom", "base_link", stamp).almost_equal(value, atol=1e-12)
    assert buffer.latest_common_time("odom", "base_link") == max(stamp for stamp, _ in samples)


@given(transforms(), transforms(), st.floats(0.0, 1.0))
@settings(**QUICK)
def test_between_samples_translation_is_linear_and_rotation_a_slerp(a, b, fraction):
    t0, t1 = 2 * S, 3 * S
    buffer = TransformBuffer()
    buffer.set_transform("odom", "base_link", t0, a)
    buffer.set_transform("odom", "base_link", t1, b)
    stamp = t0 + round(fraction * (t1 - t0))
    f = (stamp - t0) / (t1 - t0)
    between = buffer.lookup("odom", "base_link", stamp)
    assert np.allclose(between.translation, a.translation + f * (b.translation - a.translation), atol=1e-9)
    whole = rotation_angle(a.rotation, b.rotation)
    assert rotation_angle(a.rotation, between.rotation) == pytest.approx(f * whole, abs=1e-6)
    assert rotation_angle(between.rotation, b.rotation) == pytest.approx((1 - f) * whole, abs=1e-6)


def test_planar_interpolation_halfway_is_the_mean_pose_and_takes_the_short_way_round():
    halfway = interpolate(Transform.from_xy_yaw(0, 0, 0.2), Transform.from_xy_yaw(2, -4, 0.6), 0.5)
    assert (*halfway.translation[:2], halfway.yaw) == pytest.approx((1.0, -2.0, 0.4))
    across = interpolate(Transform.from_xy_yaw(0, 0, 3.0), Transform.from_xy_yaw(0, 0, -3.0), 0.5)
    assert abs(across.yaw) == pytest.approx(math.pi)
    nearly_parallel = interpolate(Transform.from_xy_yaw(0, 0, 0.01), Transform.from_xy_yaw(0, 0, 0.03), 0.25)
    assert nearly_parallel.yaw == pytest.approx(0.015, abs=1e-7)


@given(transforms(), st.integers(-10**18, 10**18), st.integers(0, 10**18))
@settings(**QUICK)
def test_a_static_edge_holds_at_every_time(value, published, asked):
    buffer = TransformBuffer(cache_s=1.0)
    buffer.set_transform("base_link", "laser", published, value, static=True)
    assert buffer.lookup("base_link", "laser", asked).almost_equal(value, atol=1e-12)
    assert buffer.lookup("laser", "base_link").almost_equal(value.inverse(), atol=1e-12)
    assert buffer.latest_common_time("base_link", "laser") is None


def rep105(map_odom_static: bool = False) -> TransformBuffer:
    """``map -> odom`` (0.8 m, 0.4 m, 0.2 rad: a localised robot's offset; 1 Hz when not
    static, as AMCL does), ``odom -> base_link`` at 20 Hz from 100 s to 102 s (the robot
    drives 0.5 m/s along odom's x), ``base_link -> laser`` static (0.1 m ahead, upside down)."""
    buffer = TransformBuffer()
    for second in (99, 100, 101, 102, 103):
        buffer.set_transform("map", "odom", second * S, Transform.from_xy_yaw(0.8, 0.4, 0.2), static=map_odom_static)
    for k in range(41):
        buffer.set_transform("odom", "base_link", 100 * S + k * S // 20, Transform.from_xy_yaw(1.0 + 0.025 * k, 0, 0))
    buffer.set_transform("base_link", "laser", 0, Transform((0.1, 0, 0), (1, 0, 0, 0)), static=True)
    return buffer


@pytest.mark.parametrize("map_odom_static", [False, True])
def test_rep105_chain_gives_the_robot_pose_in_map_with_the_odom_offset(map_odom_static):
    buffer = rep105(map_odom_static)
    assert buffer.frames() == ("base_link", "laser", "map", "odom")
    pose = buffer.lookup("map", "base_link", 101 * S)  # the robot at odom (1.5, 0), heading 0
    expected = (0.8 + 1.5 * math.cos(0.2), 0.4 + 1.5 * math.sin(0.2), 0.0, 0.2)
    assert (*pose.translation, pose.yaw) == pytest.approx(expected)
    latest = buffer.lookup("map", "base_link")  # 102 s: odom (2, 0)
    assert buffer.latest_common_time("map", "base_link") == 102 * S
    assert latest.translation[:2] == pytest.approx((0.8 + 2 * math.cos(0.2), 0.4 + 2 * math.sin(0.2)))
    # a place in map, seen in odom (a costmap's frame): the map -> odom offset undone
    places = [[0.8, 0.4], [0.8 + math.cos(0.2), 0.4 + math.sin(0.2)]]
    place_in_odom = buffer.lookup("odom", "map", 101 * S).apply(places)
    assert place_in_odom == pytest.approx(np.array([[0.0, 0.0], [1.0, 0.0]]))
    # a laser upside down (half a turn about x) 0.1 m ahead of base_link: its y is base_link's -y
    hits = buffer.lookup("map", "laser", 101 * S).apply(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    to_map = Transform.from_xy_yaw(0.8, 0.4, 0.2).apply
    assert hits == pytest.approx(to_map(np.array([[2.6, 0.0, 0.0], [1.6, -1.0, 0.0]])))
    # across branches: laser seen from odom goes up to base_link's parent and back down
    assert buffer.lookup("odom", "laser", 101 * S).apply([[0.0, 0.0]]) == pytest.approx(np.array([[1.6, 0.0]]))


def test_history_older_than_the_cache_is_pruned():
    buffer = TransformBuffer(cache_s=1.0)
    for k in range(101):  # 10 Hz for 10 s
        buffer.set_transform("odom", "base_link", k * S // 10, Transform.from_xy_yaw(k, 0, 0))
    assert buffer.lookup("odom", "base_link", 9 * S).translation[0] == pytest.approx(90)
    with pytest.raises(ExtrapolationError) as error:
        buffer.lookup("odom", "base_link", 8_500_000_000)
    assert (error.value.earliest_ns, error.value.latest_ns) == (9 * S, 10 * S)
    assert "from 9.0 s to 10.0 s" in str(error.value)
    buffer.set_transform("odom", "base_link", 2 * S, Transform())  # older than the cache: dropped
    with pytest.raises(ExtrapolationError):
        buffer.lookup("odom", "base_link", 2 * S)


def test_errors_name_the_frames_and_the_times():
    with pytest.raises(FrameMissing, match="no frames yet"):
        TransformBuffer().lookup("map", "base_link")
    buffer = rep105()
    buffer.set_transform("world", "charger", 0, Transform(), static=True)
    with pytest.raises(FrameMissing) as missing:
        buffer.lookup("map", "gripper")
    text = str(missing.value)
    assert "'gripper'" in text and "known frames: base_link, charger, laser, map, odom, world" in text
    assert "connected: {base_link, laser, map, odom} and {charger, world}" in text
    assert missing.value.frame == "gripper" and missing.value.trees == (("base_link", "laser", "map", "odom"),
                                                                       ("charger", "world"))
    with pytest.raises(NotConnected, match="'map' and 'charger' are not connected") as apart:
        buffer.lookup("map", "charger")
    assert isinstance(apart.value, FrameMissing)
    with pytest.raises(ExtrapolationError) as late:
        buffer.lookup("map", "laser", 102_500_000_000)
    assert str(late.value) == ("no transform from 'laser' to 'map' at 102.5 s: edge 'odom' -> 'base_link' has data "
                               "from 100.0 s to 102.0 s only (0.5 s after its newest sample)")
    with pytest.raises(ExtrapolationError, match=r"at 98.25 s: edge 'map' -> 'odom' has data from 99.0 s to 103.0 s "
                                                 r"only \(0.75 s before its oldest sample\)"):
        buffer.lookup("odom", "map", 98_250_000_000)


def test_the_tree_refuses_a_second_parent_a_cycle_and_bad_input():
    buffer = rep105()
    with pytest.raises(TransformError, match="'base_link' already has parent 'odom'"):
        buffer.set_transform("map", "base_link", 100 * S, Transform())
    with pytest.raises(TransformError, match="'map' is already an ancestor of 'laser'.*cycle"):
        buffer.set_transform("laser", "map", 100 * S, Transform())
    with pytest.raises(TransformError, match="the edge is static"):
        buffer.set_transform("base_link", "laser", 100 * S, Transform())
    with pytest.raises(TransformError, match="from frame 'odom' to itself"):
        buffer.set_transform("odom", "/odom", 100 * S, Transform())
    with pytest.raises(TransformError, match="non-empty"):
        buffer.set_transform("", "x", 0, Transform())
    with pytest.raises(TypeError, match="integer number of nanoseconds"):
        buffer.set_transform("odom", "base_link", 1.5, Transform())
    with pytest.raises(TypeError, match="integer number of nanoseconds"):
        buffer.lookup("odom", "base_link", 1.5)
    assert buffer.lookup("/map", "base_link", 100 * S).almost_equal(buffer.lookup("map", "/base_link", 100 * S))
    with pytest.raises(ValueError, match="not a unit quaternion"):
        Transform((0, 0, 0), (0, 0, 0, 0))
    with pytest.raises(ValueError, match="finite"):
        Transform((0, math.nan, 0), (0, 0, 0, 1))
    with pytest.raises(ValueError, match=r"\(N, 3\) or \(N, 2\)"):
        Transform().apply(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="cache_s"):
        TransformBuffer(cache_s=0)


def test_planar_transforms():
    pose = Transform.from_xy_yaw(1.0, 2.0, math.pi / 2)
    assert pose.apply([[1.0, 0.0], [0.0, 1.0]]) == pytest.approx(np.array([[1.0, 3.0], [0.0, 2.0]]))
    assert pose.apply([1.0, 0.0, 5.0]) == pytest.approx([1.0, 3.0, 5.0])
    assert pose.yaw == pytest.approx(math.pi / 2)
    assert pose.inverse().apply([[1.0, 3.0]]) == pytest.approx(np.array([[1.0, 0.0]]))
    assert pose.compose(Transform.from_xy_yaw(1, 0, math.pi / 2)).yaw == pytest.approx(math.pi)
    assert Transform((0, 0, 0), (0, 0, 1.005, 0)).rotation.tolist() == [0, 0, 1, 0]  # normalised
    with pytest.raises(ValueError):
        pose.translation[0] = 5.0  # read-only
