"""Reference-conditioned filters for the marginal network (``ann_hyper`` polar; ``ann_conv``
both detectors).

"Column sums" below are a block's light in 1 px bins along e: on a polar detector its pixel
columns, on a cartesian one each pixel split by its overlap (:mod:`..centroiding.bins_along_e`,
:func:`.refdata.marginal_pairs`); a recipe's ``detectors`` say which it trains on.

``ann_marg``'s first layer is linear in (column sums, reference): it cannot build a matched
filter from the reference. Here the reference sets the first layer's weights. At each
calibration refit a small "hyper" network maps each subaperture's reference marginal
``r`` (``p`` values, unit sum) to ``K`` filters ``F (K, p)`` and biases ``c (K,)``; per frame
a block's normalised column sums ``u = m / N`` go through its subaperture's filters and a
small tanh MLP gives the shift along e (block x)::

    refit:  q = [p r, log(p r + EPS)]  -> tanh MLP -> dF (K, p), dc (K)
            F = F0 + dF,  c = c0 + Wr (p r) + dc - F (p r)      (so that z = F p (u - r) + ...)
    frame:  z = (p F) u + c + wN lf,  lf = log10(N) / 3 - 0.8
            [optional ``templates``: J more filters log(S_j r + EPS_T) (the reference moved by
             t_j px; z_j = their dot with u, a log-likelihood of shift t_j, times a learned
             per-filter gain N^a_j)]
            h = tanh(z) -> tanh layers -> shift (batch, 1)

With ``dF = 0`` this is ``ann_marg``'s form (its first layer ``Wd p (u - r) + Wref p r``).

The convolutional hyper network (``HyperSpec.conv``, ``ann_conv``) replaces the dense map by
one that moves with the spot::

    refit:  h = tanh conv ... tanh conv ([p r, log(p r + EPS)])        (n, C, p), zero padded
            (g, c) = Linear(mean_i h)                                  (n, K) each
            F = conv(h) exp(g)                                         (n, K, p)

so a reference moved by whole pixels inside the field gives the same filters moved with it
and the same biases: a spot far from the block centre (a layer far from ``h_ref``) is read
as one at the centre, which the dense map, whose weights know each pixel, cannot do; the
pooled gain sets each filter's scale from the whole spot (how sharp it is).

Loss: MSE, or with ``weight_power`` 1 (recipe loss ``fisher``) the squared error times the
spot's Fisher information (:func:`fisher`), i.e. (error / Cramer-Rao bound)^2: the prior's
mean squared error is dominated by faint, broad, truncated spots, where a network that knows
the shift prior beats any unbiased estimator, and left the bright sharp ones 4-40 % behind
the maximum likelihood (most with a sporadic layer); weighted, each spot counts by how
far it is from its bound.

Training (``lgs-wfs train ann_hyper`` / ``ann_conv``: :func:`train`; K = 8, trunk 8-32-1,
dense 64-64, MSE / K = 16, trunk 16-32-1, conv 16-16 kernel 5, fisher):
:func:`.margtrain.generate` spots (the same prior, seeds, check and monitor sets as
``ann_marg``), Adam, cosine learning rate, best monitor weights kept. ``main`` (``python
-m lgs_wfs_ros.learning.hypertrain``) trains variants from cached chunks (:func:`cache_data`)
for experiments.

Export: one ONNX graph with inputs ``marginals (batch, p)`` and ``reference (batch, p)``
and the intermediate tensors ``filters (batch, K', p)`` and ``fbias (batch, K')`` computed
from the reference alone, and ``gain (K',)`` exponents; metadata ``lgs_wfs.hyper = true``.
The centroider (:mod:`..centroiding.ann`) cuts it into a refit graph (reference ->
filters, fbias) and a frame graph (marginals, filters, fbias -> shift).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from . import margtrain, refdata

EPS = 0.02                 # log(p r + EPS): the hyper network's second input
EPS_T = 2e-3               # template filters: log(S_j r + EPS_T), unit-sum r
FILTERS, FBIAS = "filters", "fbias"


@dataclass
class HyperSpec:
    pixels: int = 16
    k: int = 32                      # learned filters
    hyper: tuple = (64, 64)          # hyper MLP widths
    trunk: tuple = (32,)             # per-frame tanh layers after the filters
    templates: tuple = ()            # template shifts, px (empty: none)
    conv: tuple = ()                 # conv hyper network: channels of its hidden layers (empty: dense)
    kernel: int = 5                  # conv hyper network: kernel width, px
    weight_power: float = 0.0        # loss weight (Fisher information along e)^power (0: plain MSE)
    head_scale: float = 0.1          # initial scale of the hyper head
    epochs: int = 40
    batch: int = 512
    lr: float = 2e-3
    seed: int = 16


def shift_matrices(p: int, shifts) -> np.ndarray:
    """``(J, p, p)``: ``S_j r`` = ``r`` moved by ``t_j`` px (linear interpolation, zero outside)."""
    out = np.zeros((len(shifts), p, p))
    for j, t in enumerate(shifts):
        for i in range(p):
            x = i - t                              # output pixel i reads input at i - t
            a = math.floor(x)
            f = x - a
            for b, w in ((a, 1 - f), (a + 1, f)):
                if 0 <= b < p:
                    out[j, i, b] += w
    return out


def tanh_mlp(widths, outputs: int):
    """``torch`` ``Sequential``: tanh layers through ``widths`` (input first), then a linear
    layer to ``outputs`` (the trunk of every hyper network here)."""
    from torch import nn
    mods = []
    for a, b in zip(widths[:-1], widths[1:]):
        mods += [nn.Linear(a, b), nn.Tanh()]
    mods.append(nn.Linear(widths[-1], outputs))
    return nn.Sequential(*mods)


def _torch_module(spec: HyperSpec):
    import torch
    from torch import nn

    class Hyper(nn.Module):
        def __init__(self):
            super().__init__()
            torch.manual_seed(spec.seed)
            p, k = spec.pixels, spec.k
            self.p, self.k = p, k
            self.conv = bool(spec.conv)
            self.wn = nn.Parameter(torch.zeros(k + len(spec.templates)))
            if self.conv:
                self._conv_hyper(spec)
            else:
                self.base = nn.Linear(p, k)                      # F0, c0
                self.wref = nn.Linear(p, k, bias=False)          # Wr (p r) into the bias
                widths = (2 * p, *spec.hyper)
                layers = []
                for a, b in zip(widths[:-1], widths[1:]):
                    layers += [nn.Linear(a, b), nn.Tanh()]
                self.hyper = nn.Sequential(*layers)
                self.head = nn.Linear(widths[-1], k * p + k)
                with torch.no_grad():
                    self.head.weight.mul_(spec.head_scale)
                    self.head.bias.zero_()
            j = len(spec.templates)
            self.j = j
            if j:
                self.register_buffer("shift", torch.tensor(shift_matrices(p, spec.templates), dtype=torch.float32))
                self.tgain = nn.Parameter(torch.zeros(j))     # exponent a_j: z_j * N^a_j ... (scaled)
                self.tscale = nn.Parameter(torch.full((j,), 1.0))
                self.tbias = nn.Parameter(torch.zeros(j))
            self.trunk = tanh_mlp((k + j, *spec.trunk), 1)

        def _conv_hyper(self, spec):
            """Shift-equivariant filters: tanh convolutions over the reference's pixels
            (zero padded), a convolution to the K filters, and from the hidden channels'
            mean over the pixels a log gain and a bias per filter."""
            widths = (2, *spec.conv)
            pad = spec.kernel // 2
            layers = []
            for a, b in zip(widths[:-1], widths[1:]):
                layers += [nn.Conv1d(a, b, spec.kernel, padding=pad), nn.Tanh()]
            self.hyper = nn.Sequential(*layers)
            self.head = nn.Conv1d(widths[-1], self.k, spec.kernel, padding=pad)
            self.pool = nn.Linear(widths[-1], 2 * self.k)
            with torch.no_grad():
                self.head.weight.mul_(spec.head_scale * 10.0)
                self.pool.weight.mul_(0.1)
                self.pool.bias.zero_()

        def filters(self, r):
            """(F (n, k, p) acting on p (u - r), bias (n, k)) from unit-sum r (n, p)."""
            pr = self.p * r
            if self.conv:
                h = self.hyper(torch.stack([pr, torch.log(pr + EPS)], dim=1))
                g, c = self.pool(h.mean(dim=2)).split(self.k, dim=1)
                return self.head(h) * torch.exp(g).unsqueeze(2), c
            q = torch.cat([pr, torch.log(pr + EPS)], dim=1)
            out = self.head(self.hyper(q))
            df = out[:, :self.k * self.p].reshape(-1, self.k, self.p)
            dc = out[:, self.k * self.p:]
            f = self.base.weight.unsqueeze(0) + df
            c = self.base.bias + self.wref(pr) + dc
            return f, c

        def templates(self, r):
            """(T (n, j, p) log templates, acting on u)."""
            t = torch.einsum("jab,nb->nja", self.shift, r)
            return torch.log(t + EPS_T)

        def forward(self, u, r, lf):
            f, c = self.filters(r)
            d = self.p * (u - r)
            z = torch.einsum("nkp,np->nk", f, d) + c
            if self.j:
                t = self.templates(r)
                zt = torch.einsum("njp,np->nj", t, u)
                zt = zt - (torch.einsum("njp,np->nj", t, r))      # centred at the reference
                # likelihood scale N: z_j * tscale_j * 10^(3 lf tgain_j) (lf = log10 N / 3 - 0.8)
                zt = zt * self.tscale * torch.exp(self.tgain * (lf + 0.8) * 3 * math.log(10.0)) + self.tbias
                z = torch.cat([z, zt], dim=1)
            z = z + self.wn * lf
            return self.trunk(torch.tanh(z))

    return Hyper()


def _tensors(pairs):
    import torch
    tot = np.maximum(pairs.marg.sum(axis=1, keepdims=True, dtype=np.float64), 1.0)
    u = (pairs.marg / tot).astype(np.float32)
    lf = (np.log10(tot) / 3.0 - margtrain.LOG_OFFSET).astype(np.float32)
    return (torch.from_numpy(u), torch.from_numpy(np.ascontiguousarray(pairs.refs, dtype=np.float32)),
            torch.from_numpy(lf), torch.from_numpy(np.ascontiguousarray(pairs.y, dtype=np.float32)))


def fisher(pairs) -> np.ndarray:
    """``(n,)`` Fisher information of a shift along e, px^-2: ``N sum_i r'_i^2 / r_i`` from
    the reference's unit-sum column sums ``r`` (central differences, 1e-4 floor) and the
    counts' total ``N``: ``1 / sqrt`` of it is the spot's Cramer-Rao bound, px."""
    r = np.asarray(pairs.refs, np.float64)
    d = np.zeros_like(r)
    d[:, 1:-1] = (r[:, 2:] - r[:, :-2]) / 2
    d[:, 0], d[:, -1] = r[:, 1] / 2, -r[:, -2] / 2
    return pairs.marg.sum(axis=1, dtype=np.float64) * (d ** 2 / (r + 1e-4)).sum(axis=1)


def loss_weights(pairs, power: float):
    """``(n, 1)`` float32 torch weights ``fisher ^ power`` scaled to mean 1 (all 1 at power 0)."""
    import torch
    w = np.ones(len(pairs.y)) if power == 0 else np.maximum(fisher(pairs), 1e-3) ** power
    return torch.from_numpy((w / w.mean()).astype(np.float32)[:, None])


def _mae(net, t) -> float:
    import torch
    with torch.no_grad():
        out = torch.cat([net(t[0][a:a + 16384], t[1][a:a + 16384], t[2][a:a + 16384])
                         for a in range(0, t[0].shape[0], 16384)])
    return float((out - t[3]).abs().mean())


def fit(spec: HyperSpec, data, monitor, log=print, time_budget_s=None):
    """Train on :class:`.refdata.MarginalPairs` ``data``; returns (net, history)."""
    import torch
    torch.set_num_threads(1)
    net = _torch_module(spec)
    tr, mon = _tensors(data), _tensors(monitor)
    wt = loss_weights(data, spec.weight_power)

    def loss_of(idx):
        return (wt[idx] * (net(tr[0][idx], tr[1][idx], tr[2][idx]) - tr[3][idx]) ** 2).mean()

    hist = adam_cosine(net, tr[0].shape[0], loss_of, lambda: _mae(net, mon), spec.epochs,
                       spec.lr, spec.batch, spec.seed, log, time_budget_s)
    return net, hist


def adam_cosine(net, n: int, loss_of, monitor, epochs: int, lr: float, batch: int, seed: int,
                log=print, time_budget_s=None) -> list[dict]:
    """The training loop of the networks here: Adam, a cosine learning rate down to 2 % over
    ``epochs`` of ``n`` samples in shuffled batches (``torch`` generator seeded ``seed``),
    ``loss_of(idx)`` the batch's loss (a scalar tensor), ``monitor()`` the error to keep the
    best weights by (loaded at the end). Returns one record an epoch."""
    import torch
    g = torch.Generator().manual_seed(seed)
    opt = torch.optim.Adam(net.parameters(), lr=lr)
    steps = epochs * math.ceil(n / batch)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda k: 0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * min(k, steps) / steps)))
    best, best_state, hist, t0 = math.inf, None, [], time.perf_counter()
    for ep in range(epochs):
        perm = torch.randperm(n, generator=g)
        tot = 0.0
        for a in range(0, n, batch):
            idx = perm[a:a + batch]
            loss = loss_of(idx)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            tot += float(loss.detach()) * idx.numel()
        err = monitor()
        if err < best:
            best, best_state = err, {k: v.clone() for k, v in net.state_dict().items()}
        hist.append({"epoch": ep, "train_mse": tot / n, "monitor_mae_px": err,
                     "seconds": time.perf_counter() - t0})
        log(f"epoch {ep:3d} mse {tot / n:.5f} monitor {err:.5f} ({hist[-1]['seconds']:.0f} s)")
        if time_budget_s is not None and hist[-1]["seconds"] > time_budget_s:
            break
    net.load_state_dict(best_state)
    return hist


def n_weights(net) -> dict:
    """Parameter counts: the refit part (hyper network) and the per-frame part."""
    mods = (net.hyper, net.head, net.pool) if net.conv else (net.hyper, net.head, net.base, net.wref)
    refit = sum(p.numel() for m in mods for p in m.parameters())
    frame = sum(p.numel() for p in net.trunk.parameters()) + net.wn.numel()
    if net.j:
        frame += 3 * net.j
    return {"refit": int(refit), "frame": int(frame), "filters_per_subap": int((net.k + net.j) * (net.p + 1))}


# -- export ------------------------------------------------------------------------------------
def _dense_refit(net, spec: HyperSpec, st: dict, pr: str, log_pr: str, node, init) -> tuple:
    """ONNX nodes of the dense hyper network: ``(F, c)`` tensor names, ``F = F0 + dF``,
    ``c = c0 + Wr pr + dc``."""
    p, k = spec.pixels, spec.k
    q = node("Concat", [pr, log_pr], ["q"], axis=1)
    h = q
    for i, m in enumerate([m for m in net.hyper if hasattr(m, "weight")]):
        w, b = st[f"hyper.{2 * i}.weight"].T, st[f"hyper.{2 * i}.bias"]
        h = node("Tanh", [node("Add", [node("MatMul", [h, init(w, f"hw{i}")], [f"hm{i}"]), init(b, f"hb{i}")],
                                [f"hz{i}"])], [f"hh{i}"])
    out = node("Add", [node("MatMul", [h, init(st["head.weight"].T, "headw")], ["headm"]),
                       init(st["head.bias"], "headb")], ["head"])
    df = node("Slice", [out, init([0], "s0", np.int64), init([k * p], "skp", np.int64), init([1], "ax1", np.int64)], ["df"])
    dc = node("Slice", [out, "skp", init([k * p + k], "skpk", np.int64), "ax1"], ["dc"])
    f = node("Add", [node("Reshape", [df, init([-1, k, p], "shp_kp", np.int64)], ["df3"]),
                     init(st["base.weight"], "F0")], ["F"])
    c = node("Add", [node("Add", [node("MatMul", [pr, init(st["wref.weight"].T, "Wr")], ["wrpr"]),
                                  init(st["base.bias"], "c0")], ["c1"]), dc], ["cd"])
    return f, c


def _conv_refit(net, spec: HyperSpec, st: dict, pr: str, log_pr: str, node, init) -> tuple:
    """ONNX nodes of the convolutional hyper network: ``(F, c)`` tensor names, ``F = conv(h)
    exp(g)``, ``(g, c) = Linear(mean over pixels of h)``, ``h`` the tanh convolutions of
    ``[p r, log(p r + EPS)]``."""
    k, pad = spec.k, spec.kernel // 2
    ax1 = init([1], "ax1", np.int64)
    h = node("Concat", [node("Unsqueeze", [pr, ax1], ["pr_c"]), node("Unsqueeze", [log_pr, ax1], ["lpr_c"])],
             ["x0"], axis=1)                                               # (n, 2, p)
    for i, m in enumerate([m for m in net.hyper if hasattr(m, "weight")]):
        h = node("Tanh", [node("Conv", [h, init(st[f"hyper.{2 * i}.weight"], f"cw{i}"),
                                        init(st[f"hyper.{2 * i}.bias"], f"cb{i}")], [f"cz{i}"],
                               pads=[pad, pad])], [f"ch{i}"])
    raw = node("Conv", [h, init(st["head.weight"], "headw"), init(st["head.bias"], "headb")], ["Fraw"],
               pads=[pad, pad])
    pooled = node("ReduceMean", [h], ["hmean"], axes=[2], keepdims=0)      # opset 17: axes an attribute
    gc = node("Add", [node("MatMul", [pooled, init(st["pool.weight"].T, "poolw")], ["gcm"]),
                      init(st["pool.bias"], "poolb")], ["gc"])
    g = node("Slice", [gc, init([0], "s0", np.int64), init([k], "sk", np.int64), ax1], ["g"])
    c = node("Slice", [gc, "sk", init([2 * k], "s2k", np.int64), ax1], ["cd"])
    f = node("Mul", [raw, node("Unsqueeze", [node("Exp", [g], ["expg"]), init([2], "ax2u", np.int64)], ["expg3"])],
             ["F"])
    return f, c


class Graph:
    """An ONNX graph under construction: ``init`` adds a constant, ``node`` an operator;
    each returns the name of its (first) output."""

    def __init__(self):
        self.inits, self.nodes = [], []

    def init(self, arr, nm: str, dtype=np.float32) -> str:
        from onnx import numpy_helper
        self.inits.append(numpy_helper.from_array(np.asarray(arr, dtype), nm))
        return nm

    def node(self, op: str, ins, outs, **kw) -> str:
        from onnx import helper
        self.nodes.append(helper.make_node(op, ins, outs, **kw))
        return outs[0]


def build_model(net, spec: HyperSpec, metadata: dict, name: str = "ann_hyper",
                contraction: str = "einsum", detector: str = "polar"):
    """One ONNX graph: reference -> (filters, fbias) [refit part]; marginals, filters, fbias ->
    shift [frame part]. ``filters (batch, K', p)`` act on the raw-sum-normalised column sums
    ``u``; ``fbias (batch, K')`` holds every per-subaperture constant; the frame part then adds
    ``wN ln(N)``, multiplies the template rows by ``N^a`` and runs the tanh trunk.
    ``contraction``: the per-block product ``filters u`` as one ``Einsum`` (faster in
    onnxruntime 1.31) or a batched ``MatMul``. ``detector``: ``lgs_wfs.detector``, "polar"
    or, for a network trained on bins along e of both detectors, "any"."""
    p, k, j = spec.pixels, spec.k, len(spec.templates)
    kk = k + j
    st = {n_: v.detach().cpu().numpy().astype(np.float64) for n_, v in net.state_dict().items()}
    f32 = lambda a: np.asarray(a, np.float32)                         # noqa: E731
    gb = Graph()
    init, node, inits, nodes = gb.init, gb.node, gb.inits, gb.nodes
    # ---- refit part: reference (n, p) unit sum ----
    pr = node("Mul", ["reference", init([p], "c_p")], ["pr"])
    log_pr = node("Log", [node("Add", [pr, init([EPS], "c_eps")], ["pr_eps"])], ["log_pr"])
    refit = _conv_refit if spec.conv else _dense_refit
    f, c = refit(net, spec, st, pr, log_pr, node, init)        # F (n, k, p) on p (u - r); c (n, k)
    # bias: c - F pr (+ the log feature's -0.8 wN, a constant)
    fpr = node("Squeeze", [node("MatMul", [f, node("Unsqueeze", [pr, init([2], "ax2", np.int64)], ["pr3"])],
                                ["fpr3"]), "ax2"], ["fpr"])
    c = node("Sub", [node("Add", [c, init(-0.8 * st["wn"][:k], "c_wn")], ["c2"]), fpr], ["c3"])
    fu = node("Mul", [f, init([p], "c_p2")], ["Fu"])                               # acting on u
    if j:
        sm = shift_matrices(p, spec.templates)                  # (j, a, b): S_j r = r @ S_j^T
        sflat = np.transpose(sm, (2, 0, 1)).reshape(p, j * p)  # r (n, b) @ (b, j*a)
        t = node("Log", [node("Add", [node("Reshape", [node("MatMul", ["reference", init(sflat, "Sall")], ["sr"]),
                                                        init([-1, j, p], "shp_jp", np.int64)], ["sr3"]),
                                      init([EPS_T], "c_epst")], ["sre"])], ["T"])   # (n, j, p) on u
        tr = node("Squeeze", [node("MatMul", [t, node("Unsqueeze", ["reference", "ax2"], ["r3"])], ["tr3"]), "ax2"], ["tr"])
        # zt = (T u - T r) * tscale * N^a + tbias: scale the template rows by tscale, bias -T r tscale
        tscale = st["tscale"]
        tsc = node("Mul", [t, init(tscale.reshape(1, j, 1), "tscale3")], ["Ts"])
        tb = node("Mul", [tr, init(-tscale, "mtscale")], ["tb"])
        fu = node("Concat", [fu, tsc], ["Fall"], axis=1)
        c = node("Concat", [c, tb], ["call"], axis=1)
    node("Identity", [fu], [FILTERS])
    node("Identity", [c], [FBIAS])
    # ---- frame part: marginals (n, p) raw counts ----
    tot = node("Max", [node("ReduceSum", ["marginals", init([1], "axis1", np.int64)], ["total"], keepdims=1),
                       init([1.0], "one")], ["safe"])
    u = node("Div", ["marginals", tot], ["unit"])
    if contraction == "einsum":
        z = node("Einsum", [FILTERS, u], ["zu"], equation="nkp,np->nk")
    else:
        z = node("Squeeze", [node("MatMul", [FILTERS, node("Unsqueeze", [u, "ax2"], ["u3"])], ["zu3"]), "ax2"], ["zu"])
    z = node("Add", [z, FBIAS], ["zc"])
    logn = node("Log", [tot], ["logn"])
    if j:
        # template rows times N^a = exp(a ln N); then + tbias. lf + 0.8 = log10 N / 3: 3 ln10 (lf+0.8) = ln N
        a = np.concatenate([np.zeros(k), st["tgain"]])
        g = node("Exp", [node("Mul", [logn, init(a.reshape(1, kk), "tgain")], ["alogn"])], ["gainN"])
        z = node("Mul", [z, g], ["zg"])
        tb2 = np.concatenate([np.zeros(k), st["tbias"] - 0.8 * st["wn"][k:]])
        z = node("Add", [z, init(tb2, "tbias")], ["zgb"])
    # + wN lf = wN (ln N / (3 ln 10) - 0.8)
    wn = st["wn"]
    z = node("Add", [z, node("Mul", [logn, init((wn / (3 * math.log(10.0))).reshape(1, kk), "wN")], ["wnl"])], ["z0"])
    h = node("Tanh", [z], ["t0"])
    lins = [m for m in net.trunk if hasattr(m, "weight")]
    idx = [i for i, m in enumerate(net.trunk) if hasattr(m, "weight")]
    for n_, (i, m) in enumerate(zip(idx, lins)):
        w, b = st[f"trunk.{i}.weight"].T, st[f"trunk.{i}.bias"]
        last = n_ == len(lins) - 1
        zz = node("Add", [node("MatMul", [h, init(w, f"tw{n_}")], [f"tm{n_}"]), init(b, f"tb{n_}")],
                  ["shift" if last else f"tz{n_}"])
        if not last:
            h = node("Tanh", [zz], [f"th{n_}"])
    return package(nodes, inits, name, "marginals", p, 1, detector, metadata)


def package(nodes, inits, name: str, frame_input: str, pixels: int, outputs: int,
            detector: str, metadata: dict):
    """The checked ONNX model of a hyper graph: inputs ``frame_input (batch, w)`` (``w = p``
    marginals, ``p * p`` whole blocks) and ``reference (batch, w)``, output ``shift (batch,
    outputs)``, and the ``lgs_wfs.*`` metadata the centroider reads (hyper outputs
    ``filters``/``fbias``, trunk cut at ``zc``/``safe``) plus ``metadata``."""
    import onnx
    from onnx import TensorProto, helper
    marginals = frame_input == "marginals"
    width = pixels if marginals else pixels * pixels
    graph = helper.make_graph(
        nodes, name,
        [helper.make_tensor_value_info(frame_input, TensorProto.FLOAT, ["batch", width]),
         helper.make_tensor_value_info("reference", TensorProto.FLOAT, ["batch", width])],
        [helper.make_tensor_value_info("shift", TensorProto.FLOAT, ["batch", outputs])], inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)],
                              producer_name="lgs_wfs_ros.learning")
    model.ir_version = 8
    meta = {"lgs_wfs.pixels": pixels, "lgs_wfs.input": "marginals" if marginals else "pixels",
            "lgs_wfs.input_norm": "none",
            "lgs_wfs.conditioning": "reference", "lgs_wfs.conditioning_input": "reference",
            "lgs_wfs.input_name": frame_input, "lgs_wfs.output_scale": 1.0,
            "lgs_wfs.output_frame": "block", "lgs_wfs.detector": detector,
            "lgs_wfs.hyper": True, "lgs_wfs.hyper_outputs": [FILTERS, FBIAS],
            "lgs_wfs.hyper_trunk": {"z": "zc", "total": "safe"}, **metadata}
    helper.set_model_props(model, {k_: json.dumps(v, sort_keys=True) for k_, v in meta.items()})
    onnx.checker.check_model(model)
    return model


# -- lgs-wfs train ----------------------------------------------------------------------------
def spec_of(rec, epochs: int | None = None, seed: int | None = None) -> HyperSpec:
    """The :class:`HyperSpec` of a recipe with ``filters`` > 0 (``sizes``: trunk, filters
    first, output last; ``hyper_conv``: the convolutional hyper network's channels; loss
    ``fisher``: weight power 1)."""
    if rec.loss not in ("mse", "fisher"):
        raise ValueError(f"{rec.name}: a filters recipe trains with loss mse or fisher, not {rec.loss!r}")
    return HyperSpec(pixels=16, k=int(rec.filters), trunk=tuple(rec.sizes[1:-1]),
                     conv=tuple(rec.hyper_conv), weight_power=1.0 if rec.loss == "fisher" else 0.0,
                     epochs=rec.epochs if epochs is None else int(epochs), batch=rec.batch,
                     lr=rec.lr, seed=rec.seed if seed is None else int(seed))


def train(rec, target: Path, samples: int, seed: int, epochs: int, progress: bool = True,
          time_budget_s: float | None = None) -> dict:
    """Train recipe ``rec`` into ``target`` (an ONNX path) on :func:`.margtrain.generate`'s
    spots (``samples`` from ``seed``: ``ann_marg``'s data for the same numbers); returns
    ``{"path", "training", "history"}``."""
    from . import export
    t0 = time.perf_counter()
    spec = spec_of(rec, epochs, seed)
    dets = rec.detectors
    win, proj = rec.bins_window, rec.bins_projection
    data = margtrain.generate(samples, seed, progress=progress, detectors=dets, window=win,
                              projection=proj)
    mon = margtrain.generate(min(20_000, max(2000, samples // 10)), margtrain.MONITOR_SEED + seed,
                             progress=False, detectors=dets, window=win, projection=proj)
    gen_s = time.perf_counter() - t0
    log = (lambda s: print(s, flush=True)) if progress else (lambda s: None)
    net, hist = fit(spec, data, mon, log=log, time_budget_s=time_budget_s)
    del data
    check = margtrain.generate(margtrain.CHECK_N, margtrain.CHECK_SEED, progress=False, detectors=dets,
                               window=win, projection=proj)
    training = record(rec, spec, samples, gen_s, net, hist, _mae(net, _tensors(check)),
                      "fresh spots of the training prior (margtrain's check set)")
    model = build_model(net, spec, {"lgs_wfs.training": training,
                                    "lgs_wfs.domain": margtrain.domain(detectors=dets),
                                    "lgs_wfs.bins_window": win,
                                    "lgs_wfs.bins_projection": proj}, rec.name,
                        detector="polar" if set(dets) == {"polar"} else "any")
    path = export.save(model, Path(target))
    return {"path": str(path), "training": training, "history": hist}


def train_recipe(name: str, **kwargs) -> dict:
    """``lgs-wfs train`` for a filters recipe: :func:`.reftrain.train_recipe` with this
    module's :func:`train`."""
    from .reftrain import train_recipe as _train_recipe
    return _train_recipe(name, trainer=train, **kwargs)


# -- cached data (probe) ------------------------------------------------------------------------
def load_pairs(path) -> refdata.MarginalPairs:
    d = np.load(path)
    return refdata.MarginalPairs(*[d[k] for k in ("marg", "refs", "y", "r_m", "photons")])


def load_chunks(paths) -> refdata.MarginalPairs:
    parts = [load_pairs(p) for p in paths]
    return refdata.MarginalPairs(*[np.concatenate([getattr(q, f) for q in parts])
                                   for f in ("marg", "refs", "y", "r_m", "photons")])


CHUNK_BATCHES, BATCH = 25, 4096          # a cached chunk: batches [25 c, 25 (c + 1)) of 4096 spots
MONITOR_N = 20_000                       # spots in the cached monitor set


def cache_data(data_dir, chunks: int, seed: int = 16, log=print) -> None:
    """Write the training chunks (``train_NNN.npz``: batch ``k`` of 4096 spots drawn from
    ``default_rng([seed, k])``, :func:`.margtrain.generate`'s batches, so the first 195
    batches are ``ann_marg``'s own), the monitor set (``margtrain``'s) and the check set
    (``CHECK_SEED``) into ``data_dir``; existing files are kept."""
    out = Path(data_dir)
    out.mkdir(parents=True, exist_ok=True)

    def save(name, pairs):
        np.savez(out / name, marg=pairs.marg, refs=pairs.refs, y=pairs.y, r_m=pairs.r_m,
                 photons=pairs.photons)
    if not (out / "check.npz").exists():
        save("check.npz", margtrain.generate(margtrain.CHECK_N, margtrain.CHECK_SEED, progress=False))
    if not (out / "monitor.npz").exists():
        save("monitor.npz", margtrain.generate(MONITOR_N, margtrain.MONITOR_SEED + seed, progress=False))
    for c in range(chunks):
        f = out / f"train_{c:03d}.npz"
        if f.exists():
            continue
        t0 = time.perf_counter()
        parts = [refdata.marginal_pairs(np.random.default_rng([seed, k]), BATCH)
                 for k in range(c * CHUNK_BATCHES, (c + 1) * CHUNK_BATCHES)]
        save(f.name, refdata.MarginalPairs(*[np.concatenate([getattr(q, f_) for q in parts])
                                             for f_ in ("marg", "refs", "y", "r_m", "photons")]))
        log(f"chunk {c}: {time.perf_counter() - t0:.0f} s")


def record(rec, spec: HyperSpec, samples: int, generate_s: float, net, history: list,
           check_mae_px: float, check_what: str) -> dict:
    """The training record (:func:`.margtrain.record`'s schema) of ``net`` trained by
    ``spec`` for recipe ``rec``, with the spec (what a recipe does not hold: the hyper
    widths, templates, head scale) and the weight counts beside it."""
    weights = n_weights(net)
    return margtrain.record(
        rec, samples, spec.seed, generate_s, history, min(h["monitor_mae_px"] for h in history),
        check_mae_px, check_what, spec=asdict(spec), weights=weights,
        parameters=int(sum(v for k, v in weights.items() if k != "filters_per_subap")))


def experiment_record(spec: HyperSpec, samples: int, net, history: list, check_mae_px: float) -> dict:
    """The training record of a :func:`main` variant: :func:`record` for a recipe
    ``ann_hyper`` with the variant's sizes and settings, the same schema ``lgs-wfs train``
    writes; the data came from cached chunks (generate_seconds 0)."""
    from dataclasses import replace

    from .recipes import RECIPES
    rec = replace(RECIPES["ann_hyper"], name="ann_hyper_experiment", filters=spec.k,
                  hyper_conv=tuple(spec.conv), loss="fisher" if spec.weight_power == 1 else "mse",
                  sizes=(spec.k, *spec.trunk, 1), epochs=spec.epochs, batch=spec.batch,
                  lr=spec.lr, seed=spec.seed, samples=samples, shipped=False)
    return record(rec, spec, samples, 0.0, net, history, check_mae_px,
                  "fresh spots of the training prior (margtrain's check set, cached)")


def main(argv=None):
    import argparse
    import glob

    import torch
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", required=True, help="directory of cached chunks (--generate writes them)")
    ap.add_argument("--chunks", type=int, default=2, help="training chunks of 102,400 spots")
    ap.add_argument("--samples", type=int, default=None, help="keep the first SAMPLES spots")
    ap.add_argument("--k", type=int, default=32)
    ap.add_argument("--hyper", default="64,64")
    ap.add_argument("--trunk", default="32")
    ap.add_argument("--conv", default="", help="conv hyper network: hidden channels (e.g. 32,32; empty: dense)")
    ap.add_argument("--kernel", type=int, default=5, help="conv hyper network: kernel width, px")
    ap.add_argument("--weight-power", type=float, default=0.0, help="loss weight: Fisher information^power")
    ap.add_argument("--templates", default="", help="comma-separated template shifts, px")
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--head-scale", type=float, default=0.1)
    ap.add_argument("--seed", type=int, default=16, help="initialisation and shuffling (the data: seed 16)")
    ap.add_argument("--out", required=True)
    ap.add_argument("--generate", action="store_true",
                    help="first draw the missing chunks, monitor and check sets into --data")
    a = ap.parse_args(argv)
    if a.generate:
        cache_data(a.data, a.chunks, log=lambda s: print(s, flush=True))
    ints = lambda s: tuple(int(v) for v in s.split(",") if v)             # noqa: E731
    spec = HyperSpec(k=a.k, hyper=ints(a.hyper), trunk=ints(a.trunk), conv=ints(a.conv), kernel=a.kernel,
                     weight_power=a.weight_power,
                     epochs=a.epochs, lr=a.lr,
                     head_scale=a.head_scale, seed=a.seed,
                     templates=tuple(float(v) for v in a.templates.split(",") if v))
    files = sorted(glob.glob(f"{a.data}/train_*.npz"))[:a.chunks]
    data = load_chunks(files)
    if a.samples:
        data = refdata.MarginalPairs(*[getattr(data, f)[:a.samples]
                                       for f in ("marg", "refs", "y", "r_m", "photons")])
    monitor = load_pairs(f"{a.data}/monitor.npz")
    check = load_pairs(f"{a.data}/check.npz")
    print(f"{len(data.y)} spots; spec {asdict(spec)}", flush=True)
    net, hist = fit(spec, data, monitor, log=lambda s: print(s, flush=True))
    training = experiment_record(spec, int(len(data.y)), net, hist, _mae(net, _tensors(check)))
    model = build_model(net, spec, {"lgs_wfs.training": training,
                                    "lgs_wfs.domain": margtrain.domain(refdata.MARGINAL_SPEC)})
    out = Path(a.out)
    out.write_bytes(model.SerializeToString())
    onnx_mae = float(np.abs(margtrain.predict(out, check) - check.y).mean())
    torch.save(net.state_dict(), out.with_suffix(".pt"))
    print(json.dumps({**training, "check_onnx_mae_px": onnx_mae}), flush=True)


if __name__ == "__main__":
    main()
