"""Small stand-ins for the fitting tests: a flat patch, a flat-patch tracer, a toy kernel model.

They are independent of the real kernels/geodesics modules on purpose: the optimiser, density
control and fit loop are tested on their own logic, with geometry simple enough (a plane) that
the expected answers are known in closed form.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch


def flat_patch(n: int = 9, size: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """A square grid of (n x n) vertices in the z = 0 plane, centred at the origin."""
    t = np.linspace(-size / 2, size / 2, n)
    x, y = np.meshgrid(t, t, indexing="xy")
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = (
        idx[:-1, :-1].ravel(),
        idx[:-1, 1:].ravel(),
        idx[1:, :-1].ravel(),
        idx[1:, 1:].ravel(),
    )
    f = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return v, f


def locate_flat(v: np.ndarray, f: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Face and barycentrics of points in the z = 0 plane (brute force over faces)."""
    tri = v[f][:, :, :2]  # (m, 3, 2)
    p = pts[:, None, :2]
    v0, v1, v2 = tri[None, :, 0], tri[None, :, 1], tri[None, :, 2]
    d = (v1[..., 0] - v0[..., 0]) * (v2[..., 1] - v0[..., 1]) - (v2[..., 0] - v0[..., 0]) * (
        v1[..., 1] - v0[..., 1]
    )
    b1 = (
        (p[..., 0] - v0[..., 0]) * (v2[..., 1] - v0[..., 1])
        - (v2[..., 0] - v0[..., 0]) * (p[..., 1] - v0[..., 1])
    ) / d
    b2 = (
        (v1[..., 0] - v0[..., 0]) * (p[..., 1] - v0[..., 1])
        - (p[..., 0] - v0[..., 0]) * (v1[..., 1] - v0[..., 1])
    ) / d
    b0 = 1 - b1 - b2
    bary = np.stack([b0, b1, b2], -1)  # (P, m, 3)
    fid = np.argmax(bary.min(-1), axis=1)
    out = bary[np.arange(len(pts)), fid]
    out = np.clip(out, 0, None)
    return fid, out / out.sum(1, keepdims=True)


class FlatTracer:
    """Exponential map of a plane: straight lines, transport = identity (clamped at the border)."""

    def __init__(self, v: np.ndarray, f: np.ndarray) -> None:
        self.v, self.f = v, f
        self.lo, self.hi = v[:, :2].min(0), v[:, :2].max(0)
        self.calls = 0

    def trace(self, face_ids, bary, vectors):
        self.calls += 1
        face_ids, bary, vectors = (np.asarray(x) for x in (face_ids, bary, vectors))
        start = (self.v[self.f[face_ids]] * bary[:, :, None]).sum(1)
        end = start + vectors
        end[:, :2] = np.clip(end[:, :2], self.lo, self.hi)
        fid, b = locate_flat(self.v, self.f, end)
        return fid, b, vectors.copy()

    def trace_full(self, face_ids, bary, vectors, transport=None):
        """``trace`` plus the extra vectors, transported by the identity (a plane)."""
        fid, b, vec = self.trace(face_ids, bary, vectors)
        extra = None if transport is None else np.asarray(transport).reshape(len(fid), -1, 3)
        return SimpleNamespace(face_ids=fid, bary=b, vectors=vec, transported=extra)


class ToyModel(torch.nn.Module):
    """Isotropic Gaussian 'kernels' with the attribute names and row API of HeatKernelModel.

    albedo = clamp(a0 + sum_j rho_j a_j / max(1, sum rho), 0, 1) over the top-k responses,
    rho_j = exp(-|x - c_j|^2 / (2 w_j^2)) scaled by the threshold; theta, s and sharpness enter
    the width w_j slightly so that every attribute receives a gradient.
    """

    def __init__(self, v, f, face_ids, bary, colors=None, k_blend: int = 4, sigma: float = 0.25):
        super().__init__()
        n = len(face_ids)
        g = torch.Generator().manual_seed(1)
        dt = torch.float64
        self.register_buffer("V", torch.as_tensor(v, dtype=dt))
        self.register_buffer("F", torch.as_tensor(f, dtype=torch.long))
        self.register_buffer("face_ids", torch.as_tensor(face_ids, dtype=torch.long))
        self.bary = torch.nn.Parameter(torch.as_tensor(bary, dtype=dt))
        self.theta = torch.nn.Parameter(torch.rand(n, generator=g, dtype=dt) * 3)
        self.s = torch.nn.Parameter(torch.log1p(1 + 10 * torch.rand(n, generator=g, dtype=dt)))
        self.threshold = torch.nn.Parameter(0.9 + 0.09 * torch.rand(n, generator=g, dtype=dt))
        self.sharpness = torch.nn.Parameter(10 + 20 * torch.rand(n, generator=g, dtype=dt))
        c = colors if colors is not None else 0.2 * torch.randn(n, 3, generator=g, dtype=dt)
        self.colors = torch.nn.Parameter(torch.as_tensor(c, dtype=dt))
        self.base_color = torch.nn.Parameter(torch.full((3,), 0.5, dtype=dt))
        # the paper's blend: a priority row that follows the kernels and gets no gradient
        self.priority = torch.nn.Parameter(torch.zeros(n, dtype=dt), requires_grad=False)
        # sigma_B for every kernel: a log-scale row that follows the kernels, no gradient
        self.log_sigma = torch.nn.Parameter(torch.zeros(n, dtype=dt), requires_grad=False)
        # flat colours: a slope row that follows the kernels, no gradient
        self.color_slopes = torch.nn.Parameter(
            torch.zeros((n, 3, 3), dtype=dt), requires_grad=False
        )
        self.k_blend = k_blend
        self.sigma = sigma
        self.refreshes = 0

    def _rows(self):
        return [
            self.bary, self.theta, self.s, self.threshold, self.sharpness, self.colors,
            self.priority, self.log_sigma, self.color_slopes,
        ]  # fmt: skip

    def centres(self) -> torch.Tensor:
        return (self.V[self.F[self.face_ids]] * self.bary[:, :, None]).sum(1)

    def albedo(self, face_ids, bary, return_aux=False):
        x = (self.V[self.F[face_ids]] * bary[:, :, None]).sum(1)
        d2 = ((x[:, None, :] - self.centres()[None]) ** 2).sum(-1)
        width = self.sigma * (
            1 + 0.01 * torch.cos(self.theta) + 0.001 * self.s + 0.001 * self.sharpness
        )
        rho = torch.exp(-d2 / (2 * width[None] ** 2)) * self.threshold[None]
        k = min(self.k_blend, rho.shape[1])
        vals, idx = rho.topk(k, dim=1)
        blend = (vals[..., None] * self.colors[idx]).sum(1) / vals.sum(1, keepdim=True).clamp_min(1)
        a = (self.base_color + blend).clamp(0, 1)
        return (a, {"indices": idx, "rho": vals}) if return_aux else a

    def refresh(self) -> None:
        self.refreshes += 1

    @torch.no_grad()
    def project_(self) -> None:
        self.theta.clamp_(0, np.pi)
        self.s.clamp_(np.log(2.0), np.log(201.0))
        self.threshold.clamp_(0.3, 1 - 1e-4)
        self.sharpness.clamp_(10, 200)
        self.colors.clamp_(-1, 1)
        self.base_color.clamp_(0, 1)

    @torch.no_grad()
    def set_centres(self, face_ids, bary) -> None:
        self.face_ids = torch.as_tensor(face_ids, dtype=torch.long)
        self.bary.data = torch.as_tensor(bary, dtype=torch.float64).clone()

    @torch.no_grad()
    def select(self, idx):
        idx = torch.as_tensor(idx, dtype=torch.long)
        self.face_ids = self.face_ids[idx]
        for p in self._rows():
            p.data = p.data[idx]
            p.grad = None
        return self

    @torch.no_grad()
    def append(
        self,
        face_ids,
        bary,
        theta,
        eta,
        threshold,
        sharpness,
        colors,
        priority=None,
        log_sigma=None,
        color_slopes=None,
    ):
        self.face_ids = torch.cat([self.face_ids, torch.as_tensor(face_ids, dtype=torch.long)])
        if priority is None:
            priority = torch.zeros(len(face_ids), dtype=torch.float64)
        if log_sigma is None:
            log_sigma = torch.zeros(len(face_ids), dtype=torch.float64)
        if color_slopes is None:
            color_slopes = torch.zeros((len(face_ids), 3, 3), dtype=torch.float64)
        new = [
            bary,
            theta,
            torch.log1p(torch.as_tensor(eta)),
            threshold,
            sharpness,
            colors,
            priority,
            log_sigma,
            color_slopes,
        ]
        for p, rows in zip(self._rows(), new, strict=True):
            p.data = torch.cat([p.data, torch.as_tensor(rows, dtype=torch.float64)])
            p.grad = None
        return self


def two_colour(points: torch.Tensor) -> torch.Tensor:
    """Target albedo: red where x < 0, blue elsewhere."""
    red = torch.tensor([0.9, 0.1, 0.1], dtype=points.dtype)
    blue = torch.tensor([0.1, 0.2, 0.9], dtype=points.dtype)
    return torch.where((points[:, :1] < 0), red, blue)


class ToyObjective:
    """Random points on the patch, smooth-L1 against :func:`two_colour`."""

    def __init__(self, v, f, n_points: int = 64) -> None:
        self.V = torch.as_tensor(v, dtype=torch.float64)
        self.F = torch.as_tensor(f, dtype=torch.long)
        self.n = n_points

    def sample(self, step, rng):
        fid = rng.integers(0, len(self.F), self.n)
        b = rng.dirichlet(np.ones(3), self.n)
        return torch.as_tensor(fid), torch.as_tensor(b)

    def loss(self, model, batch):
        from hktex_engine.fitting.loop import PointStats

        fid, b = batch
        pred, aux = model.albedo(fid, b, return_aux=True)
        idx, rho = aux["indices"], aux["rho"]
        x = (self.V[self.F[fid]] * b[:, :, None]).sum(1)
        target = two_colour(x)
        loss = torch.nn.functional.smooth_l1_loss(pred, target, beta=1.0)
        err = (pred - target).abs().mean(1)
        return loss, PointStats(err.detach(), idx, rho.detach(), fid, b)


class StopAfter:
    """A Progress that asks the loop to stop once it has been polled ``polls`` times (the loop
    polls before every step, so the fit cancels before step ``polls``, 0-based)."""

    def __init__(self, polls: int) -> None:
        self.polls = polls
        self.calls = 0

    def update(self, step, total, **metrics) -> None:
        return None

    def should_stop(self) -> bool:
        self.calls += 1
        return self.calls > self.polls
