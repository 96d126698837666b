"""Optimisers for a heat-kernel set (ALGORITHM.md section 6).

Two kinds of parameters live on two kinds of spaces:

* attributes (colours, angle, anisotropy, threshold, sharpness, base colour, and the layered
  blend's priority, which the paper's blend gives no gradient) live in boxes:
  Adam, then projection back into each box;
* centres live on the surface: Riemannian SGD whose step is an exponential-map trace
  (``geodesics.SurfaceTracer.trace``), with momentum parallel-transported along the same path.

A kernel's angle ``theta`` is measured from its centre face's ``u_ref`` (ALGORITHM.md 1), so
when a step carries a centre into another face the number alone would describe another axis
there. The long axis is therefore parallel-transported along the step's path and ``theta``
re-expressed against the end face's ``u_ref`` (:func:`theta_in_faces`).

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

import math
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
    "priority": "lr_priority",
    "log_sigma": "lr_sigma",
    "color_slopes": "lr_slopes",
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
    "priority",
    "log_sigma",
    "color_slopes",
)


class Tracer(Protocol):
    """What the optimiser needs from ``geodesics.SurfaceTracer``.

    ``trace_full(face_ids, bary, vectors, transport=T)`` (an object with ``face_ids``,
    ``bary``, ``vectors`` and ``transported``) is needed as well wherever kernel axes are
    carried along (:class:`KernelOptimiser` given ``face_frames``, density splits).
    """

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


#: angles this close (radians) outside [0, pi] are clamped, not folded (see theta_in_faces)
_FOLD_SLACK = 1e-6


def axis_pair(
    face_frames: torch.Tensor,
    face_normals: torch.Tensor,
    face_ids: torch.Tensor,
    theta: torch.Tensor,
) -> torch.Tensor:
    """(N, 2, 3): the long axis u_theta and w_theta = n x u_theta, in float64.

    Both are transported so that the end face can tell whether the path's transport kept the
    sense of rotation about its normal (it does not across faces of opposite winding), which
    decides the sign of theta's Adam momentum there (:meth:`KernelOptimiser.step`).
    """
    n = face_normals[face_ids].to(torch.float64)
    u = long_axis(
        face_frames.to(torch.float64),
        face_normals.to(torch.float64),
        face_ids,
        theta.detach().to(torch.float64),
    )
    return torch.stack([u, torch.linalg.cross(n, u, dim=-1)], dim=1)


def theta_in_faces(
    face_frames: torch.Tensor,
    face_normals: torch.Tensor,
    face_ids: torch.Tensor,
    axes: torch.Tensor,
    theta_ref: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Angles of tangent axes against their faces' u_ref; (theta in [0, pi], reversed mask).

    ``axes`` is (N, 2, 3): an axis and the vector a quarter turn from it (:func:`axis_pair`),
    both in the plane of ``face_ids``. An axis has no sign, so its angle is defined modulo
    pi; of all representatives we take the one nearest ``theta_ref`` (the kernel's angle
    before the move), then fold it into [0, pi]. So an axis whose frame did not change keeps
    its angle, at 0 and at pi too (the model clamps theta into [0, pi], it never wraps),
    instead of jumping between the ends on rounding.

    ``reversed`` is True where the second vector is on the clockwise side of the axis about
    the face normal: the transport turned positive rotations into negative ones (faces wound
    the other way), so d/dtheta now points the other way.
    """
    dt = torch.float64
    n = face_normals[face_ids].to(dt)
    u = face_frames[face_ids].to(dt)
    u = u - (u * n).sum(-1, keepdim=True) * n  # frames are in-plane; guard float32 input
    u = u / u.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    w = torch.linalg.cross(n, u, dim=-1)
    a, b = axes[:, 0].to(dt), axes[:, 1].to(dt)
    phi = torch.atan2((a * w).sum(-1), (a * u).sum(-1))
    ref = theta_ref.detach().to(dt)
    half = math.pi / 2
    t = ref + torch.remainder(phi - ref + half, math.pi) - half  # nearest ref, = phi mod pi
    # fold into [0, pi]; within _FOLD_SLACK of an end clamp instead: rounding must not send
    # an axis at 0 to pi (the same line, but the far end of the model's clamped range)
    t = torch.where(t < -_FOLD_SLACK, t + math.pi, t)
    t = torch.where(t > math.pi + _FOLD_SLACK, t - math.pi, t).clamp(0.0, math.pi)
    reversed_ = (torch.linalg.cross(a, b, dim=-1) * n).sum(-1) < 0
    return t.to(theta_ref.dtype), reversed_


def face_unit_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    tri = vertices[faces]
    n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    return n / n.norm(dim=-1, keepdim=True).clamp_min(1e-30)


def _back(x: Any, device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    return torch.as_tensor(x if torch.is_tensor(x) else np.asarray(x)).to(device, dtype)


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
    return (
        _back(f_end, device, torch.long),
        _back(b_end, device, bary.dtype),
        _back(v_end, device, vectors.dtype),
    )


def trace_transporting(
    tracer: Tracer,
    face_ids: torch.Tensor,
    bary: torch.Tensor,
    vectors: torch.Tensor,
    transport: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`trace_on_surface` that also parallel-transports ``transport`` (N, K, 3).

    Returns (end faces, end barycentrics, transported step vectors, transported extras in
    float64, (N, K, 3)).
    """
    if not hasattr(tracer, "trace_full"):
        raise TypeError("carrying kernel axes needs a tracer with trace_full(..., transport=)")
    device = bary.device
    res = tracer.trace_full(
        face_ids.detach(),
        bary.detach().to(torch.float64),
        vectors.detach().to(torch.float64),
        transport=transport.detach().to(torch.float64),
    )
    extra = _back(res.transported, device, torch.float64).reshape(transport.shape)
    return (
        _back(res.face_ids, device, torch.long),
        _back(res.bary, device, bary.dtype),
        _back(res.vectors, device, vectors.dtype),
        extra,
    )


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
        f, b, _ = self.step_transporting(face_ids, bary, grad, None, scale)
        return f, b

    @torch.no_grad()
    def step_transporting(
        self,
        face_ids: torch.Tensor,
        bary: torch.Tensor,
        grad: torch.Tensor,
        transport: torch.Tensor | None,
        scale: float = 1.0,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """:meth:`step`, also parallel-transporting ``transport`` (N, K, 3) along each path.

        Returns (face_ids, barycentrics, transported (float64; rows of centres that did not
        move are the input's), or None without ``transport``).
        """
        if self.buf is None or self.buf.shape != grad.shape:
            self.buf = torch.zeros_like(grad)
        m = self.buf.mul_(self.momentum).add_(grad) if self.momentum else grad.clone()
        lr = self.lr * scale
        step = -lr * m
        moving = step.norm(dim=-1) > 0
        extra = None if transport is None else transport.detach().to(torch.float64).clone()
        if lr == 0.0 or not bool(moving.any()):
            self.buf = m
            return face_ids, bary, extra
        new_f, new_b = face_ids.clone(), bary.clone()
        if extra is None:
            f_end, b_end, v_end = trace_on_surface(
                self.tracer, face_ids[moving], bary[moving], step[moving]
            )
        else:
            f_end, b_end, v_end, x_end = trace_transporting(
                self.tracer, face_ids[moving], bary[moving], step[moving], extra[moving]
            )
            extra[moving] = x_end
        new_f[moving], new_b[moving] = f_end, b_end
        m = m.clone()
        m[moving] = v_end / (-lr)
        self.buf = m
        return new_f, new_b, extra

    def resize(self, keep: torch.Tensor, n_new: int) -> None:
        if self.buf is not None:
            self.buf = _keep_append(self.buf, keep, n_new)


def model_tensors(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    """The model's per-kernel tensors plus ``base_color``, by name (no copies)."""
    out = {name: getattr(model, name) for name in KERNEL_ATTRIBUTES}
    out["base_color"] = model.base_color
    return out


class KernelOptimiser:
    """Adam on attributes + Riemannian SGD on centres for one model; state resizable by rows.

    With ``face_frames`` (the spectra's per-face u_ref, on the model's device) a centre that
    changes face keeps its long axis in 3-D: the axis is parallel-transported along the step's
    path and theta re-expressed in the end face (:func:`theta_in_faces`), in place, so Adam's
    rows stay attached. Theta's Adam moments are kept: a change of reference direction shifts
    theta by a constant (and a fold by pi), which leaves d/dtheta, i.e. the rotation of the
    axis about the normal, unchanged; only where the transport reverses the sense of rotation
    (faces wound the other way) the first moment's row changes sign. Without ``face_frames``
    theta stays a number (the behaviour for callers that have no frames).
    """

    def __init__(
        self,
        model: torch.nn.Module,
        params: FitParams,
        tracer: Tracer,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        momentum: float | None = None,
        face_frames: torch.Tensor | None = None,
    ) -> None:
        self.model = model
        self.params = params
        self.vertices = vertices
        self.faces = faces
        self.face_frames = face_frames
        self.face_normals = None
        if face_frames is not None:
            if not hasattr(tracer, "trace_full"):
                raise TypeError("face_frames need a tracer with trace_full(..., transport=)")
            self.face_normals = face_unit_normals(vertices.to(torch.float64), faces.to(torch.long))
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
        if step_index < self.params.priority_start * self.params.steps:
            attrs.pop("priority", None)  # footprints first, layers after (FitParams)
        if step_index < self.params.sigma_start * self.params.steps:
            attrs.pop("log_sigma", None)  # likewise a per-kernel sigma (FitParams)
        if step_index < self.params.slope_start * self.params.steps:
            attrs.pop("color_slopes", None)  # and linear colours' slopes
        self.adam.step(attrs, scale)
        self.model.project_()  # attributes back into their boxes (ALGORITHM.md 4)
        gb = self.model.bary.grad
        if gb is not None:
            f0 = self.model.face_ids
            g = tangent_gradient(self.vertices, self.faces, f0, gb)
            if self.face_frames is None:
                f, b = self.centres.step(f0, self.model.bary, g, scale)
            else:
                axes = axis_pair(self.face_frames, self.face_normals, f0, self.model.theta)
                f, b, moved = self.centres.step_transporting(f0, self.model.bary, g, axes, scale)
                self._reorient(f0, f, moved)
            self.model.set_centres(f, b)

    @torch.no_grad()
    def _reorient(self, f0: torch.Tensor, f1: torch.Tensor, axes: torch.Tensor) -> None:
        """Re-express theta of centres that changed face; keep Adam's rows meaningful.

        Only rows whose face changed are touched: inside one face transport is the identity,
        so theta there is already right and stays bit-identical. (A path that leaves its face
        and comes back within one step could pick up holonomy around a vertex; steps are far
        shorter than a face, so this is ignored.)
        """
        changed = torch.nonzero(f1 != f0).squeeze(1)
        if changed.numel() == 0:
            return
        theta = self.model.theta
        new, reversed_ = theta_in_faces(
            self.face_frames, self.face_normals, f1[changed], axes[changed], theta[changed]
        )
        theta.index_copy_(0, changed, new.to(theta.dtype))
        st = self.adam.state.get("theta")
        if st is not None and bool(reversed_.any()):
            flip = changed[reversed_]
            st.exp_avg.index_copy_(0, flip, -st.exp_avg[flip])

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
