"""Episodic replay for Bootstrapped Random Updates (thesis 3.4)."""
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hdrqn_ros.agents.replay import Episode, EpisodeReplay


def make_episode(eid, seg_lengths, frame_shape=(2,), img=False):
    """Frames encode (episode id, step index) so windows can be traced back exactly."""
    t = int(sum(seg_lengths))
    starts = np.concatenate([[0], np.cumsum(seg_lengths)[:-1]]).astype(np.int32)
    if img:
        frames = np.zeros((t + 1, *frame_shape), np.uint8)
        frames[:, 0, 0, 0] = eid
        frames[:, 0, 0, 1] = np.arange(t + 1)
    else:
        frames = np.zeros((t + 1, *frame_shape), np.float32)
        frames[:, 0] = eid
        frames[:, 1] = np.arange(t + 1)
    step = np.arange(t)
    seg_of_step = np.searchsorted(starts, step, side="right") - 1
    fields = {
        "action": (step % 4).astype(np.uint8),
        "reward": step.astype(np.float32) + 0.5,
        "terminal": step == t - 1,
        "step": step.astype(np.int32),
        "segment": seg_of_step.astype(np.int16),
    }
    seg_data = {"subgoal": np.arange(len(seg_lengths), dtype=np.int32) + 100 * eid}
    return Episode(frames, fields, starts, seg_data)


def check_batch(replay, batch, n):
    b = batch.valid.shape[0]
    assert batch.frames.shape[:2] == (b, n + 1)
    for name, a in batch.fields.items():
        assert a.shape[:2] == (b, n), name
    for i in range(b):
        w = int(batch.valid[i].sum())
        assert w >= 1
        assert batch.valid[i, :w].all() and not batch.valid[i, w:].any()  # right padded
        ep = replay[int(batch.episode_index[i])]
        eid = ep.frames[0, 0]
        # never crosses episodes: every frame of the window comes from one episode
        assert (batch.frames[i, : w + 1, 0] == eid).all()
        steps = batch.fields["step"][i, :w]
        assert (np.diff(steps) == 1).all()
        assert steps[0] == batch.start[i]
        # next-frame alignment: frames[t] is the input of step t, frames[t + 1] its next
        assert (batch.frames[i, :w, 1] == steps).all()
        assert (batch.frames[i, 1 : w + 1, 1] == steps + 1).all()
        # never crosses a segment boundary
        segs = batch.fields["segment"][i, :w]
        assert (segs == segs[0]).all()
        k = int(segs[0])
        seg_end = int(ep.segment_starts[k]) + int(ep.segment_lengths[k])
        # a window runs n steps from its random start, cut at the end of its segment
        assert w == min(n, seg_end - int(batch.start[i]))
        assert batch.segment_data["subgoal"][i] == ep.segment_data["subgoal"][k]
        # padding is zeros
        assert not batch.frames[i, w + 1 :].any()
        assert all(not a[i, w:].any() for a in batch.fields.values())
        # loss on the last max(1, n // 2) valid steps, or on all of them when the window
        # begins at its segment's start (the zero LSTM state is then the true one)
        expect = np.zeros(n, bool)
        from_start = int(batch.start[i]) == int(ep.segment_starts[k])
        expect[0 if from_start else max(0, w - max(1, n // 2)) : w] = True
        assert (batch.loss_mask[i] == expect).all()


def test_sample_windows_respect_segments_and_alignment():
    replay = EpisodeReplay(10, seed=0)
    replay.add(make_episode(1, [5, 1, 12]))
    replay.add(make_episode(2, [20]))
    replay.add(make_episode(3, [2, 3]))
    for n in (1, 2, 4, 8, 30):
        check_batch(replay, replay.sample(16, n), n)


def test_short_segment_padding_and_masks():
    replay = EpisodeReplay(5, seed=1)
    replay.add(make_episode(7, [3]))
    batch = replay.sample(64, 8)
    from_start = batch.start == 0
    assert from_start.any() and (~from_start).any()
    assert (batch.valid[from_start] == np.array([[1, 1, 1, 0, 0, 0, 0, 0]], bool)).all()
    # shorter than n // 2 = 4: every valid step carries the loss
    assert (batch.loss_mask == batch.valid).all()
    assert (batch.frames[from_start, :4, 1] == [0, 1, 2, 3]).all()
    assert not batch.frames[:, 4:].any()

    b1 = replay.sample(6, 1)
    assert b1.valid.all() and b1.loss_mask.all() and b1.frames.shape == (6, 2, 2)
    assert (b1.frames[:, 1, 1] == b1.frames[:, 0, 1] + 1).all()

    replay.add(make_episode(8, [10]))
    b = replay.sample(64, 6)
    long = (b.valid.sum(1) == 6) & (b.start > 0)  # not at the segment start (see below)
    assert long.any()
    assert (b.loss_mask[long] == np.array([0, 0, 0, 1, 1, 1], bool)).all()


def loss_counts(seg_lengths, seq_len, draws, batch=8, seed=0):
    """How often each step of one episode carries the loss over ``draws`` minibatches."""
    replay = EpisodeReplay(5, seed=seed)
    replay.add(make_episode(1, seg_lengths))
    counts = np.zeros(int(sum(seg_lengths)))
    for _ in range(draws):
        b = replay.sample(batch, seq_len)
        for i in range(batch):
            counts[b.fields["step"][i][b.loss_mask[i]]] += 1
    return counts


def test_last_step_of_a_segment_reaches_the_loss_as_often_as_any_other():
    """Windows begin at a uniformly random step; each step carries the loss in the windows
    that start up to n/2 - 1 steps before it (fewer at a segment's start)."""
    counts = loss_counts([30], 8, 300, batch=16, seed=3)
    inner, last = counts[3:29].mean(), counts[29]
    assert last > 0.7 * inner  # the option's last step is not starved


def test_segment_chosen_proportional_to_length():
    replay = EpisodeReplay(2, seed=2)
    replay.add(make_episode(1, [1, 9]))
    b = replay.sample(4000, 2)
    frac_long = (b.fields["segment"][:, 0] == 1).mean()
    assert 0.87 < frac_long < 0.93


def test_image_frames_and_nbytes_accounting():
    replay = EpisodeReplay(10, seed=0)
    ep = make_episode(1, [4, 6], frame_shape=(44, 44, 3), img=True)
    ep.segment_data["subgoal_image"] = np.zeros((2, 44, 44, 3), np.uint8)
    expected = (
        11 * 5808  # T + 1 frames
        + 10 * (1 + 4 + 1 + 4 + 2)  # action u8, reward f32, terminal bool, step i32, segment i16
        + 2 * 4  # segment starts int32
        + 2 * 4  # subgoal ids
        + 2 * 5808  # subgoal images, once per option
    )
    assert ep.nbytes == expected
    replay.add(ep)
    assert replay.nbytes == expected and replay.num_steps == 10 and len(replay) == 1
    b = replay.sample(3, 4)
    assert b.frames.shape == (3, 5, 44, 44, 3) and b.frames.dtype == np.uint8
    assert b.segment_data["subgoal_image"].shape == (3, 44, 44, 3)


def test_views_are_copied_so_nbytes_is_real():
    big = np.zeros((1000, 2), np.float32)
    ep = Episode(big[:4], {"r": np.zeros(3, np.float32)})
    replay = EpisodeReplay(3)
    replay.add(ep)
    stored = replay[0]
    assert stored.frames.base is None and not np.shares_memory(stored.frames, big)
    assert replay.nbytes == 4 * 2 * 4 + 3 * 4 + 4


def test_ring_capacity_in_episodes():
    replay = EpisodeReplay(3, seed=0)
    for e in range(1, 6):
        replay.add(make_episode(e, [e + 1]))
    assert len(replay) == 3
    assert [int(replay[i].frames[0, 0]) for i in range(3)] == [3, 4, 5]
    assert replay.num_steps == 4 + 5 + 6
    assert replay.nbytes == sum(replay[i].nbytes for i in range(3))


def test_ring_capacity_in_bytes():
    one = make_episode(0, [10]).nbytes
    replay = EpisodeReplay(100, seed=0, capacity_bytes=int(2.5 * one))
    for e in range(1, 6):
        replay.add(make_episode(e, [10]))
        assert replay.nbytes <= replay.capacity_bytes
    assert len(replay) == 2
    assert [int(replay[i].frames[0, 0]) for i in range(2)] == [4, 5]
    with pytest.raises(ValueError, match="capacity_bytes"):
        replay.add(make_episode(9, [30]))


def test_seeded_determinism():
    def run(seed):
        replay = EpisodeReplay(10, seed=seed)
        for e in range(1, 5):
            replay.add(make_episode(e, [3, 7, 2]))
        return [replay.sample(5, 4) for _ in range(3)]

    a, b = run(42), run(42)
    for x, y in zip(a, b):
        assert (x.frames == y.frames).all() and (x.start == y.start).all()
    replay = EpisodeReplay(10)
    replay.add(make_episode(1, [50]))
    s1 = replay.sample(8, 3, rng=np.random.default_rng(7))
    s2 = replay.sample(8, 3, rng=np.random.default_rng(7))
    assert (s1.start == s2.start).all()


def test_validation_errors():
    replay = EpisodeReplay(2)
    with pytest.raises(ValueError, match="empty"):
        replay.sample(1, 1)
    with pytest.raises(ValueError):
        EpisodeReplay(0)
    f = np.zeros((5, 2), np.float32)
    with pytest.raises(ValueError, match="T \\+ 1"):
        Episode(np.zeros((1, 2)))
    with pytest.raises(ValueError, match="fields"):
        Episode(f, {"r": np.zeros(5)})
    with pytest.raises(ValueError, match="start at 0"):
        Episode(f, {}, np.array([1, 2]))
    with pytest.raises(ValueError, match="increase"):
        Episode(f, {}, np.array([0, 2, 2]))
    with pytest.raises(ValueError, match="< T"):
        Episode(f, {}, np.array([0, 4]))
    with pytest.raises(ValueError, match="segment_data"):
        Episode(f, {}, np.array([0, 2]), {"g": np.zeros(3)})
    replay.add(Episode(f, {"r": np.zeros(4, np.float32)}))
    with pytest.raises(ValueError, match="layout"):
        replay.add(Episode(f, {"r": np.zeros(4, np.float64)}))
    with pytest.raises(ValueError):
        replay.sample(0, 2)
    with pytest.raises(ValueError):
        replay.sample(2, 0)


@settings(max_examples=25, deadline=None)
@given(
    layouts=st.lists(st.lists(st.integers(1, 9), min_size=1, max_size=5), min_size=1, max_size=4),
    n=st.integers(1, 10),
    capacity=st.integers(1, 4),
    seed=st.integers(0, 2**16),
)
def test_property_random_layouts(layouts, n, capacity, seed):
    replay = EpisodeReplay(capacity, seed=seed)
    for e, segs in enumerate(layouts, start=1):
        replay.add(make_episode(e, segs))
    kept = layouts[-capacity:]
    assert len(replay) == len(kept)
    assert replay.num_steps == sum(map(sum, kept))
    check_batch(replay, replay.sample(6, n), n)


def test_first_step_of_each_segment_is_trained():
    """With n = 2 (the meta-controller's n^M) the first step of an episode of several
    steps must still carry the loss in windows that begin there."""
    counts = loss_counts([3], 2, 200)
    assert counts[0] > 0.2 * counts.sum() / 3


class ScriptedStarts:
    """A stand-in for ``np.random.Generator`` whose draws are given: first the episodes of
    the minibatch, then each window's start step."""

    def __init__(self, episodes, starts):
        self.episodes, self.starts = list(episodes), iter(starts)

    def integers(self, high, size=None):
        if size is not None:
            assert len(self.episodes) == size and max(self.episodes) < high
            return np.array(self.episodes)
        s = next(self.starts)
        assert s < high
        return s


def bits(rows):
    return np.array([[c == "1" for c in row] for row in rows], bool)


# Episode 0: options of 3, 10 and 6 steps (segments start at steps 0, 3, 13; T = 19).
# Episode 1: one segment of 12 steps (a flat or meta episode). Window length n = 8: the
# loss on the last n/2 = 4 valid steps, on every valid step when the window begins at
# its segment's start; windows are cut at the end of their segment (option or episode).
#          (episode, start,   valid,     loss)
MASK_TABLE_N8 = [
    (0, 0, "11100000", "11100000"),  # option 0 from its start: 3 steps, all trained
    (0, 1, "11000000", "11000000"),  # cut at option 0's end: 2 steps (< n/2), all trained
    (0, 2, "10000000", "10000000"),  # option 0's last step alone
    (0, 3, "11111111", "11111111"),  # option 1 from its start: the zero state is the true one
    (0, 4, "11111111", "00001111"),  # mid-option full window: the last 4
    (0, 5, "11111111", "00001111"),  # ends exactly at option 1's last step (12)
    (0, 7, "11111100", "00111100"),  # cut at option 1's end after 6 steps: the last 4 of those
    (0, 10, "11100000", "11100000"),  # 3 steps before the boundary at 13
    (0, 12, "10000000", "10000000"),  # option 1's last step alone
    (0, 13, "11111100", "11111100"),  # option 2 from its start, cut at the episode's end
    (0, 14, "11111000", "01111000"),
    (0, 18, "10000000", "10000000"),  # the episode's last step
    (1, 0, "11111111", "11111111"),
    (1, 2, "11111111", "00001111"),
    (1, 6, "11111100", "00111100"),  # cut at the episode's end
    (1, 9, "11100000", "11100000"),
]
# Window length n = 2 (the meta-controller's n^M): the loss on the last step only, on both
# when the window begins at its segment's start.
MASK_TABLE_N2 = [
    (0, 0, "11", "11"), (0, 1, "11", "01"), (0, 2, "10", "10"), (0, 3, "11", "11"),
    (0, 11, "11", "01"), (0, 12, "10", "10"), (1, 0, "11", "11"), (1, 5, "11", "01"), (1, 11, "10", "10"),
]


@pytest.mark.parametrize("n, table", [(8, MASK_TABLE_N8), (2, MASK_TABLE_N2)], ids=["n8", "n2"])
def test_loss_masks_match_the_written_table(n, table):
    replay = EpisodeReplay(5, seed=0)
    replay.add(make_episode(0, [3, 10, 6]))
    replay.add(make_episode(1, [12]))
    episodes, starts, valid, loss = zip(*table)
    batch = replay.sample(len(table), n, rng=ScriptedStarts(episodes, starts))
    np.testing.assert_array_equal(batch.start, starts)
    np.testing.assert_array_equal(batch.valid, bits(valid))
    np.testing.assert_array_equal(batch.loss_mask, bits(loss))
    for i, (e, s, v, _) in enumerate(table):  # the window holds steps s, s+1, ... of episode e
        w = v.count("1")
        np.testing.assert_array_equal(batch.fields["step"][i, :w], np.arange(s, s + w))
        assert (batch.frames[i, : w + 1, 0] == e).all()


class _ScriptedRng:
    """``np.random.Generator`` stand-in: the minibatch's episodes, then each window's start."""

    def __init__(self, episodes, starts):
        self.episodes, self.starts = np.array(episodes), iter(starts)

    def integers(self, high, size=None):
        return self.episodes if size is not None else next(self.starts)


def _typed_episode(meta=True):
    fields = {"action": np.array([2, 0, 1, 3, 1], np.uint8),
              "reward": np.array([0.5, 1.0, 0.0, -1.0, 2.0], np.float32),
              "terminal": np.array([False, False, False, False, True])}
    if meta:
        fields["next_invalid"] = np.array([-1, 2, -1, 0, 1], np.int8)
        fields["option_steps"] = np.array([1, 2, 1, 3, 1], np.int32)
    frames = np.arange(6, dtype=np.float32)[:, None] * np.array([1.0, 10.0], np.float32)  # frame t = (t, 10 t)
    return Episode(frames, fields, segment_starts=np.array([0, 3], np.int32),
                   segment_data={"img": np.array([100, 200], np.float32)})


def test_sample_transitions_is_a_typed_batch_with_the_stored_values():
    """A hand-made episode of two segments (steps 0-2, 3-4), windows of n = 3 from steps 1
    and 3: the typed batch holds exactly the stored fields, right-padded, with the loss mask
    (window from step 1: its last n // 2 = 1 step; from step 3, a segment start: all steps)."""
    replay = EpisodeReplay(4, seed=0)
    replay.add(_typed_episode())
    built = []

    def build_input(window):  # the network input: each frame plus its segment's data
        built.append(window)
        return window.frames + window.segment_data["img"][:, None, None]

    b = replay.sample_transitions(2, 3, build_input, rng=_ScriptedRng([0, 0], [1, 3]))
    assert type(b).__name__ == "ReplaySamples" and b._fields == (
        "obs", "action", "reward", "terminal", "mask", "next_invalid", "option_steps", "episode_end", "start",
        "return_to_go")
    assert len(built) == 1
    obs = np.zeros((2, 4, 2), np.float32)
    obs[0, :3] = [[101, 110], [102, 120], [103, 130]]  # frames 1..3 + segment 0's 100
    obs[0, 3] = 100  # padding frame (zeros) + the segment's data
    obs[1, :3] = [[203, 230], [204, 240], [205, 250]]  # frames 3..5 + segment 1's 200
    obs[1, 3] = 200
    np.testing.assert_array_equal(b.obs.numpy(), obs)
    assert b.obs.dtype == torch.float32
    assert b.action.dtype == torch.int64 and b.action.tolist() == [[0, 1, 0], [3, 1, 0]]
    assert b.reward.dtype == torch.float32 and b.reward.tolist() == [[1.0, 0.0, 0.0], [-1.0, 2.0, 0.0]]
    assert b.terminal.dtype == torch.float32 and b.terminal.tolist() == [[0, 0, 0], [0, 1, 0]]
    assert b.mask.dtype == torch.bool and b.mask.tolist() == [[False, True, False], [True, True, False]]
    assert b.next_invalid.dtype == torch.int64 and b.next_invalid.tolist() == [[2, -1, 0], [0, 1, 0]]
    assert b.option_steps.dtype == torch.float32 and b.option_steps.tolist() == [[2, 1, 0], [3, 1, 0]]
    assert b.episode_end.tolist() == [[False, False, False], [False, True, False]]  # step 4 ends the episode
    assert b.start.tolist() == [1, 3] and b.return_to_go is None

    sub = EpisodeReplay(4, seed=0)
    sub.add(_typed_episode(meta=False))
    b = sub.sample_transitions(3, 2, lambda w: w.frames)
    assert b.next_invalid is None and b.option_steps is None


@pytest.mark.parametrize("n", [8, 2])
def test_windows_with_history_give_every_loss_step_its_history(n):
    """``history=True``: each loss step has ``n - n // 2`` steps of its own segment before it
    in the window, or the window begins at the segment's start (the true zero state); no
    window crosses a segment, and every step, each segment's first and last included,
    reaches the loss."""
    replay = EpisodeReplay(5, seed=1)
    replay.add(make_episode(1, [3, 12, 1, 9]))
    loss_len, counts = max(1, n // 2), np.zeros(25)
    for _ in range(400):
        b = replay.sample(8, n, history=True)
        for i in range(8):
            steps, segs = b.fields["step"][i], b.fields["segment"][i]
            valid, mask = b.valid[i], b.loss_mask[i]
            assert len(set(segs[valid])) == 1
            seg_start = int(replay._episodes[0].segment_starts[segs[0]])
            if steps[0] == seg_start:
                assert mask[valid].all()
            else:
                assert not mask[: n - loss_len].any() and mask[n - loss_len:][valid[n - loss_len:]].all()
            counts[steps[mask]] += 1
    assert counts.min() > 0, counts
