"""Q-networks: layer shapes, exact parameter counts (tables 4.5/4.6), act()==forward()."""
import math

import numpy as np
import pytest
import torch
from torch import nn

from hdrqn_ros.agents.lstm_sequence import lstm_sequence
from hdrqn_ros.agents.networks import (
    ConvTrunk,
    DuelingHead,
    FeedForwardQNetwork,
    MlpTrunk,
    RecurrentQNetwork,
    lstm_state_size,
    make_image_qnet,
    make_state_qnet,
)

torch.manual_seed(0)


def n_params(module):
    return sum(p.numel() for p in module.parameters())


# Hand-written arithmetic, layer by layer.
def conv(k, cin, cout):
    return k * k * cin * cout + cout


CONV_REST = conv(3, 32, 32) + conv(3, 32, 32) + conv(3, 32, 256)  # 9248 + 9248 + 73984
LSTM = 4 * (256 * 256 * 2 + 2 * 256)  # W_ih, W_hh, b_ih, b_hh: 526,336


def dueling(n):
    return (128 * n + n) + (128 * 1 + 1)


MLP = (256 * 200 + 200) + (200 * 200 + 200) + (200 * 256 + 256)  # 143,056


def images(*lead, c=3, seed=0):
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.integers(0, 256, size=(*lead, 44, 44, c), dtype=np.uint8))


def test_conv_layer_shapes():
    trunk = ConvTrunk(6)
    maps = trunk.feature_maps(images(5, c=6))
    assert [tuple(m.shape) for m in maps] == [
        (5, 32, 11, 11),
        (5, 32, 5, 5),
        (5, 32, 3, 3),
        (5, 256, 1, 1),
    ]
    assert trunk(images(5, c=6)).shape == (5, 256)
    assert all((m >= 0).all() for m in maps)  # ReLU after every conv


def test_conv_trunk_is_the_four_valid_convolutions():
    """The trunk computes its last conv as one matrix product: still Conv2d's function."""
    torch.manual_seed(2)
    trunk = ConvTrunk(6)
    x = images(7, c=6, seed=3)
    h = x.float().div(255).permute(0, 3, 1, 2)
    for conv in trunk.convs:
        h = torch.relu(nn.functional.conv2d(h, conv.weight, conv.bias, conv.stride))
    with torch.no_grad():
        torch.testing.assert_close(trunk(x), h.flatten(1), atol=1e-5, rtol=0)
    assert h.abs().max() > 1e-2


def test_mlp_and_head_shapes():
    mlp = MlpTrunk(256)
    x = torch.randn(7, 256)
    h1 = torch.relu(mlp.net[0](x))
    assert h1.shape == (7, 200)
    assert mlp.net[2](h1).shape == (7, 200)
    assert mlp(x).shape == (7, 256)
    assert (mlp(x) < 0).any()  # FC3 has no activation
    assert DuelingHead(5)(torch.randn(3, 4, 256)).shape == (3, 4, 5)


def test_parameter_counts():
    assert CONV_REST == 9248 + 9248 + 73984
    assert LSTM == 526_336
    assert MLP == 143_056

    v1_meta = make_image_qnet(3, 2)
    assert n_params(v1_meta) == conv(3, 3, 32) + CONV_REST + LSTM + dueling(2) == 620_099

    sub = make_image_qnet(6, 4)
    assert n_params(sub) == conv(3, 6, 32) + CONV_REST + LSTM + dueling(4) == 621_221

    v2_meta = make_state_qnet(256, 2)
    assert n_params(v2_meta) == MLP + LSTM + dueling(2) == 669_779

    dqn = make_image_qnet(3, 4, recurrent=False)
    assert isinstance(dqn, FeedForwardQNetwork)
    assert n_params(dqn) == conv(3, 3, 32) + CONV_REST + (256 * 256 + 256) + dueling(4) == 159_813


def test_forward_shapes_and_state_convention():
    net = make_image_qnet(6, 4)
    x = images(2, 3, c=6)
    q, (h, c) = net(x)
    assert q.shape == (2, 3, 4)
    assert h.shape == c.shape == (2, lstm_state_size)
    q1, (h1, c1) = net.act(x[:, 0])
    assert q1.shape == (2, 4) and h1.shape == c1.shape == (2, 256)
    with pytest.raises(ValueError):
        net(x, (h[:1], c[:1]))
    with pytest.raises(ValueError):
        net(images(2, 3, c=3))


def test_act_matches_forward():
    net = make_image_qnet(6, 4)
    x = images(3, 6, c=6, seed=1)
    # Non-zero initial state too.
    state0 = (torch.randn(3, 256) * 0.5, torch.randn(3, 256) * 0.5)
    for init in (None, state0):
        with torch.no_grad():
            q_seq, (h_seq, c_seq) = net(x, init)
            state = init
            qs = []
            for t in range(x.shape[1]):
                q, state = net.act(x[:, t], state)
                qs.append(q)
        torch.testing.assert_close(torch.stack(qs, 1), q_seq, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(state[0], h_seq, atol=1e-5, rtol=1e-4)
        torch.testing.assert_close(state[1], c_seq, atol=1e-5, rtol=1e-4)
    # Continuing a sequence with forward() from act()'s state.
    with torch.no_grad():
        _, st = net.act(x[:, 0])
        q_rest, _ = net(x[:, 1:], st)
        q_all, _ = net(x)
    torch.testing.assert_close(q_rest, q_all[:, 1:], atol=1e-5, rtol=1e-4)


def test_act_matches_forward_state_net_and_grad_flows():
    net = make_state_qnet(256, 2)
    x = torch.randn(2, 4, 256)
    q_seq, _ = net(x)
    state, qs = None, []
    for t in range(4):
        q, state = net.act(x[:, t], state)
        qs.append(q)
    torch.testing.assert_close(torch.stack(qs, 1), q_seq, atol=1e-5, rtol=1e-4)
    torch.stack(qs, 1).sum().backward()
    assert net.lstm.weight_hh_l0.grad is not None and net.lstm.weight_hh_l0.grad.abs().sum() > 0


def test_feedforward_net_signatures():
    net = make_image_qnet(3, 4, recurrent=False)
    x = images(2, 3)
    q, state = net(x)
    assert q.shape == (2, 3, 4) and state is None
    q1, state = net.act(x[:, 1], None)
    assert state is None
    torch.testing.assert_close(q1, q[:, 1])


def test_dueling_mean_zero_advantage():
    head = DuelingHead(5)
    with torch.no_grad():
        head.advantage.bias.uniform_(-1, 1)
        head.value.bias.fill_(0.7)
    x = torch.randn(10, 256)
    a = head.advantages(x)
    torch.testing.assert_close(a.mean(-1), torch.zeros(10), atol=1e-6, rtol=0)
    q = head(x)
    v = head.value(x[:, 128:]).squeeze(-1)
    torch.testing.assert_close(q.mean(-1), v, atol=1e-5, rtol=1e-5)  # mean(Q) == V
    # Advantage sees only the first half, value only the second half.
    x2 = x.clone()
    x2[:, 128:] += 1.0
    torch.testing.assert_close(head.advantages(x2), a)


@pytest.mark.parametrize("make", [lambda: make_image_qnet(6, 4), lambda: make_state_qnet(256, 2),
                                  lambda: make_image_qnet(3, 4, recurrent=False)])
def test_xavier_init_bounds_and_zero_biases(make):
    net = make()
    for name, p in net.named_parameters():
        if "bias" in name:
            assert torch.count_nonzero(p) == 0, name
            continue
        if p.dim() == 4:  # conv: fan = channels * kernel area
            rf = p.shape[2] * p.shape[3]
            fan_in, fan_out = p.shape[1] * rf, p.shape[0] * rf
        else:
            fan_out, fan_in = p.shape
        bound = math.sqrt(6.0 / (fan_in + fan_out))
        assert p.abs().max() <= bound + 1e-7, name
        assert p.abs().max() > 0.5 * bound, name  # uniform over the full range, not tiny
        assert abs(p.std().item() - bound / math.sqrt(3)) < 0.2 * bound, name


def test_uint8_input_handling():
    net = make_image_qnet(3, 2)
    x = images(2, 2, seed=3)
    with torch.no_grad():
        q_u8, _ = net(x)
        q_f, _ = net(x.float() / 255.0)  # floats are taken as already scaled
        q_np, _ = net(x.numpy())  # numpy arrays are accepted
    torch.testing.assert_close(q_u8, q_f)
    torch.testing.assert_close(q_u8, q_np)
    # Channels-last: the network must see channel c of pixel (i, j) as channel c.
    trunk = ConvTrunk(3)
    img = torch.zeros(1, 44, 44, 3, dtype=torch.uint8)
    img[..., 2] = 255
    chw = trunk._prepare(img)
    assert chw.shape == (1, 3, 44, 44)
    assert chw[0, 2].min() == 1.0 and chw[0, :2].max() == 0.0


@pytest.mark.parametrize("make, shape", [(lambda: make_image_qnet(6, 18), (44, 44, 6)),
                                         (lambda: make_state_qnet(256, 7), (256,))], ids=["sub", "v2-meta"])
def test_lstm_sequence_equals_torch_nn_lstm(make, shape):
    """The hand-unrolled LSTM of ``act`` (batch 1, the acting path) and of ``forward`` are
    ``nn.LSTM`` itself: same Q-values, h and c at every one of 20 steps, from a zero and
    from a non-zero state (full-size networks: the sub-controller on Montezuma's 18
    actions and the hDRQNv2 meta-controller)."""
    torch.manual_seed(3)
    net = make()
    steps = 20
    if len(shape) == 3:
        x = images(1, steps, c=shape[-1], seed=4)[0]  # (20, 44, 44, 6) uint8
    else:
        x = torch.randn(steps, *shape) * 3
    for init in (None, (torch.randn(1, 256) * 0.5, torch.randn(1, 256) * 0.5)):
        with torch.no_grad():
            feats = net.trunk(x)  # (20, 256)
            h0, c0 = (torch.zeros(1, 256), torch.zeros(1, 256)) if init is None else init
            out, (hn, cn) = net.lstm(feats[None], (h0[None], c0[None]))  # torch's own LSTM
            ref_q = net.head(out[0])
            # nn.LSTM one step at a time, for c after every step
            ref_c, state = [], (h0[None], c0[None])
            for t in range(steps):
                _, state = net.lstm(feats[None, t:t + 1], state)
                ref_c.append(state[1][0, 0])
            q_act, h_act, c_act, st = [], [], [], init
            for t in range(steps):
                q, st = net.act(x[t:t + 1], st)
                q_act.append(q[0])
                h_act.append(st[0][0])
                c_act.append(st[1][0])
            q_fwd, (h_fwd, c_fwd) = net(x[None], init)
        tol = dict(atol=1e-5, rtol=0)
        torch.testing.assert_close(torch.stack(q_act), ref_q, **tol)
        torch.testing.assert_close(torch.stack(h_act), out[0], **tol)
        torch.testing.assert_close(torch.stack(c_act), torch.stack(ref_c), **tol)
        torch.testing.assert_close(torch.stack(ref_c)[-1], cn[0, 0], **tol)
        torch.testing.assert_close(q_fwd[0], ref_q, **tol)
        torch.testing.assert_close((h_fwd[0], c_fwd[0]), (hn[0, 0], cn[0, 0]), **tol)
        assert ref_q.abs().max() > 1e-3 and cn.abs().max() > 1e-2  # not a trivial comparison


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 1e-5)])
@pytest.mark.parametrize("batch, steps", [(4, 9), (12, 3), (1, 1)])
def test_lstm_sequence_gradients_equal_torch_nn_lstm(dtype, tol, batch, steps):
    """:func:`lstm_sequence`'s hand-written backward gives ``nn.LSTM``'s gradients for the
    inputs, the initial state and all four weights, with a loss on every output step and on
    the final h and c (windows of the sub- and meta-controller, and one step)."""
    torch.manual_seed(5)
    lstm = nn.LSTM(256, 256, batch_first=True).to(dtype)
    with torch.no_grad():
        for p in lstm.parameters():
            p.uniform_(-0.2, 0.2)
    x = torch.randn(batch, steps, 256, dtype=dtype, requires_grad=True)
    h0 = (torch.randn(batch, 256, dtype=dtype) * 0.5).requires_grad_()
    c0 = (torch.randn(batch, 256, dtype=dtype) * 0.5).requires_grad_()
    w_out, w_h, w_c = (torch.randn(batch, steps, 256, dtype=dtype), torch.randn(batch, 256, dtype=dtype),
                       torch.randn(batch, 256, dtype=dtype))
    params = [x, h0, c0, lstm.weight_ih_l0, lstm.weight_hh_l0, lstm.bias_ih_l0, lstm.bias_hh_l0]

    def grads(run):
        out, (h, c) = run()
        loss = (out * w_out).sum() + (h * w_h).sum() + (c * w_c).sum()
        return [out.detach(), h.detach(), c.detach(), *torch.autograd.grad(loss, params)]

    ref = grads(lambda: (lambda o, s: (o, (s[0][0], s[1][0])))(*lstm(x, (h0[None], c0[None]))))
    got = grads(lambda: lstm_sequence(x, (h0, c0), lstm.weight_ih_l0, lstm.weight_hh_l0,
                                      lstm.bias_ih_l0 + lstm.bias_hh_l0))
    names = ["out", "h", "c", "x", "h0", "c0", "w_ih", "w_hh", "b_ih", "b_hh"]
    for name, a, b in zip(names, got, ref):
        torch.testing.assert_close(a, b, atol=tol * max(1.0, b.abs().max().item()), rtol=0, msg=name)
        assert b.abs().max() > 1e-3, name  # not a trivial comparison
