"""Small measured probes behind docs/fitting.md, 'Why the CPU fits fall short (investigation)'.

Spot with a reduced 3 x 2 x 64 grid (spectra cached under --cache), one torch thread, each probe
well under 3 minutes on one core:

    python benchmarks/uv_fit_probe.py init                # footprint coverage at initialisation
    python benchmarks/uv_fit_probe.py grad                # gradient sizes after one batch
    python benchmarks/uv_fit_probe.py prune               # what prune would remove at init
    python benchmarks/uv_fit_probe.py target              # fit targets == surface-PSNR targets
    python benchmarks/uv_fit_probe.py fit '{"densify": false}'   # FitParams overrides (JSON)
    python benchmarks/uv_fit_probe.py fit '{}' --variant clone-offset   # A/B of density control

``--variant`` patches density control for one run (an experiment, not a product option):
``clone-offset`` traces each clone (1 - eps) * 0.2 along its long axis, one random side,
as split children are traced (the parent stays); ``no-prune`` skips prune events.

Fits default to 2000 -> 4000 kernels, 300 steps, 20,000 evaluation points.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

import hktex_engine.fitting.density as density
from hktex_engine.config import FitParams, SpectralConfig
from hktex_engine.evaluation.metrics import psnr, surface_samples
from hktex_engine.fitting.optimise import axis_pair, tangent_gradient, trace_on_surface
from hktex_engine.fitting.uv import UVObjective, fit_uv, initial_kernelset
from hktex_engine.geometry.mesh import load_mesh
from hktex_engine.geometry.sampling import points_from_barycentric, sample_surface
from hktex_engine.kernels.model import HeatKernelModel
from hktex_engine.spectra.grid import compute_spectra, load_spectra, write_spectra
from hktex_engine.spectra.interpolation import SpectralField

SPOT = Path(__file__).resolve().parents[2] / "shared" / "data" / "spot"
GRID = SpectralConfig(angles=3, anisotropies=(1.0, 30.0), k=64, k_iso=65)


def setup(cache: Path):
    mesh = load_mesh(SPOT / "spot_triangulated.obj", texture=SPOT / "spot_texture.png")
    if not cache.exists():
        write_spectra(compute_spectra(mesh, GRID), cache)
    return mesh, load_spectra(cache)


def initial_model(mesh, spectra, n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    ks = initial_kernelset(mesh, spectra, FitParams(kernels=n), rng)
    return ks, HeatKernelModel.from_kernelset(ks, SpectralField(spectra, device="cpu")), rng


def centres(spectra, ks) -> np.ndarray:
    v, f = np.asarray(spectra.vertices), np.asarray(spectra.faces)
    return points_from_barycentric(v, f, ks.face_ids, ks.barycentrics)


def probe_init(mesh, spectra, n: int) -> None:
    """How much of the surface the initial kernels cover (sum of rho) and the init PSNR."""
    ks, model, _ = initial_model(mesh, spectra, n)
    f, b, tgt = surface_samples(mesh, 20000, 0)
    with torch.no_grad():
        fb = (torch.as_tensor(f), torch.as_tensor(b, dtype=model.field.dtype))
        pred, aux = model.albedo(*fb, return_aux=True)
    rs = aux["rho"].sum(1).numpy()
    base_only = psnr(np.broadcast_to(ks.base_color, tgt.shape), tgt)
    print(f"init PSNR {psnr(pred.numpy(), tgt):.2f} dB, base colour only {base_only:.2f} dB")
    for thr in (1e-3, 1e-2, 0.1, 0.5):
        print(f"fraction of points with sum rho < {thr}: {(rs < thr).mean():.3f}")
    v, fc = np.asarray(spectra.vertices), np.asarray(spectra.faces)
    c = centres(spectra, ks)
    _, nn = cKDTree(c).query(points_from_barycentric(v, fc, f, b))
    nearest = np.clip(ks.base_color + ks.colors[nn], 0, 1)
    print(
        f"median sum rho {np.median(rs):.2f}; nearest-centre colour PSNR {psnr(nearest, tgt):.2f}"
    )


def probe_grad(mesh, spectra, n: int) -> None:
    """Gradient sizes per attribute after one 512-point batch, and the centre step they give."""
    _, model, rng = initial_model(mesh, spectra, n)
    obj = UVObjective(mesh, 512, torch.device("cpu"), model.field.dtype)
    loss, _ = obj.loss(model, obj.sample(0, rng))
    loss.backward()
    for name in ("colors", "theta", "s", "threshold", "sharpness", "bary"):
        g = getattr(model, name).grad.abs().reshape(n, -1).amax(1)
        print(
            f"{name:10s} rows with gradient {(g > 0).double().mean():.3f}, "
            f"median |g| {g[g > 0].median():.2e}"
        )
    v = torch.as_tensor(np.array(spectra.vertices))
    g = tangent_gradient(
        v,
        torch.as_tensor(np.array(spectra.faces)),
        model.face_ids,
        model.bary.grad.to(torch.float64),
    ).norm(dim=1)
    step = FitParams().lr_centers * g[g > 0]
    print(f"centre step lr_centers*|g|: median {step.median():.2e}, max {step.max():.2e}")


def probe_prune(mesh, spectra, n: int) -> None:
    """Fractions prune would remove at init after windows of 15 and 150 steps."""
    _, model, rng = initial_model(mesh, spectra, n)
    hits = torch.zeros(n, dtype=torch.float64)
    rho_sum = torch.zeros(n, dtype=torch.float64)
    for step in range(150):
        f, b = sample_surface(mesh.vertices, mesh.faces, 512, rng)
        with torch.no_grad():
            fb = (torch.as_tensor(f), torch.as_tensor(b, dtype=model.field.dtype))
            _, aux = model.albedo(*fb, return_aux=True)
        rho = aux["rho"].to(torch.float64)
        idx = aux["indices"].reshape(-1)
        hits.index_add_(0, idx, (rho > 0).reshape(-1).double())
        rho_sum.index_add_(0, idx, rho.reshape(-1))
        if step + 1 in (15, 150):
            low_hits = hits < 0.02 * hits.max()
            low_c = rho_sum / hits.clamp_min(1) < 0.07
            print(
                f"window {step + 1} steps: by hits {low_hits.double().mean():.3f}, by "
                f"contribution {low_c.double().mean():.3f}, either "
                f"{(low_hits | low_c).double().mean():.3f}"
            )


def probe_target(mesh) -> None:
    """The fit's targets and the surface-PSNR protocol's are the same lookup."""
    f, b, t = surface_samples(mesh, 4096, 0)
    fo, bo, to = UVObjective(mesh, 4096, torch.device("cpu"), torch.float32).sample(
        0, np.random.default_rng(0)
    )
    print(
        f"same faces {np.array_equal(f, fo.numpy())}, max target difference "
        f"{np.abs(t - to.numpy()).max():.1e}"
    )


def probe_fit(mesh, spectra, overrides: dict) -> None:
    """One fit with FitParams overrides; PSNR, kernel counts and near-duplicate centres."""
    kw = {"kernels": 2000, "max_kernels": 4000, "steps": 300, "checkpoint_every": 0}
    kw.update(overrides)
    t0 = time.perf_counter()
    r = fit_uv(mesh, spectra, FitParams(**kw), eval_points=20000)
    m = r.metrics
    d, _ = cKDTree(centres(spectra, r.kernelset)).query(centres(spectra, r.kernelset), k=2)
    print(
        f"{json.dumps(overrides)}: init {m['surface_psnr_initial']:.2f} final "
        f"{m['surface_psnr']:.2f} dB, kernels {m['kernels_initial']}->{m['kernels']}, "
        f"centres with another within 1e-3: {(d[:, 1] < 1e-3).mean():.3f}, "
        f"{time.perf_counter() - t0:.0f} s"
    )


def patch_density(variant: str) -> None:
    """Swap one density-control step for the A/B runs of the investigation."""
    if variant == "no-prune":
        density.DensityController._prune = lambda self, model, opt: False
    elif variant == "clone-offset":
        exact = density.DensityController.new_rows

        def offset_clones(self, model, clone, split):
            out = exact(self, model, clone, split)
            nc = clone.numel()
            if nc == 0:
                return out
            f, b = model.face_ids.detach()[clone], model.bary.detach()[clone]
            eps = model.threshold.detach()[clone]
            axes = axis_pair(self.face_frames, self.face_normals, f, model.theta.detach()[clone])
            gen = torch.Generator().manual_seed(nc)
            sign = torch.where(torch.rand(nc, generator=gen) < 0.5, -1.0, 1.0).to(axes.dtype)
            length = (1.0 - eps).to(axes.dtype) * self.rules.split_offset * sign
            end_f, end_b, _ = trace_on_surface(self.tracer, f, b, length[:, None] * axes[:, 0])
            out["face_ids"], out["bary"] = out["face_ids"].clone(), out["bary"].clone()
            out["face_ids"][:nc], out["bary"][:nc] = end_f, end_b.to(out["bary"].dtype)
            return out

        density.DensityController.new_rows = offset_clones


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("probe", choices=("init", "grad", "prune", "target", "fit"))
    ap.add_argument("overrides", nargs="?", default="{}", help="FitParams JSON (fit)")
    ap.add_argument("--kernels", type=int, default=2000)
    ap.add_argument("--cache", type=Path, default=Path("/tmp/hktex_probe_spot_3x2x64"))
    ap.add_argument("--variant", choices=("clone-offset", "no-prune"), default=None)
    args = ap.parse_args(argv)
    if args.variant:
        patch_density(args.variant)
    torch.set_num_threads(1)
    mesh, spectra = setup(args.cache)
    if args.probe == "init":
        probe_init(mesh, spectra, args.kernels)
    elif args.probe == "grad":
        probe_grad(mesh, spectra, args.kernels)
    elif args.probe == "prune":
        probe_prune(mesh, spectra, args.kernels)
    elif args.probe == "target":
        probe_target(mesh)
    else:
        probe_fit(mesh, spectra, json.loads(args.overrides))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
