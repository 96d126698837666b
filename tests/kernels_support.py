"""Small spectra for the kernel tests (engineer "kernels").

``tiny_spectra`` uses the project's ``compute_spectra`` when it is available; otherwise it
builds an equivalent-shaped artefact by dense generalised eigendecomposition of a cotangent
Laplacian plus a smooth per-node potential, so the grid varies smoothly over (theta, s).
"""

from __future__ import annotations

import functools

import numpy as np
import scipy.linalg
import trimesh

from hktex_engine.config import KernelConfig, SpectralConfig
from hktex_engine.spectra.grid import Spectra

TINY_CONFIG = SpectralConfig(angles=3, anisotropies=(1.0, 10.0), k=16, k_iso=9)


def tiny_mesh(subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """A unit icosphere scaled to the normalised frame (largest bbox side 2)."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(sphere.vertices, dtype=np.float64)
    v = v - v.mean(axis=0)
    v = v * (2.0 / (v.max(axis=0) - v.min(axis=0)).max())
    return v, np.asarray(sphere.faces, dtype=np.int64)


def _operators(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    import igl

    stiffness = -igl.cotmatrix(v, f).toarray()
    mass = igl.massmatrix(v, f, igl.MASSMATRIX_TYPE_BARYCENTRIC).diagonal()
    return stiffness, mass


def _eig(a: np.ndarray, mass: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    vals, vecs = scipy.linalg.eigh(a, np.diag(mass), subset_by_index=[0, k - 1])
    return vals, vecs


def handmade_spectra(config: SpectralConfig = TINY_CONFIG, subdivisions: int = 2) -> Spectra:
    """Spectra of the shapes the real artefact has, from a dense eigensolver."""
    v, f = tiny_mesh(subdivisions)
    stiffness, mass = _operators(v, f)
    iso_vals, iso_vecs = _eig(stiffness, mass, config.k_iso)
    iso_vals[0] = 0.0
    grid_theta = np.linspace(0.0, np.pi, config.angles)
    grid_eta = np.asarray(config.anisotropies, dtype=np.float64)
    ref_vals, ref_vecs = _eig(stiffness, mass, config.k)
    evals, evecs = [], []
    for theta in grid_theta:
        direction = np.array([np.cos(theta), np.sin(theta), 0.3])
        for eta in grid_eta:
            potential = 2.0 * np.log1p(eta) * (v @ direction) ** 2
            vals, vecs = _eig(stiffness + np.diag(mass * potential), mass, config.k)
            # fix signs against the isotropic basis so neighbouring nodes interpolate sensibly
            corr = np.einsum("nk,n,nk->k", ref_vecs, mass, vecs)
            vecs = vecs * np.where(corr < 0, -1.0, 1.0)[None, :]
            evals.append(vals)
            evecs.append(vecs)
    p = v[f]
    u = p[:, 1] - p[:, 0]
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return Spectra(
        vertices=v,
        faces=f,
        mass=mass,
        grid_theta=grid_theta,
        grid_eta=grid_eta,
        evals=np.stack(evals),
        evecs=np.stack(evecs, axis=1),
        iso_evals=iso_vals,
        iso_evecs=iso_vecs,
        face_frames=u,
        config=config,
        mesh_hash=f"handmade-icosphere-{subdivisions}",
    )


@functools.lru_cache(maxsize=4)
def tiny_spectra(subdivisions: int = 2) -> Spectra:
    """The spectra the kernel tests use (cached per process)."""
    try:
        from hktex_engine.geometry.mesh import mesh_from_arrays
        from hktex_engine.spectra.grid import compute_spectra
    except ImportError:
        return handmade_spectra(TINY_CONFIG, subdivisions)
    v, f = tiny_mesh(subdivisions)
    return compute_spectra(mesh_from_arrays(v, f), TINY_CONFIG)


def random_kernels(spectra: Spectra, n: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Kernel parameters inside their ranges, centres uniformly spread over faces."""
    rng = np.random.default_rng(seed)
    bary = rng.dirichlet(np.ones(3), size=n)
    return {
        "face_ids": rng.integers(0, spectra.faces.shape[0], size=n),
        "bary": bary,
        "theta": rng.uniform(0, np.pi, size=n),
        "eta": 1 + 99 * rng.uniform(size=n),
        "threshold": rng.uniform(0.5, 0.95, size=n),
        "sharpness": 10 + 40 * rng.uniform(size=n),
        "colors": rng.uniform(-0.5, 0.5, size=(n, 3)),
        "base_color": rng.uniform(0.3, 0.7, size=3),
    }


def random_points(spectra: Spectra, p: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return rng.integers(0, spectra.faces.shape[0], size=p), rng.dirichlet(np.ones(3), size=p)


def kernelset_of(spectra: Spectra, kp: dict, config: KernelConfig):
    """A ``KernelSet`` of the parameters ``kp`` (``random_kernels``' keys) on ``spectra``."""
    from hktex_engine.kernels.model import KernelSet

    return KernelSet(
        face_ids=kp["face_ids"],
        barycentrics=kp["bary"],
        theta=kp["theta"],
        eta=kp["eta"],
        threshold=kp["threshold"],
        sharpness=kp["sharpness"],
        colors=kp["colors"],
        base_color=kp["base_color"],
        kernel_config=config,
        mesh_hash=spectra.mesh_hash,
        config_hash=spectra.config_hash,
        sigma_ratio=kp.get("sigma_ratio"),
    )
