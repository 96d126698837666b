"""Optimisers for a heat-kernel set (ALGORITHM.md section 6).

Two kinds of parameters live on two kinds of spaces:

* attributes (colours, angle, anisotropy, threshold, sharpness, base colour) live in boxes:
  Adam, then projection back into each box;
* centres live on the surface: Riemannian SGD whose step is an exponential-map trace
  (``geodesics.SurfaceTracer.trace``), with momentum parallel-transported along the same path.

Both keep their state **per kernel row** so density control can clone, split and prune kernels
and the state follows the survivors while newcomers start from zero (:meth:`resize`). That is
why Adam is written here rather than taken from ``torch.optim``: torch's Adam keeps one step
count per tensor, so a newcomer appended to a long-running tensor would get the bias
correction of step 10,000 for its very first update (an effective first step ~3x too large),
and its state cannot be gathered row-wise through a public API.

The model is ``kernels.HeatKernelModel`` (or anything with its attribute names, see
:data:`KERNEL_ATTRIBUTES`, and its ``project_``, ``set_centres``, ``select``, ``append``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
import torch

from hktex_engine.config import FitParams

#: tensors optimised by Adam (the model's attribute names) -> FitParams learning-rate field.
#: ``s`` = ln(1 + eta) is the model's parameter for the anisotropy (kernels.HeatKernelModel).
ATTRIBUTE_LRS: dict[str, str] = {
    "colors": "lr_colors",
    "theta": "lr_theta",
    "s": "lr_eta",
    "threshold": "lr_threshold",
    "sharpness": "lr_sharpness",
    "base_color": "lr_base",
}
#: every per-kernel tensor of the model (the centre is face_ids + bary), checkpoint order
KERNEL_ATTRIBUTES: tuple[str, ...] = (
    "face_ids",
    "bary",
    "theta",
    "s",
    "threshold",
    "sharpness",
    "colors",
)


class Tracer(Protocol):
    """What the optimiser needs from ``geodesics.SurfaceTracer``."""

    def trace(self, face_ids: Any, bary: Any, vectors: Any) -> tuple[Any, Any, Any]: ...


def lr_factor(step: int, params: FitParams) -> float:
    """Step decay: x lr_decay every lr_decay_every steps (reference: x0.5 every 1000)."""
    if params.lr_decay_every <= 0:
        return 1.0
    return float(params.lr_decay ** (step // params.lr_decay_every))


def tangent_gradient(
    vertices: torch.Tensor, faces: torch.Tensor, face_ids: torch.Tensor, grad_bary: torch.Tensor
) -> torch.Tensor:
    """Euclidean gradient w.r.t. a centre's 3-D position, in its face plane, from dL/db.

    A centre x = sum_v b_v x_v moves in its face plane when the barycentrics change by db with
    sum(db) = 0, so dx = db_1 (x_1 - x_0) + db_2 (x_2 - x_0) and dL = db_1 (G_1 - G_0) +
    db_2 (G_2 - G_0) with G = dL/db. The in-plane g with dL = g . dx for every such dx therefore
    solves g . (x_v - x_0) = G_v - G_0 (v = 1, 2); writing g = c_1 e_1 + c_2 e_2 turns this
    into the 2 x 2 Gram system E E^T c = dG, solved for all centres at once.
    """
    tri = vertices[faces[face_ids]]  # (N, 3, 3)
    edges = tri[:, 1:, :] - tri[:, :1, :]  # (N, 2, 3): e_1, e_2
    gram = edges @ edges.transpose(1, 2)  # (N, 2, 2)
    grad_bary = grad_bary.to(vertices.dtype)
    rhs = (grad_bary[:, 1:] - grad_bary[:, :1]).unsqueeze(-1)  # (N, 2, 1)
    coeffs = torch.linalg.solve(gram, rhs)  # (N, 2, 1)
    return (coeffs.transpose(1, 2) @ edges).squeeze(1)  # (N, 3)


def long_axis(
    face_frames: torch.Tensor,
    face_normals: torch.Tensor,
    face_ids: torch.Tensor,
    theta: torch.Tensor,
) -> torch.Tensor:
    """u_theta: the face's u_ref rotated by theta about the face normal (ALGORITHM.md 1)."""
    u = face_frames[face_ids]
    n = face_normals[face_ids]
    w = torch.linalg.cross(n, u, dim=-1)
    return torch.cos(theta)[:, None] * u + torch.sin(theta)[:, None] * w


def face_unit_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    tri = vertices[faces]
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)


def trace_on_surface(
    tracer: Tracer, face_ids: torch.Tensor, bary: torch.Tensor, vectors: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Call the tracer with float64 tensors on their device; answers come back as tensors.

    ``geodesics.SurfaceTracer`` answers torch input with tensors on the input's device (no
    host round trip on CUDA); a tracer answering numpy is accepted as well.
    """
    device = bary.device
    f_end, b_end, v_end = tracer.trace(
        face_ids.detach(),
        bary.detach().to(torch.float64),
        vectors.detach().to(torch.float64),
    )

    def back(x, dtype: torch.dtype) -> torch.Tensor:
        return torch.as_tensor(x if torch.is_tensor(x) else np.asarray(x)).to(device, dtype)

    return back(f_end, torch.long), back(b_end, bary.dtype), back(v_end, vectors.dtype)


@dataclass
class _AdamRows:
    """Adam moments and step counts for one tensor; rows are kernels (or one shared row)."""

    exp_avg: torch.Tensor
    exp_avg_sq: torch.Tensor
    steps: torch.Tensor  # (N,) per-row step count, or () for a shared tensor


class RowAdam:
    """Adam with per-row state (see the module docstring for why not torch.optim.Adam)."""

    def __init__(self, lrs: dict[str, float], betas=(0.9, 0.999), eps: float = 1e-15) -> None:
        # eps is tiny (as 3D Gaussian splatting's optimisers use) because gradients of a single
        # kernel's attributes are small (each kernel touches a few points per batch) and an
        # eps of 1e-8 would mute them.
        self.lrs = dict(lrs)
        self.betas = betas
        self.eps = eps
        self.state: dict[str, _AdamRows] = {}

    def _rows(self, name: str, p: torch.Tensor) -> _AdamRows:
        st = self.state.get(name)
        if st is None or st.exp_avg.shape != p.shape:
            per_row = name != "base_color"
            st = _AdamRows(
                torch.zeros_like(p),
                torch.zeros_like(p),
                torch.zeros(p.shape[0] if per_row else (), dtype=p.dtype, device=p.device),
            )
            self.state[name] = st
        return st

    @torch.no_grad()
    def step(self, tensors: dict[str, torch.Tensor], scale: float = 1.0) -> None:
        b1, b2 = self.betas
        for name, p in tensors.items():
            if p.grad is None:
                continue
            g = p.grad
            st = self._rows(name, p)
            st.steps += 1
            st.exp_avg.mul_(b1).add_(g, alpha=1.0 - b1)
            st.exp_avg_sq.mul_(b2).addcmul_(g, g, value=1.0 - b2)
            t = st.steps.reshape(st.steps.shape + (1,) * (p.dim() - st.steps.dim()))
            bias1 = 1.0 - b1**t
            bias2 = 1.0 - b2**t
            denom = (st.exp_avg_sq / bias2).sqrt_().add_(self.eps)
            p.sub_(self.lrs[name] * scale * (st.exp_avg / bias1) / denom)

    def resize(self, keep: torch.Tensor, n_new: int) -> None:
        """Keep the rows ``keep`` of every per-kernel state, append ``n_new`` zero rows."""
        for name, st in self.state.items():
            if st.steps.dim() == 0:
                continue
            self.state[name] = _AdamRows(
                _keep_append(st.exp_avg, keep, n_new),
                _keep_append(st.exp_avg_sq, keep, n_new),
                _keep_append(st.steps, keep, n_new),
            )


def _keep_append(t: torch.Tensor, keep: torch.Tensor, n_new: int) -> torch.Tensor:
    zeros = torch.zeros((n_new,) + tuple(t.shape[1:]), dtype=t.dtype, device=t.device)
    return torch.cat([t[keep], zeros], dim=0)


class RiemannianSGD:
    """SGD with momentum for points on a triangle mesh; steps follow the exponential map."""

    def __init__(self, tracer: Tracer, lr: float, momentum: float) -> None:
        self.tracer = tracer
        self.lr = lr
        self.momentum = momentum
        self.buf: torch.Tensor | None = None  # (N, 3) momentum, in each centre's face plane

    @torch.no_grad()
    def step(
        self, face_ids: torch.Tensor, bary: torch.Tensor, grad: torch.Tensor, scale: float = 1.0
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Move centres by -lr * m along geodesics; return the new (face_ids, barycentrics).

        ``grad`` is the tangent Euclidean gradient (:func:`tangent_gradient`). The momentum is
        carried to the end face by the tracer's parallel transport of the step vector itself:
        transport is linear, so transporting -lr*m and dividing by -lr transports m.
        """
        if self.buf is None or self.buf.shape != grad.shape:
            self.buf = torch.zeros_like(grad)
        m = self.buf.mul_(self.momentum).add_(grad) if self.momentum else grad.clone()
        lr = self.lr * scale
        step = -lr * m
        moving = step.norm(dim=-1) > 0
        if lr == 0.0 or not bool(moving.any()):
            self.buf = m
            return face_ids, bary
        new_f, new_b = face_ids.clone(), bary.clone()
        f_end, b_end, v_end = trace_on_surface(
            self.tracer, face_ids[moving], bary[moving], step[moving]
        )
        new_f[moving], new_b[moving] = f_end, b_end
        m = m.clone()
        m[moving] = v_end / (-lr)
        self.buf = m
        return new_f, new_b

    def resize(self, keep: torch.Tensor, n_new: int) -> None:
        if self.buf is not None:
            self.buf = _keep_append(self.buf, keep, n_new)


def model_tensors(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The model's per-kernel tensors plus ``base_color``, by name (no copies)."""
    out = {name: getattr(model, name) for name in KERNEL_ATTRIBUTES}
    out["base_color"] = model.base_color
    return out


class KernelOptimiser:
    """Adam on attributes + Riemannian SGD on centres for one model; state resizable by rows."""

    def __init__(
        self,
        model: torch.nn.Module,
        params: FitParams,
        tracer: Tracer,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        momentum: float | None = None,
    ) -> None:
        self.model = model
        self.params = params
        self.vertices = vertices
        self.faces = faces
        lrs = {name: getattr(params, field) for name, field in ATTRIBUTE_LRS.items()}
        self.adam = RowAdam(lrs)
        mom = params.center_momentum if momentum is None else momentum
        self.centres = RiemannianSGD(tracer, params.lr_centers, mom)

    def zero_grad(self) -> None:
        for t in model_tensors(self.model).values():
            t.grad = None

    @torch.no_grad()
    def step(self, step_index: int) -> None:
        """One update of every parameter; the caller refreshes the model's query state."""
        scale = lr_factor(step_index, self.params)
        tensors = model_tensors(self.model)
        attrs = {k: v for k, v in tensors.items() if k in self.adam.lrs}
        self.adam.step(attrs, scale)
        self.model.project_()  # attributes back into their boxes (ALGORITHM.md 4)
        gb = self.model.bary.grad
        if gb is not None:
            g = tangent_gradient(self.vertices, self.faces, self.model.face_ids, gb)
            f, b = self.centres.step(self.model.face_ids, self.model.bary, g, scale)
            self.model.set_centres(f, b)

    def resize(self, keep: torch.Tensor, n_new: int) -> None:
        self.adam.resize(keep, n_new)
        self.centres.resize(keep, n_new)

    def state_arrays(self) -> dict[str, np.ndarray]:
        """Optimiser state as plain arrays (for checkpoints; no pickles)."""
        out: dict[str, np.ndarray] = {}
        for name, st in self.adam.state.items():
            out[f"adam.{name}.exp_avg"] = st.exp_avg.detach().cpu().numpy()
            out[f"adam.{name}.exp_avg_sq"] = st.exp_avg_sq.detach().cpu().numpy()
            out[f"adam.{name}.steps"] = st.steps.detach().cpu().numpy()
        if self.centres.buf is not None:
            out["centres.momentum"] = self.centres.buf.detach().cpu().numpy()
        return out

    def load_state_arrays(self, arrays: dict[str, np.ndarray], device: torch.device) -> None:
        self.adam.state = {}
        names = {k.split(".")[1] for k in arrays if k.startswith("adam.")}
        for name in names:
            self.adam.state[name] = _AdamRows(
                *(
                    torch.as_tensor(arrays[f"adam.{name}.{part}"], device=device)
                    for part in ("exp_avg", "exp_avg_sq", "steps")
                )
            )
        mom = arrays.get("centres.momentum")
        self.centres.buf = None if mom is None else torch.as_tensor(mom, device=device)
