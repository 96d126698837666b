"""How elongated a kernel's footprint can be where a texture's small features are.

    python benchmarks/footprint_shape.py --mesh blub [--k 128] [--out benchmarks/results]

A feature of the texture (a connected dark region: blub's eyes) is an ellipse of some aspect
ratio. One kernel can draw it with one sharp edge only if its footprint can take that shape.
The footprint is ``S(r)`` with ``r = h w / h(c)`` (ALGORITHM.md section 4). The anisotropy
lives in the heat kernel ``h``, whose width is set by the diffusion time. The biharmonic
decay ``w`` is isotropic and bounds the footprint's radius by ``sigma_B``.

So this measures, at the centre of each of the mesh's largest dark features:

- the feature's aspect ratio and semi-axes (second moments of area-uniform points, 3-D);
- a single kernel's footprint (``rho > 0.5``, sharpness 200) for anisotropy ``eta`` 1, 30,
  200 and thresholds 0.3 and 0.5, at the default's sigma_B and wider ones (``inf``: the heat
  kernel alone). The feature's long axis sets theta, so the footprint has its best chance.

Second moments: a uniform ellipse of semi-axes ``a >= b`` has variances ``a^2/4`` and
``b^2/4``, so ``2 sqrt(var)`` is the semi-axis. Used in docs/fitting.md's thirteenth pass.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import torch
from _machine import machine_info, machine_line
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from hktex_engine.config import DEFAULT_SIGMA_B, fit_preset
from hktex_engine.evaluation.metrics import surface_samples
from hktex_engine.fitting.optimise import face_unit_normals, theta_in_faces
from hktex_engine.geometry.sampling import points_from_barycentric
from hktex_engine.kernels.model import HeatKernelModel
from hktex_engine.spectra.interpolation import SpectralField

#: texels darker than this (mean RGB) make up the features
DARK = 0.12
#: sample points closer than this (3-D, normalised mesh) belong to one feature
LINK = 0.01
#: stands for sigma_B = inf: w = 1 everywhere on a normalised mesh (d_B is below ~1 there)
INFINITE_SIGMA_B = 1e6


def shape(points: np.ndarray) -> tuple[dict, np.ndarray]:
    """Aspect ratio and semi-axes of a planar-ish point cloud from its second moments, and
    its long axis (3-D unit vector)."""
    q = points - points.mean(0)
    var, vecs = np.linalg.eigh(q.T @ q / len(q))  # ascending
    long, short = var[2], var[1]
    summary = {
        "points": len(points),
        "aspect": float(np.sqrt(long / max(short, 1e-300))),
        "semi_axes": [float(2 * np.sqrt(long)), float(2 * np.sqrt(short))],
    }
    return summary, vecs[:, 2]


def features(pts: np.ndarray, dark: np.ndarray, count: int) -> list[np.ndarray]:
    """Indices (into ``pts``) of the ``count`` largest connected dark regions."""
    idx = np.flatnonzero(dark)
    pairs = cKDTree(pts[idx]).query_pairs(LINK, output_type="ndarray")
    n = len(idx)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    return [idx[label == c] for c in np.argsort(np.bincount(label))[::-1][:count]]


def theta_along(spectra, mesh, face: int, axis: np.ndarray) -> float:
    """The kernel angle in ``face`` of the direction ``axis`` (projected into the face),
    measured from the spectra's ``u_ref`` as the fit measures it (``theta_in_faces``)."""
    dt = torch.float64
    normals = face_unit_normals(
        torch.as_tensor(np.asarray(mesh.vertices), dtype=dt),
        torch.as_tensor(np.asarray(mesh.faces)),
    )
    n = normals[face]
    a = torch.as_tensor(axis, dtype=dt)
    a = a - (a @ n) * n
    a = a / a.norm()
    axes = torch.stack([a, torch.linalg.cross(n, a, dim=-1)])[None]  # (1, 2, 3)
    frames = torch.as_tensor(np.asarray(spectra.face_frames), dtype=dt)
    face_ids = torch.tensor([face])
    theta, _ = theta_in_faces(frames, normals, face_ids, axes, torch.zeros(1, dtype=dt))
    return float(theta[0])


def footprint(model_args: dict, field, f, b, pts) -> dict:
    """Shape of one kernel's ``rho > 0.5`` region over the sample points ``f, b, pts``."""
    model = HeatKernelModel(field, **model_args)
    with torch.no_grad():
        cand = torch.zeros((len(f), 1), dtype=torch.long)
        rho = model.responses(torch.as_tensor(f), torch.as_tensor(b, dtype=field.dtype), cand)[0]
    inside = rho.numpy()[:, 0] > 0.5
    return shape(pts[inside])[0] if inside.sum() > 10 else {"points": int(inside.sum())}


def main() -> int:
    sys.path.insert(0, str(Path(__file__).parent))
    from fidelity import add_mesh_file_argument, named_mesh_and_spectra

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", default="blub", help="a shared mesh or a --mesh-file name")
    add_mesh_file_argument(ap)
    ap.add_argument("--k", type=int, default=128)
    ap.add_argument("--features", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    args = ap.parse_args()

    mesh, spectra = named_mesh_and_spectra(args.mesh_file, args.mesh, args.k)
    field = SpectralField(spectra)
    f, b, target = surface_samples(mesh, 400_000, 1)
    pts = points_from_barycentric(mesh.vertices, mesh.faces, f, b)
    kernel = fit_preset("default").kernel
    rows = []
    for n, members in enumerate(features(pts, target.mean(1) < DARK, args.features)):
        feat, long_axis = shape(pts[members])
        centre = members[np.argmin(np.linalg.norm(pts[members] - pts[members].mean(0), axis=1))]
        near = np.flatnonzero(np.linalg.norm(pts - pts[centre], axis=1) < 4 * feat["semi_axes"][0])
        theta = theta_along(spectra, mesh, int(f[centre]), long_axis)
        for sigma_b in (DEFAULT_SIGMA_B, 0.05, float("inf")):
            for threshold in (0.3, 0.5):
                for eta in (1.0, 30.0, 200.0):
                    config = replace(
                        kernel,
                        sigma_b=INFINITE_SIGMA_B if np.isinf(sigma_b) else sigma_b,
                        k_search=1,
                        k_blend=1,
                    )
                    model_args = dict(
                        face_ids=np.array([f[centre]]),
                        bary=b[centre : centre + 1],
                        theta=np.array([theta]),
                        eta=np.array([eta]),
                        threshold=np.array([threshold]),
                        sharpness=np.array([200.0]),
                        colors=np.ones((1, 3)),
                        base_color=np.zeros(3),
                        config=config,
                    )
                    fp = footprint(model_args, field, f[near], b[near], pts[near])
                    rows.append(
                        {
                            "feature": n,
                            "feature_shape": feat,
                            "sigma_b": sigma_b,
                            "threshold": threshold,
                            "eta": eta,
                            "footprint": fp,
                        }
                    )
                    print(
                        f"feature {n} (aspect {feat['aspect']:.2f}, semi-axes "
                        f"{feat['semi_axes'][0]:.3f} x {feat['semi_axes'][1]:.3f}) sigma_B "
                        f"{sigma_b:g} eps {threshold} eta {eta:g}: footprint aspect "
                        f"{fp.get('aspect', float('nan')):.2f}, semi-axes "
                        f"{fp.get('semi_axes', [float('nan')] * 2)[0]:.3f} x "
                        f"{fp.get('semi_axes', [float('nan')] * 2)[1]:.3f}",
                        flush=True,
                    )
    command = "python " + " ".join(shlex.quote(a) for a in sys.argv)
    args.out.mkdir(parents=True, exist_ok=True)
    stem = args.out / f"footprint_shape_{args.mesh}"
    record = {
        "command": command,
        "machine": machine_info(),
        "diffusion_time": kernel.diffusion_time,
        "spectra_k": args.k,
        "rows": rows,
    }
    stem.with_suffix(".json").write_text(json.dumps(record, indent=1, default=float))
    stem.with_suffix(".md").write_text(table(rows, command, record["machine"]))
    return 0


def table(rows: list[dict], command: str, machine: dict) -> str:
    """Markdown: one line per feature, sigma_B, threshold; eta across."""
    lines = [
        "# Footprint shape at a texture's small features (benchmarks/footprint_shape.py)",
        "",
        f"Command: `{command}`  ",
        f"Machine: {machine_line(machine)}",
        "",
        "One kernel at the feature's centre, its long axis along the feature's, sharpness 200; "
        "footprint = points with rho > 0.5; aspect = long / short semi-axis (3-D, normalised "
        "mesh). sigma_B inf = the heat kernel alone (t of the default preset).",
        "",
        "| feature (aspect, semi-axes) | sigma_B | threshold | eta 1 | eta 30 | eta 200 |",
        "|---|---:|---:|---|---|---|",
    ]
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["feature"], r["sigma_b"], r["threshold"]), []).append(r)
    for (n, sigma_b, threshold), group in groups.items():
        feat = group[0]["feature_shape"]
        cells = []
        for r in sorted(group, key=lambda r: r["eta"]):
            fp = r["footprint"]
            cells.append(
                f"{fp['aspect']:.2f} ({fp['semi_axes'][0]:.3f} x {fp['semi_axes'][1]:.3f})"
                if "aspect" in fp
                else "-"
            )
        lines.append(
            f"| {n} ({feat['aspect']:.2f}, {feat['semi_axes'][0]:.3f} x "
            f"{feat['semi_axes'][1]:.3f}) | {sigma_b:g} | {threshold} | " + " | ".join(cells) + " |"
        )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
