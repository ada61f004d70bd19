"""Levenberg-Marquardt for the paper's one-hidden-layer network (PyTorch, lazily imported).

The paper trained its 256-16-2 networks with Matlab's ``trainlm``. This is the same
algorithm on a fixed training batch: residuals ``r = f(x; w) - y`` (``2 N`` of them),
the analytic Jacobian ``J`` ``(2N, P)`` of a tanh MLP with one hidden layer, and the step
``(J^T J + mu I) dw = -J^T r``; a step that lowers the sum of squares is kept and ``mu``
divided by ``mu_dec`` (10), otherwise ``mu`` is multiplied by ``mu_inc`` (10) and the
step retried (Matlab's defaults: mu 1e-3, dec 0.1, inc 10, max 1e10).

``J^T J`` (4,146^2 for 256-16-2) is accumulated over chunks of samples in float32 and
solved in float64 by Cholesky; its cost is ``2 N P^2`` flops per iteration, so the batch
is a few 10^4 samples at most.
"""

from __future__ import annotations

import time



def _unpack(theta, sizes):
    n_in, n_h, n_out = sizes
    k = 0
    w1 = theta[k:k + n_h * n_in].reshape(n_h, n_in); k += n_h * n_in
    b1 = theta[k:k + n_h]; k += n_h
    w2 = theta[k:k + n_out * n_h].reshape(n_out, n_h); k += n_out * n_h
    b2 = theta[k:k + n_out]
    return w1, b1, w2, b2


def pack(net):
    """Flat float64 parameter vector of a 1-hidden-layer :func:`.model.mlp`."""
    import torch
    from .model import linears
    l1, l2 = linears(net)
    return torch.cat([l1.weight.reshape(-1), l1.bias, l2.weight.reshape(-1), l2.bias]).detach().double()


def unpack_into(net, theta) -> None:
    """Write a flat parameter vector back into the network."""
    import torch
    from .model import linears, sizes_of
    w1, b1, w2, b2 = _unpack(theta, sizes_of(net))
    l1, l2 = linears(net)
    with torch.no_grad():
        l1.weight.copy_(w1); l1.bias.copy_(b1); l2.weight.copy_(w2); l2.bias.copy_(b2)


def _forward(theta, sizes, x):
    w1, b1, w2, b2 = _unpack(theta, sizes)
    h = (x @ w1.T + b1).tanh()
    return h, h @ w2.T + b2


def sse(theta, sizes, x, y, chunk: int = 65536) -> float:
    """Sum of squared residuals."""
    tot = 0.0
    for a in range(0, x.shape[0], chunk):
        _, out = _forward(theta, sizes, x[a:a + chunk])
        tot += float(((out - y[a:a + chunk]) ** 2).sum())
    return tot


def normal_equations(theta, sizes, x, y, chunk: int = 2048):
    """``(J^T J (P, P) float64, J^T r (P,) float64, sse)`` over all samples."""
    import torch
    n_in, n_h, n_out = sizes
    P = theta.numel()
    jtj = torch.zeros((P, P), dtype=torch.float32)
    jtr = torch.zeros(P, dtype=torch.float64)
    total = 0.0
    th32 = theta.float()
    w1, b1, w2, b2 = _unpack(th32, sizes)
    for a in range(0, x.shape[0], chunk):
        xc, yc = x[a:a + chunk], y[a:a + chunk]
        m = xc.shape[0]
        h = (xc @ w1.T + b1).tanh()                                  # (m, H)
        r = h @ w2.T + b2 - yc                                       # (m, O)
        total += float((r.double() ** 2).sum())
        dh = 1.0 - h * h
        rows = []
        for o in range(n_out):
            a_o = w2[o][None, :] * dh                                # (m, H)
            jw1 = (a_o[:, :, None] * xc[:, None, :]).reshape(m, -1)  # (m, H*in)
            jw2 = torch.zeros((m, n_out * n_h)); jw2[:, o * n_h:(o + 1) * n_h] = h
            jb2 = torch.zeros((m, n_out)); jb2[:, o] = 1.0
            rows.append(torch.cat([jw1, a_o, jw2, jb2], dim=1))
        jac = torch.cat(rows, dim=0)                                 # (O*m, P)
        res = torch.cat([r[:, o] for o in range(n_out)])             # (O*m,)
        jtj.addmm_(jac.T, jac)
        jtr += (jac.T @ res).double()
    return jtj.double(), jtr, total


def fit(net, x, y, *, iterations: int = 100, mu: float = 1e-3, mu_dec: float = 0.1,
        mu_inc: float = 10.0, mu_max: float = 1e10, time_budget_s: float | None = None,
        callback=None, progress: bool = True) -> list[dict]:
    """Train a 1-hidden-layer tanh MLP in place by Levenberg-Marquardt.

    Args:
        net: :func:`.model.mlp` with sizes ``(in, hidden, out)``.
        x, y: float32 torch tensors ``(N, in)``, ``(N, out)`` (the fixed training batch).
        iterations: accepted-or-rejected outer iterations (epochs in Matlab's terms).
        mu, mu_dec, mu_inc, mu_max: Marquardt damping schedule.
        time_budget_s: stop after this wall time.
        callback: ``callback(iteration, net) -> dict`` merged into the history row.

    Returns:
        history rows ``{"iter", "mse", "mu", "seconds", ...}``.
    """
    import torch
    from tqdm.auto import tqdm

    from .model import sizes_of
    sizes = sizes_of(net)
    if len(sizes) != 3:
        raise ValueError(f"LM here handles one hidden layer, got sizes {sizes}")
    theta = pack(net)
    t0 = time.perf_counter()
    hist = []
    eye = torch.eye(theta.numel(), dtype=torch.float64)
    n_res = y.numel()
    bar = tqdm(range(iterations), desc="LM", disable=not progress, mininterval=2.0)
    for it in bar:
        jtj, jtr, cur = normal_equations(theta, sizes, x, y)
        diag_scale = 1.0   # Matlab trainlm damps with mu*I (not Marquardt's diag scaling)
        improved = False
        while mu <= mu_max:
            try:
                chol = torch.linalg.cholesky(jtj + mu * diag_scale * eye)
                step = torch.cholesky_solve(-jtr[:, None], chol)[:, 0]
            except RuntimeError:
                mu *= mu_inc
                continue
            cand = theta + step
            new = sse(cand.float(), sizes, x, y)
            if new < cur:
                theta, cur = cand, new
                mu *= mu_dec
                improved = True
                break
            mu *= mu_inc
        row = {"iter": it, "mse": cur / n_res, "mu": mu, "seconds": time.perf_counter() - t0}
        if callback is not None:
            unpack_into(net, theta.float())
            row.update(callback(it, net))
        hist.append(row)
        bar.set_postfix(mse=f"{row['mse']:.3g}", mu=f"{mu:.1e}")
        if not improved or (time_budget_s is not None and row["seconds"] > time_budget_s):
            break
    unpack_into(net, theta.float())
    return hist


__all__ = ["fit", "normal_equations", "sse", "pack", "unpack_into"]
