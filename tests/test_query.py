"""AlbedoQuery: validation, file-unit points, chunking with bounded tensor sizes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from hktex_engine.config import KernelConfig
from hktex_engine.errors import KernelSetError, QueryError
from hktex_engine.kernels import tables as tables_mod
from hktex_engine.kernels.model import HeatKernelModel
from hktex_engine.kernels.query import AlbedoQuery
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import kernelset_of, random_kernels, random_points, tiny_spectra

CONFIG = KernelConfig(diffusion_time=0.01, sigma_b=0.3, k_search=10, k_blend=4)


@pytest.fixture(scope="module")
def spectra():
    # a non-trivial file frame, so file units and normalised units differ
    sp = tiny_spectra()
    translation = [0.25, -1.0, 2.0]
    # write_spectra takes the frame from the manifest, so set it in both places
    manifest = {**sp.manifest, "scale": 0.5, "translation": translation}
    return dataclasses.replace(sp, scale=0.5, translation=np.array(translation), manifest=manifest)


@pytest.fixture(scope="module")
def kernelset(spectra):
    kp = random_kernels(spectra, 40, seed=3)
    kp["threshold"] = np.random.default_rng(4).uniform(0.3, 0.6, 40)
    return kernelset_of(spectra, kp, CONFIG)


@pytest.fixture(scope="module")
def query(spectra, kernelset):
    return AlbedoQuery(spectra, kernelset, device="cpu")


def test_colors_match_the_model(spectra, kernelset, query):
    face_ids, bary = random_points(spectra, 50, seed=5)
    got = query.colors(face_ids, bary)
    assert got.dtype == np.float32 and got.shape == (50, 3)
    field = SpectralField(spectra, device="cpu", dtype=torch.float64)
    model = HeatKernelModel.from_kernelset(kernelset, field)
    with torch.no_grad():
        ref = model.albedo(face_ids, bary).numpy()
    np.testing.assert_allclose(got, ref, atol=1e-5)
    assert np.ptp(got) > 0.05
    assert query.colors(np.zeros(0, dtype=np.int64), np.zeros((0, 3))).shape == (0, 3)


def test_points_in_file_units(spectra, query):
    face_ids, _ = random_points(spectra, 30, seed=6)
    bary = np.random.default_rng(7).dirichlet(np.full(3, 4.0), 30)  # well inside the faces
    normalised = np.einsum("pv,pvd->pd", bary, spectra.vertices[spectra.faces[face_ids]])
    file_units = (normalised - spectra.translation) / spectra.scale
    np.testing.assert_allclose(
        query.colors_at_points(file_units), query.colors(face_ids, bary), atol=1e-5
    )


@pytest.mark.parametrize(
    ("face_ids", "bary", "match"),
    [
        (np.array([0, 10**6]), np.full((2, 3), 1 / 3), "face ids"),
        (np.array([-1, 0]), np.full((2, 3), 1 / 3), "face ids"),
        (np.array([0.0, 1.0]), np.full((2, 3), 1 / 3), "integers"),
        (np.array([0, 1]), np.array([[1.2, -0.2, 0.0], [1, 0, 0]]), "non-negative"),
        (np.array([0, 1]), np.array([[0.5, 0.2, 0.0], [1, 0, 0]]), "sum to 1"),
        (np.array([0, 1]), np.array([[np.nan, 0.5, 0.5], [1, 0, 0]]), "NaN"),
        (np.array([0, 1]), np.full((3, 3), 1 / 3), "shape"),
        (np.array([[0, 1]]), np.full((2, 3), 1 / 3), "shape"),
        (np.array([0, 1]), np.full((2, 2), 1 / 2), "shape"),
    ],
)
def test_query_validation(query, face_ids, bary, match):
    with pytest.raises(QueryError, match=match):
        query.colors(face_ids, bary)


@pytest.mark.parametrize(
    "points", [np.zeros((4, 2)), np.array([[0.0, np.inf, 0.0]]), np.array([["a", "b", "c"]])]
)
def test_points_validation(query, points):
    with pytest.raises(QueryError):
        query.colors_at_points(points)


def test_refuses_a_kernel_set_of_another_mesh(spectra, kernelset):
    other = dataclasses.replace(kernelset, mesh_hash="0" * 64)
    with pytest.raises(KernelSetError, match="another mesh"):
        AlbedoQuery(spectra, other, device="cpu")
    other = dataclasses.replace(kernelset, config_hash="0" * 64)
    with pytest.raises(KernelSetError, match="config"):
        AlbedoQuery(spectra, other, device="cpu")


class _LargestTensor(TorchDispatchMode):
    """Records the largest tensor any torch operation produces (views of an input, such as
    the ``detach`` behind ``Tensor.numpy``, allocate nothing and are not counted)."""

    def __init__(self) -> None:
        super().__init__()
        self.largest = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        inputs = [a for a in (*args, *(kwargs or {}).values()) if isinstance(a, torch.Tensor)]
        storages = {a.untyped_storage().data_ptr() for a in inputs}
        for t in out if isinstance(out, tuple | list) else (out,):
            if isinstance(t, torch.Tensor) and t.untyped_storage().data_ptr() not in storages:
                self.largest = max(self.largest, t.numel() * t.element_size())
        return out


def test_chunked_memory_is_bounded(spectra, kernelset):
    chunked = AlbedoQuery(spectra, kernelset, device="cpu", chunk_points=16)
    whole = AlbedoQuery(spectra, kernelset, device="cpu", chunk_points=10**6)
    sizes = []
    # 64 points: the per-point path; then more points than vertices: whole-mesh candidate
    # tables, built by the first such call (their size depends on the mesh, not the points)
    for p in (64, 600, 512, 4096):
        face_ids, bary = random_points(spectra, p, seed=p)
        with _LargestTensor() as mode:
            got = chunked.colors(face_ids, bary)
        sizes.append(mode.largest)
        np.testing.assert_allclose(got, whole.colors(face_ids, bary), atol=1e-6)
    assert sizes[2] == sizes[3], "peak tensor size must not grow with the number of points"
    for size in (sizes[0], sizes[2]):
        assert size <= 16 * chunked.bytes_per_point()
    tables = chunked.model._vtables
    assert tables is not None and chunked.model._vtables_full
    # the build: mesh-sized tables and intermediates capped by the tables' chunk sizes
    cap = max(4 * tables.nbytes, tables_mod.DISTANCE_CHUNK_BYTES, tables_mod.H_CHUNK_BYTES)
    assert sizes[1] <= cap
    auto = AlbedoQuery(spectra, kernelset, device="cpu", memory_budget=1 << 20)
    assert auto.chunk_points == (1 << 20) // auto.bytes_per_point()


def test_mesh_tables_take_larger_chunks(spectra, kernelset, monkeypatch):
    """Once whole-mesh tables answer through the compiled blend, a call runs in chunks of
    ``TABLE_CHUNK_POINTS`` (within the memory budget at ``TABLE_BYTES_PER_POINT``), not the
    per-point path's, so the blend's threads get whole chunks; a chosen ``chunk_points``
    stays as chosen. Colours are the same either way."""
    from hktex_engine.kernels import fused_blend
    from hktex_engine.kernels import query as query_mod

    monkeypatch.setattr(query_mod, "TABLE_CHUNK_POINTS", 700)
    face_ids, bary = random_points(spectra, 2000, seed=21)
    auto = AlbedoQuery(spectra, kernelset, device="cpu", memory_budget=1 << 20)
    chosen = AlbedoQuery(spectra, kernelset, device="cpu", chunk_points=64)
    assert auto.chunk_points < 700
    sizes = {}
    for name, q in (("auto", auto), ("chosen", chosen)):
        seen = []
        real = q.model.albedo
        monkeypatch.setattr(q.model, "albedo", lambda f, b, real=real, seen=seen: seen.append(len(f)) or real(f, b))  # fmt: skip
        sizes[name] = (q.colors(face_ids, bary), seen)
    compiled = fused_blend.available(torch.device("cpu"), auto.field.dtype)
    assert auto.model.blends_from_mesh_tables() == compiled
    expect = 700 if compiled else auto.chunk_points
    assert max(sizes["auto"][1]) == expect
    assert max(sizes["chosen"][1]) == 64
    np.testing.assert_allclose(sizes["auto"][0], sizes["chosen"][0], atol=1e-6)
    small = AlbedoQuery(spectra, kernelset, device="cpu", memory_budget=128 * 300)
    assert small._table_chunk == 300


def test_cli_query(tmp_path, spectra, kernelset, query, capsys):
    import json

    from hktex_engine.cli import main
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.spectra.grid import write_spectra

    sdir = write_spectra(spectra, tmp_path / "spectra")
    hkt = save_hkt(kernelset, tmp_path / "k.hkt", compact=False)
    face_ids, bary = random_points(spectra, 25, seed=9)
    np.save(tmp_path / "f.npy", face_ids)
    np.save(tmp_path / "b.npy", bary)
    args = ["query", str(hkt), "--spectra", str(sdir), "-o", str(tmp_path / "c.out")]
    rc = main(
        [
            *args,
            "--faces",
            str(tmp_path / "f.npy"),
            "--barycentrics",
            str(tmp_path / "b.npy"),
            "--json",
        ]
    )
    summary = json.loads(capsys.readouterr().out)
    assert rc == 0 and summary["count"] == 25 and summary["points_per_s"] > 0
    got = np.load(tmp_path / "c.out")
    np.testing.assert_allclose(got, query.colors(face_ids, bary), atol=1e-6)

    points = np.einsum("pv,pvd->pd", bary, spectra.vertices[spectra.faces[face_ids]])
    np.save(tmp_path / "p.npy", (points - spectra.translation) / spectra.scale)
    assert main([*args, "--points", str(tmp_path / "p.npy")]) == 0
    np.testing.assert_allclose(np.load(tmp_path / "c.out"), got, atol=1e-5)

    np.save(tmp_path / "bad.npy", np.full(25, 10**7))
    rc = main(
        [*args, "--faces", str(tmp_path / "bad.npy"), "--barycentrics", str(tmp_path / "b.npy")]
    )
    err = capsys.readouterr().err
    assert rc == 2 and "face ids" in err and len(err.strip().splitlines()) == 1
    assert (
        main([*args, "--points", str(tmp_path / "p.npy"), "--faces", str(tmp_path / "f.npy")]) == 2
    )
    assert "either --points" in capsys.readouterr().err
    (tmp_path / "junk.hkt").write_text("junk")
    assert (
        main(["query", str(tmp_path / "junk.hkt"), *args[2:], "--points", str(tmp_path / "p.npy")])
        == 2
    )


def test_cli_query_dense_builds_tables_with_the_state(tmp_path, spectra, kernelset, capsys):
    """A call with more points than vertices builds the candidate tables before the timer
    (``state_seconds``) and answers as the per-point path does."""
    import json

    from hktex_engine.cli import main
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.spectra.grid import write_spectra

    sdir = write_spectra(spectra, tmp_path / "spectra")
    hkt = save_hkt(kernelset, tmp_path / "k.hkt", compact=False)
    n = 2 * spectra.vertices.shape[0]
    face_ids, bary = random_points(spectra, n, seed=10)
    np.save(tmp_path / "f.npy", face_ids)
    np.save(tmp_path / "b.npy", bary)
    rc = main(
        [
            "query",
            str(hkt),
            "--spectra",
            str(sdir),
            "-o",
            str(tmp_path / "c.out"),
            "--faces",
            str(tmp_path / "f.npy"),
            "--barycentrics",
            str(tmp_path / "b.npy"),
            "--json",
        ]
    )
    summary = json.loads(capsys.readouterr().out)
    assert rc == 0 and summary["count"] == n and summary["state_seconds"] > 0
    sparse = AlbedoQuery(spectra, kernelset, device="cpu", tables=False)
    with torch.no_grad():
        from hktex_engine.kernels import model as kernels_mod

        old, kernels_mod.TABLE_PATH = kernels_mod.TABLE_PATH, "never"
        try:
            ref = sparse.colors(face_ids, bary)
        finally:
            kernels_mod.TABLE_PATH = old
    np.testing.assert_allclose(np.load(tmp_path / "c.out"), ref, atol=1e-5)
