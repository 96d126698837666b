"""Density control: prune idle kernels, clone or split busy ones (ALGORITHM.md section 7).

Schedules are fractions of the total steps T. Statistics are gathered over a window before
each event (reference 0.05 T) and reset after every event of the same kind: densify events
come every 0.04 T, so its effective window is the 0.04 T since the previous densify (the
kernel rows changed at that event; older statistics describe kernels that no longer exist).
Any resize (by either kind of event) carries every accumulator's rows along: survivors keep
their statistics, newcomers start at zero.

All decisions are vectorised over kernels: masks, argsorts and one batched exponential-map
trace for the split children.
"""

from __future__ import annotations

import numpy as np
import torch

from hktex_engine.config import DensityRules, FitParams
from hktex_engine.fitting.optimise import (
    KERNEL_ATTRIBUTES,
    KernelOptimiser,
    Tracer,
    axis_pair,
    face_unit_normals,
    theta_in_faces,
    trace_on_surface,
    trace_transporting,
)


def schedule(total: int, start: float, until: float, every: float) -> list[int]:
    """Event steps (1-based step counts after which to act) for fractions of ``total``."""
    if total <= 0 or every <= 0:
        return []
    fr = np.arange(start, until + 1e-9, every)
    steps = sorted({int(round(f * total)) for f in fr})
    return [s for s in steps if 0 < s < total]


def prune_mask(hits: torch.Tensor, contribution: torch.Tensor, rules: DensityRules) -> torch.Tensor:
    """True for kernels to remove; never leaves fewer than ``rules.floor`` kernels.

    A kernel goes if its hits are below 2 % of the busiest kernel's or its mean contribution
    is below 0.07. When that would cross the floor, only the least-hit ones go.
    """
    n = hits.shape[0]
    remove = (hits < rules.min_hits_fraction * hits.max().clamp_min(0)) | (
        contribution < rules.min_contribution
    )
    allowed = max(0, n - rules.floor)
    if int(remove.sum()) <= allowed:
        return remove
    # rank candidates by hits then contribution (ascending); keep the rest
    key = hits.to(torch.float64) + contribution.to(torch.float64).clamp(0, 1) * 0.5
    key = torch.where(remove, key, torch.full_like(key, float("inf")))
    order = torch.argsort(key, stable=True)
    out = torch.zeros(n, dtype=torch.bool, device=hits.device)
    out[order[:allowed]] = True
    return out


def densify_selection(
    mean_error: torch.Tensor, threshold: torch.Tensor, n_budget: int, rules: DensityRules
) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices of kernels to clone and to split this round.

    Candidates have a mean error above the threshold, highest first; at most
    ``max_growth`` x the current count and never past the budget. Each chosen kernel adds
    exactly one kernel (a clone, or two children replacing the parent). Size proxy 1 - eps:
    large kernels split, small ones clone.
    """
    n = mean_error.shape[0]
    cap = min(int(rules.max_growth * n), max(0, n_budget - n))
    cand = torch.nonzero(mean_error > rules.error_threshold).squeeze(1)
    if cap <= 0 or cand.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=mean_error.device)
        return empty, empty
    order = torch.argsort(mean_error[cand], descending=True, stable=True)
    chosen = cand[order[:cap]]
    big = (1.0 - threshold[chosen]) > rules.split_size
    return chosen[~big], chosen[big]


@torch.no_grad()
def resize_model(model: torch.nn.Module, keep: torch.Tensor, new_rows: dict) -> None:
    """Keep rows ``keep`` (in order) and append ``new_rows`` (raw attribute names, as
    :data:`~hktex_engine.fitting.optimise.KERNEL_ATTRIBUTES`), through the model's own select/append."""
    model.select(keep)
    if int(new_rows["face_ids"].shape[0]) == 0:
        return
    model.append(
        new_rows["face_ids"],
        new_rows["bary"],
        new_rows["theta"],
        torch.expm1(new_rows["s"]),  # append takes eta in natural units
        new_rows["threshold"],
        new_rows["sharpness"],
        new_rows["colors"],
        new_rows["priority"],
        new_rows["log_sigma"],
        new_rows["color_slopes"],
    )


@torch.no_grad()
def load_rows(model: torch.nn.Module, rows: dict[str, torch.Tensor]) -> None:
    """Replace every kernel row with ``rows`` exactly (bit for bit; used by resume)."""
    n = int(rows["face_ids"].shape[0])
    model.select(torch.zeros(n, dtype=torch.long, device=model.face_ids.device))
    for name in KERNEL_ATTRIBUTES[2:]:
        getattr(model, name).copy_(rows[name])
    model.set_centres(rows["face_ids"], rows["bary"])


class DensityController:
    """Gathers per-kernel statistics and applies the prune / densify schedule."""

    def __init__(
        self,
        params: FitParams,
        total: int,
        vertices: torch.Tensor,
        faces: torch.Tensor,
        face_frames: torch.Tensor,
        tracer: Tracer,
        rules: DensityRules | None = None,
        transport_theta: bool = False,
    ) -> None:
        self.rules = rules or params.density
        self.transport_theta = bool(transport_theta)
        r = self.rules
        self.enabled = bool(params.densify)
        self.budget = int(params.budget)
        self.total = int(total)
        if r.prune_at:
            self.prune_steps = sorted({int(round(f * total)) for f in r.prune_at} - {0, total})
        else:
            self.prune_steps = schedule(total, r.prune_from, r.prune_until, r.prune_every)
        self.densify_steps = schedule(total, r.densify_from, r.densify_until, r.densify_every)
        self.window = max(1, int(round(r.window * total)))
        self.faces = faces
        self.vertices = vertices
        self.face_frames = face_frames
        self.face_normals = face_unit_normals(vertices, faces)
        self.tracer = tracer
        self.step = 0  # steps completed
        self._n = 0  # current kernel count (bind / act keep it current)
        self.acc: dict[str, torch.Tensor] = {}
        self.window_steps = {"prune": 0, "densify": 0}  # steps recorded since the last event
        self.events: list[dict] = []

    # --- statistics ---------------------------------------------------------------------

    def _next(self, steps: list[int]) -> int | None:
        for s in steps:
            if s > self.step:
                return s
        return None

    def _collecting(self, steps: list[int]) -> bool:
        nxt = self._next(steps)
        return self.enabled and nxt is not None and self.step + 1 > nxt - self.window

    def _ensure(self, n: int, device: torch.device) -> None:
        for key in ("hits", "rho_sum", "err_sum", "err_weight"):
            t = self.acc.get(key)
            if t is None or t.shape[0] != n:
                self.acc[key] = torch.zeros(n, dtype=torch.float64, device=device)

    @torch.no_grad()
    def record(self, stats) -> None:
        """Accumulate one step's per-point stats (``fitting.PointStats``) into kernel rows."""
        prune_on, dens_on = self._collecting(self.prune_steps), self._collecting(self.densify_steps)
        if not (prune_on or dens_on):
            return
        n = self.n_kernels
        self._ensure(n, stats.rho.device)
        idx = stats.topk.reshape(-1)
        rho = stats.rho.detach().to(torch.float64).reshape(stats.topk.shape)
        valid = (stats.topk >= 0) & (rho > 0)
        safe = idx.clamp_min(0)
        # importance weights (error sampling): every sum below estimates the uniform one
        pw = (
            torch.ones_like(rho[:, :1])
            if stats.weights is None
            else stats.weights.detach().to(torch.float64).reshape(-1, 1)
        )
        if prune_on:
            self.window_steps["prune"] += 1
            self.acc["hits"].index_add_(0, safe, (valid * pw).reshape(-1))
            self.acc["rho_sum"].index_add_(0, safe, (rho * valid * pw).reshape(-1))
        if dens_on:
            self.window_steps["densify"] += 1
            # each point's L1 error spread over its final kernels by normalised contributions
            w = rho * valid
            w = w / w.sum(dim=1, keepdim=True).clamp_min(1e-30)
            err = stats.l1_error.detach().to(torch.float64)[:, None] * w
            self.acc["err_sum"].index_add_(0, safe, (err * pw).reshape(-1))
            self.acc["err_weight"].index_add_(0, safe, (w * pw).reshape(-1))

    @property
    def n_kernels(self) -> int:
        return int(self._n)

    def bind(self, model: torch.nn.Module) -> None:
        self._n = int(model.face_ids.shape[0])

    # --- events -------------------------------------------------------------------------

    def act(self, step: int, model: torch.nn.Module, opt: KernelOptimiser) -> bool:
        """Run the events scheduled after ``step`` completed steps; True if kernels changed."""
        self.step = step
        self._n = int(model.face_ids.shape[0])
        if not self.enabled:
            return False
        changed = False
        if step in self.prune_steps:
            changed |= self._prune(model, opt)
            for key in ("hits", "rho_sum"):
                self.acc.pop(key, None)
            self.window_steps["prune"] = 0
        if step in self.densify_steps:
            changed |= self._densify(model, opt)
            for key in ("err_sum", "err_weight"):
                self.acc.pop(key, None)
            self.window_steps["densify"] = 0
        self._n = int(model.face_ids.shape[0])
        return changed

    def _resize(self, model, opt, keep: torch.Tensor, new_rows: dict, kind: str) -> None:
        n_new = int(new_rows["face_ids"].shape[0])
        n_before = int(model.face_ids.shape[0])
        resize_model(model, keep, new_rows)
        opt.resize(keep, n_new)
        for key, t in list(self.acc.items()):
            zeros = torch.zeros(n_new, dtype=t.dtype, device=t.device)
            self.acc[key] = torch.cat([t[keep], zeros])
        self._n = int(model.face_ids.shape[0])
        self.events.append({"step": self.step, "kind": kind, "before": n_before, "after": self._n})

    @torch.no_grad()
    def _prune(self, model, opt) -> bool:
        n = int(model.face_ids.shape[0])
        device = model.face_ids.device
        if "hits" not in self.acc or self.acc["hits"].shape[0] != n:
            return False
        hits = self.acc["hits"]
        if self.rules.stats == "step_sum":  # §7b: per-step sum, averaged over the window
            contribution = self.acc["rho_sum"] / max(1, self.window_steps["prune"])
        else:
            contribution = self.acc["rho_sum"] / hits.clamp_min(1.0)
        remove = prune_mask(hits, contribution, self.rules)
        if not bool(remove.any()):
            return False
        keep = torch.nonzero(~remove).squeeze(1)
        empty = {name: getattr(model, name)[:0].detach() for name in KERNEL_ATTRIBUTES}
        self._resize(model, opt, keep.to(device), empty, "prune")
        return True

    @torch.no_grad()
    def _densify(self, model, opt) -> bool:
        n = int(model.face_ids.shape[0])
        if "err_sum" not in self.acc or self.acc["err_sum"].shape[0] != n:
            return False
        if self.rules.stats == "step_sum":  # §7b: error mass per step over the window
            mean_err = self.acc["err_sum"] / max(1, self.window_steps["densify"])
        else:
            mean_err = self.acc["err_sum"] / self.acc["err_weight"].clamp_min(1e-30)
            mean_err = torch.where(self.acc["err_weight"] > 0, mean_err, torch.zeros_like(mean_err))
        clone, split = densify_selection(
            mean_err, model.threshold.detach(), self.budget, self.rules
        )
        if clone.numel() == 0 and split.numel() == 0:
            return False
        new_rows = self.new_rows(model, clone, split)
        keep_mask = torch.ones(n, dtype=torch.bool, device=model.face_ids.device)
        keep_mask[split] = False
        keep = torch.nonzero(keep_mask).squeeze(1)
        self._resize(model, opt, keep, new_rows, "densify")
        return True

    @torch.no_grad()
    def new_rows(self, model, clone: torch.Tensor, split: torch.Tensor) -> dict:
        """Rows for clones (exact copies) and split children (two per parent, traced apart).

        Children keep their parent's theta by default: the parent's kernel is shaped by the
        global field at angle theta from every face's u_ref, so the same number orients each
        child like the parent's footprint where the child lands. With ``transport_theta`` a
        child that lands in another face instead gets its parent's long axis
        parallel-transported along its path and theta re-expressed against that face's u_ref
        (``optimise.theta_in_faces``). Children start with zero optimiser state either way.
        """
        rows = {name: getattr(model, name).detach() for name in KERNEL_ATTRIBUTES}
        out = {name: t[clone] for name, t in rows.items()}
        if split.numel() == 0:
            return out
        eps = rows["threshold"][split]
        f, b = rows["face_ids"][split], rows["bary"][split]
        theta = rows["theta"][split]
        axes = axis_pair(self.face_frames, self.face_normals, f, theta)  # (S, 2, 3) float64
        offset = ((1.0 - eps) * self.rules.split_offset).to(axes.dtype)[:, None] * axes[:, 0]
        f2, axes2, theta2 = torch.cat([f, f]), torch.cat([axes, axes]), torch.cat([theta, theta])
        offsets = torch.cat([offset, -offset])
        if self.transport_theta:
            end_f, end_b, _, end_axes = trace_transporting(
                self.tracer, f2, torch.cat([b, b]), offsets, axes2
            )
        else:
            end_f, end_b, _ = trace_on_surface(self.tracer, f2, torch.cat([b, b]), offsets)
        children = {name: torch.cat([t[split], t[split]]) for name, t in rows.items()}
        children["face_ids"] = end_f
        children["bary"] = end_b.to(rows["bary"].dtype)
        moved = torch.nonzero(end_f != f2).squeeze(1)
        if self.transport_theta and moved.numel():
            new_theta, _ = theta_in_faces(
                self.face_frames, self.face_normals, end_f[moved], end_axes[moved], theta2[moved]
            )
            children["theta"] = children["theta"].clone()
            children["theta"][moved] = new_theta.to(children["theta"].dtype)
        shrunk = 1.0 - (1.0 - eps) / self.rules.split_shrink
        children["threshold"] = torch.cat([shrunk, shrunk])
        return {name: torch.cat([out[name], children[name]]) for name in out}

    # --- checkpoint support ------------------------------------------------------------

    def state_arrays(self) -> dict[str, np.ndarray]:
        return {f"density.{k}": v.detach().cpu().numpy() for k, v in self.acc.items()}

    def state_meta(self) -> dict:
        return {"step": self.step, "events": self.events, "window_steps": self.window_steps}

    def load_state(self, arrays: dict, meta: dict, device: torch.device) -> None:
        self.acc = {
            k.split(".", 1)[1]: torch.as_tensor(v, device=device)
            for k, v in arrays.items()
            if k.startswith("density.")
        }
        self.step = int(meta["step"])
        self.events = list(meta.get("events", []))
        self.window_steps = dict(meta.get("window_steps", {"prune": 0, "densify": 0}))
