"""The colour at a point from its chosen kernels: ALGORITHM.md §5's blend and our layered one.

``paper`` (§5): ``albedo = clamp(a_0 + Σ_j ρ_j a_j / max(1, Σ_j ρ_j), 0, 1)``. Where kernels
overlap they average, so a small kernel lying on large ones that saturate (ρ = 1) gets only
``1 / n`` of the say: measured on blub's eyes and the torus's straight edges, where the MLP
baseline draws what our sets blur (docs/fitting.md).

``layered`` (our extension, a ``blend`` of ``KernelConfig``): each kernel also has a priority
``β_j`` (in :data:`PRIORITY_RANGE`), and

    ω_j = ρ_j exp(β_j − max_c β_c)
    albedo = clamp(a_0 + min(1, Σ_j ρ_j) Σ_j ω_j a_j / Σ_j ω_j, 0, 1)      (a_0 where Σ ω = 0)

With equal priorities it is the paper's blend exactly (``min(1, S) / S = 1 / max(1, S)``);
a kernel whose priority is higher by Δ outweighs ``exp(Δ)`` saturated ones, so where it
overlaps them its own level set draws the edge. Coverage (how much of ``a_0`` shows) is the
paper's ``min(1, Σ ρ)``; only the shares among the covering kernels change. The ``K_c``
choice is untouched: still the largest ρ under the tie rule. Subtracting the point's largest
priority keeps ``exp`` below 1 (it cancels in the ratio).

Both rules are linear in the colours for fixed footprints (the colour solve uses
:func:`weights`).

Measured (docs/fitting.md, tenth pass): it wins on hard-edged patches (spot +3.8 dB, the
torus +1.3) and loses on small eyes (blub −2 to −3.4 dB), so the paper's blend stays the
default and this one is an option.
"""

from __future__ import annotations

import torch

#: The priority's box: exp(16) ~ 9e6 separates any two layers far past K_c saturated kernels.
PRIORITY_RANGE = (-8.0, 8.0)


def weights(rho: torch.Tensor, priority: torch.Tensor | None) -> torch.Tensor:
    """(P, K_c) blend weights ``w`` with ``albedo = clamp(a_0 + Σ w_j a_j, 0, 1)``.

    ``priority`` (P, K_c) are the chosen kernels' ``β`` (None: the paper's blend).
    """
    total = rho.sum(dim=1, keepdim=True)
    if priority is None:
        return rho / torch.clamp(total, min=1.0)
    omega = rho * torch.exp(priority - priority.max(dim=1, keepdim=True).values)
    mass = omega.sum(dim=1, keepdim=True)
    share = torch.where(mass > 0, omega / torch.where(mass > 0, mass, 1.0), 0.0)
    return torch.clamp(total, max=1.0) * share


def albedo(
    rho: torch.Tensor, colors: torch.Tensor, base: torch.Tensor, priority: torch.Tensor | None
) -> torch.Tensor:
    """(P, 3) colours from the chosen kernels' ``rho`` (P, K_c), ``colors`` (P, K_c, 3).

    The paper's blend keeps §5's own order of operations (sum, then one division), which the
    compiled paths reproduce.
    """
    if priority is None:
        weighted = torch.einsum("pc,pcd->pd", rho, colors)
        denom = torch.clamp(rho.sum(dim=1, keepdim=True), min=1.0)
        return torch.clamp(base[None, :] + weighted / denom, 0.0, 1.0)
    w = weights(rho, priority)
    return torch.clamp(base[None, :] + torch.einsum("pc,pcd->pd", w, colors), 0.0, 1.0)
