"""One LSTM layer over a short window, with its backward pass written out (BPTT).

The same function as ``nn.LSTM`` (one layer, gate order i, f, g, o), made for the thesis's
windows (n + 1 <= 17 steps, batch 4-12, 256 units) on a CPU, where a training update costs
the number of small operations more than their arithmetic:

* forward: the input projections of all T steps in one matrix product, then per step one
  matrix product and seven element-wise operations, written into preallocated time-major
  buffers;
* backward: per step one matrix product and four element-wise operations; the factors that
  do not depend on the recursion (the gates' derivatives) are computed for all steps at
  once, and each weight gradient is one matrix product over the whole window.

Autograd sees one node where the step-by-step version records about eleven per step.
``test/test_networks.py`` checks outputs and every gradient against ``nn.LSTM``.
"""
from __future__ import annotations

import torch
from torch import Tensor


def _forward(gates_x: Tensor, h: Tensor, c: Tensor, w_hh: Tensor, keep: bool):
    """``gates_x`` (T, B, 4H): input projections, biases included. Returns the hidden states
    ``hs`` and cell states ``cs``, each (T + 1, B, H) with ``[0]`` the initial state, and,
    with ``keep``, the activated gates (T, B, 4H) and ``tanh(c_t)`` (T, B, H)."""
    steps, batch, four_h = gates_x.shape
    hidden = four_h // 4
    hs = gates_x.new_empty(steps + 1, batch, hidden)
    cs = gates_x.new_empty(steps + 1, batch, hidden)
    hs[0], cs[0] = h, c
    acts = gates_x.new_empty(steps if keep else 1, batch, four_h)
    tanh_c = gates_x.new_empty(steps if keep else 1, batch, hidden)
    w_hh_t = w_hh.t()
    for t in range(steps):
        a, tc = acts[t if keep else 0], tanh_c[t if keep else 0]
        torch.addmm(gates_x[t], hs[t], w_hh_t, out=a)
        i, f, g, o = a.split(hidden, 1)
        i.sigmoid_()
        f.sigmoid_()
        g.tanh_()
        o.sigmoid_()
        torch.mul(f, cs[t], out=cs[t + 1]).addcmul_(i, g)
        torch.tanh(cs[t + 1], out=tc)
        torch.mul(o, tc, out=hs[t + 1])
    return hs, cs, (acts if keep else None), (tanh_c if keep else None)


def _input_gates(x: Tensor, w_ih: Tensor, bias: Tensor) -> tuple[Tensor, Tensor]:
    """``x`` (B, T, F) -> (its rows time-major, (T * B, F); their input projections plus
    ``bias``, (T, B, 4H)): one matrix product for the whole window."""
    b, t, features = x.shape
    rows = x.transpose(0, 1).reshape(t * b, features)
    return rows, torch.addmm(bias, rows, w_ih.t()).view(t, b, -1)


class _LSTMSequence(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x: Tensor, h0: Tensor, c0: Tensor, w_ih: Tensor, w_hh: Tensor, bias: Tensor):
        rows, gates_x = _input_gates(x, w_ih, bias)
        hs, cs, acts, tanh_c = _forward(gates_x, h0, c0, w_hh, keep=True)
        ctx.save_for_backward(rows, hs, cs, acts, tanh_c, w_ih, w_hh)
        return hs[1:].transpose(0, 1).contiguous(), hs[-1].clone(), cs[-1].clone()

    @staticmethod
    def backward(ctx, grad_out: Tensor, grad_h: Tensor, grad_c: Tensor):
        rows, hs, cs, acts, tanh_c, w_ih, w_hh = ctx.saved_tensors
        steps, batch, four_h = acts.shape
        hidden = four_h // 4
        i, f, g, o = acts.split(hidden, 2)
        # the recursion-free factors, for all steps at once:
        #   d o_pre = dh * tanh(c) * o (1 - o);    dc += dh * o * (1 - tanh(c)^2)
        #   d [i, f, g]_pre = dc * [g i (1 - i), c_prev f (1 - f), i (1 - g^2)];  dc_prev = dc * f
        out_factor = tanh_c * o * (1 - o)
        cell_factor = o * (1 - tanh_c * tanh_c)
        ifg_factor = torch.cat([g * i * (1 - i), cs[:-1] * f * (1 - f), i * (1 - g * g)], 2).view(steps, batch, 3, hidden)
        grad_steps = grad_out.transpose(0, 1)  # (T, B, H)
        dgates = acts.new_empty(steps, batch, four_h)
        dh = grad_steps[-1] + grad_h
        dc = grad_c.clone()
        for t in range(steps - 1, -1, -1):
            d = dgates[t]
            torch.mul(dh, out_factor[t], out=d[:, 3 * hidden:])
            dc.addcmul_(dh, cell_factor[t])
            torch.mul(ifg_factor[t], dc.unsqueeze(1), out=d[:, :3 * hidden].view(batch, 3, hidden))
            dc.mul_(f[t])
            dh = torch.addmm(grad_steps[t - 1], d, w_hh) if t else d @ w_hh
        flat = dgates.view(steps * batch, four_h)
        grad_x = (flat @ w_ih).view(steps, batch, -1).transpose(0, 1) if ctx.needs_input_grad[0] else None
        grad_w_ih = flat.t() @ rows
        grad_w_hh = flat.t() @ hs[:-1].reshape(steps * batch, hidden)
        return grad_x, dh, dc, grad_w_ih, grad_w_hh, flat.sum(0)


def lstm_sequence(x: Tensor, state: tuple[Tensor, Tensor], w_ih: Tensor, w_hh: Tensor,
                  bias: Tensor) -> tuple[Tensor, tuple[Tensor, Tensor]]:
    """``x`` (B, T, F), ``state`` (h, c) each (B, H), ``w_ih`` (4H, F), ``w_hh`` (4H, H),
    ``bias`` (4H,) = ``bias_ih + bias_hh`` -> (outputs (B, T, H), (h_T, c_T))."""
    h, c = state
    if not torch.is_grad_enabled() or not any(v.requires_grad for v in (x, h, c, w_ih, w_hh, bias)):
        hs, cs, _, _ = _forward(_input_gates(x, w_ih, bias)[1], h, c, w_hh, keep=False)
        return hs[1:].transpose(0, 1), (hs[-1], cs[-1])
    out, h, c = _LSTMSequence.apply(x, h, c, w_ih, w_hh, bias)
    return out, (h, c)
