"""The Python client against the real service: uvicorn on a loopback port, real HTTP.

One small service per module (tokens for two owners, one worker slot) serves every test; the
fitted kernel set is made once (tiny grid, few steps) and shared. Independent checks: the
colours the service answers over NPY equal those the engine computes locally from the
downloaded ``.hkt`` and spectra archive, and the JSON path answers the same numbers.
"""

from __future__ import annotations

import asyncio
import tarfile
import zipfile
from pathlib import Path

import numpy as np
import pytest
from hktex_client import (
    AsyncClient,
    Client,
    JobFailed,
    NotFound,
    PayloadTooLarge,
    Unauthorized,
    ValidationFailed,
)
from hktex_server.api.schemas import FitParamsIn
from hktex_server.demo import spawned_service

ALICE, BOB = "tok-alice", "tok-bob"
SPECTRAL = {"angles": 2, "anisotropies": [1.0, 10.0], "k": 8, "k_iso": 6}
FIT = {"kernels": 24, "max_kernels": 48, "steps": 12, "points_per_step": 128, "seed": 1}
MAX_UPLOAD = 2_000_000
if "eval_points" in FitParamsIn.model_fields:  # the fit's own PSNR evaluation dominates tiny fits
    FIT["eval_points"] = 2_000


@pytest.fixture(scope="module")
def service(tmp_path_factory: pytest.TempPathFactory) -> str:
    """``hktex serve`` in a child process: what the client talks to in production."""
    env = {
        "HKTEX_TOKENS": f"{ALICE}:alice,{BOB}:bob",
        "HKTEX_MAX_UPLOAD_BYTES": str(MAX_UPLOAD),
        "HKTEX_POLL_SECONDS": "0.1",
        "OMP_NUM_THREADS": "1",  # tiny problems: one thread is fastest (docs/client.md)
        "OPENBLAS_NUM_THREADS": "1",
    }
    with spawned_service(tmp_path_factory.mktemp("hktex-client-service"), 1, env) as url:
        yield url


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    from hktex_engine.evaluation.synthetic import textured_demo, write_textured_obj

    out = tmp_path_factory.mktemp("hktex-client-mesh")
    v, f, uv, tex = textured_demo(subdivisions=2, texture_size=64)
    obj = write_textured_obj(out / "blob.obj", v, f, uv, tex)
    return obj, obj.with_name("blob_albedo.png")


@pytest.fixture(scope="module")
def alice(service: str):
    with Client(service, token=ALICE, timeout=120) as client:
        yield client


@pytest.fixture(scope="module")
def fitted(alice: Client, mesh_files: tuple[Path, Path]) -> dict:
    """Upload, spectra, fit once; the ids every query test uses."""
    obj, tex = mesh_files
    mesh = alice.upload_mesh(obj, texture=tex)
    spectra = alice.request_spectra(mesh.id, **SPECTRAL)
    if not spectra.ready:
        assert spectra.job_id, spectra
        alice.wait(spectra.job_id, timeout=300, poll=0.2)
    job = alice.fit_uv(mesh.id, spectra=SPECTRAL, **FIT)
    done = alice.wait(job.id, timeout=300, poll=0.2)
    assert done.state == "succeeded" and done.result.kernelset_id
    return {"mesh": mesh, "spectra_id": done.result.spectra_id or spectra.id, "job": done}


# ---- service records and typed errors ---------------------------------------------------------


def test_health_and_info_are_typed(alice: Client) -> None:
    assert alice.health().status == "ok"
    info = alice.info()
    assert info.owner == "alice" and info.version
    assert info.limits.get("max_upload_bytes") == MAX_UPLOAD


def test_unknown_token_is_unauthorized_with_reason(service: str) -> None:
    with Client(service, token="not-a-token") as client:
        with pytest.raises(Unauthorized) as info:
            client.list_meshes()
    assert info.value.status == 401 and info.value.reason


def test_missing_record_is_not_found_with_reason(alice: Client) -> None:
    with pytest.raises(NotFound) as info:
        alice.get_job("job_does_not_exist")
    assert info.value.status == 404
    assert "job_does_not_exist" in info.value.reason or "not found" in info.value.reason.lower()


def test_garbage_mesh_is_rejected_with_the_validators_reason(alice: Client, tmp_path) -> None:
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n")
    with pytest.raises(ValidationFailed) as info:
        alice.upload_mesh(bad)
    assert info.value.status == 422 and len(info.value.reason) > 5


def test_oversized_upload_is_payload_too_large(alice: Client, tmp_path) -> None:
    big = tmp_path / "big.obj"
    big.write_bytes(b"# padding\n" * (MAX_UPLOAD // 10 + 1000))
    with pytest.raises(PayloadTooLarge) as info:
        alice.upload_mesh(big)
    assert info.value.status == 413


def test_unknown_fit_parameter_names_the_field(alice: Client, fitted: dict) -> None:
    with pytest.raises(ValidationFailed) as info:
        alice.fit_uv(fitted["mesh"].id, stepz=5)
    assert "stepz" in info.value.reason


def test_other_owner_sees_404_not_403(service: str, fitted: dict) -> None:
    with Client(service, token=BOB) as bob:
        with pytest.raises(NotFound):
            bob.get_mesh(fitted["mesh"].id)
        with pytest.raises(NotFound):
            bob.albedo(fitted["job"].result.kernelset_id, points=[[0.0, 0.0, 0.0]])
        assert all(m.id != fitted["mesh"].id for m in bob.list_meshes())


# ---- the fitted path --------------------------------------------------------------------------


def test_same_content_gives_same_mesh_id(alice: Client, mesh_files, fitted: dict) -> None:
    again = alice.upload_mesh(mesh_files[0], texture=mesh_files[1])
    assert again.id == fitted["mesh"].id
    assert again.has_texture and again.n_faces == fitted["mesh"].n_faces
    assert any(m.id == again.id for m in alice.list_meshes())


def _unpack(archive: Path, into: Path) -> Path:
    if zipfile.is_zipfile(archive):
        with zipfile.ZipFile(archive) as zf:
            zf.extractall(into)
    else:
        with tarfile.open(archive) as tf:
            tf.extractall(into, filter="data")
    manifests = list(into.rglob("manifest.json"))
    assert manifests, "the spectra archive holds no manifest.json"
    return manifests[0].parent


def test_npy_answers_equal_the_engine_on_the_downloaded_files(
    alice: Client, fitted: dict, tmp_path: Path
) -> None:
    from hktex_engine.kernels.hkt import load_hkt
    from hktex_engine.kernels.query import AlbedoQuery
    from hktex_engine.spectra.grid import load_spectra

    ks_id = fitted["job"].result.kernelset_id
    hkt = alice.download_kernelset(ks_id, tmp_path / "k.hkt")
    archive = alice.download_spectra(fitted["spectra_id"], tmp_path / "spectra.archive")
    spectra = load_spectra(_unpack(archive, tmp_path / "spectra"))
    local = AlbedoQuery(spectra, load_hkt(hkt), device="cpu")

    rng = np.random.default_rng(3)
    n_faces = fitted["mesh"].n_faces
    faces = rng.integers(0, n_faces, 500)
    bary = rng.dirichlet(np.ones(3), 500)
    remote = alice.albedo(ks_id, face_ids=faces, barycentrics=bary)
    assert remote.shape == (500, 3)
    np.testing.assert_allclose(remote, local.colors(faces, bary), atol=1e-5)
    as_json = alice.albedo(ks_id, face_ids=faces, barycentrics=bary, binary=False)
    np.testing.assert_allclose(as_json, remote, atol=1e-6)
    chunked = alice.albedo(ks_id, face_ids=faces, barycentrics=bary, chunk_size=128)
    _same_colors(chunked, remote)


def _same_colors(a: np.ndarray, b: np.ndarray) -> None:
    """Equal per point up to float noise: a point's colour must not depend on its batch
    (chunking, point vs face requests). The engine's K_s candidate cut once made 2 of 2,000
    points differ by up to 0.036; b332260 made it exact."""
    np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)


def test_point_queries_match_face_queries(alice: Client, fitted: dict, mesh_files) -> None:
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.geometry.sampling import points_from_barycentric, sample_surface

    mesh = load_mesh(mesh_files[0], texture=mesh_files[1])
    faces, bary = sample_surface(mesh.vertices, mesh.faces, 200, 5)
    pts = mesh.to_file_units(points_from_barycentric(mesh.vertices, mesh.faces, faces, bary))
    ks_id = fitted["job"].result.kernelset_id
    at_faces = alice.albedo(ks_id, face_ids=faces, barycentrics=bary)
    at_points = alice.albedo(ks_id, points=pts)
    _same_colors(at_points, at_faces)


def test_bad_query_is_a_422_with_reason(alice: Client, fitted: dict) -> None:
    ks_id = fitted["job"].result.kernelset_id
    with pytest.raises(ValidationFailed) as info:
        alice.albedo(ks_id, face_ids=[10**9], barycentrics=[[1.0, 0.0, 0.0]])
    assert info.value.reason
    with pytest.raises(ValidationFailed):
        alice.albedo(ks_id, points=[[np.nan, 0.0, 0.0]])


def test_job_listing_filters_by_state(alice: Client, fitted: dict) -> None:
    done = alice.list_jobs(state="succeeded")
    assert fitted["job"].id in {j.id for j in done}
    assert all(j.state == "succeeded" for j in done)
    assert len(alice.list_jobs(limit=1)) == 1


def test_kernelset_record_and_render(alice: Client, fitted: dict) -> None:
    ks = alice.get_kernelset(fitted["job"].result.kernelset_id)
    assert ks.n_kernels > 0 and ks.bytes > 0 and ks.job_id == fitted["job"].id
    png = alice.render(ks.id, width=48, height=40)
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    assert int.from_bytes(png[16:20], "big") == 48 and int.from_bytes(png[20:24], "big") == 40


def test_async_client_answers_like_the_sync_client(
    alice: Client, fitted: dict, mesh_files: tuple[Path, Path]
) -> None:
    ks_id = fitted["job"].result.kernelset_id
    rng = np.random.default_rng(11)
    faces = rng.integers(0, fitted["mesh"].n_faces, 64)
    bary = rng.dirichlet(np.ones(3), 64)
    expected = alice.albedo(ks_id, face_ids=faces, barycentrics=bary)

    async def main() -> tuple:
        async with AsyncClient(alice.base_url, token=ALICE) as ac:
            colors, job, records = await asyncio.gather(
                ac.albedo(ks_id, face_ids=faces, barycentrics=bary),
                ac.wait(fitted["job"].id, timeout=10),
                _collect(ac.watch(fitted["job"].id)),
            )
            with pytest.raises(NotFound):
                await ac.get_kernelset("kst_missing")
            again = await ac.upload_mesh(mesh_files[0], texture=mesh_files[1])  # streamed
            assert again.id == fitted["mesh"].id
            return colors, job, records

    colors, job, records = asyncio.run(main())
    np.testing.assert_array_equal(colors, expected)
    assert job.state == "succeeded" and records[-1].state == "succeeded"


async def _collect(aiter) -> list:
    return [item async for item in aiter]


def test_concurrent_renders_all_succeed(alice: Client, fitted: dict) -> None:
    # Concurrent requests run on different threads of the API's threadpool; each must render
    # (Dr.Jit's JIT flags are per thread, so per-process set-up is not enough).
    ks_id = fitted["job"].result.kernelset_id

    async def main() -> list[bytes]:
        async with AsyncClient(alice.base_url, token=ALICE, timeout=300) as ac:
            return await asyncio.gather(
                *(ac.render(ks_id, width=16 + 8 * i, height=16) for i in range(3))
            )

    for i, png in enumerate(asyncio.run(main())):
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        assert int.from_bytes(png[16:20], "big") == 16 + 8 * i


# ---- progress: wait, events, cancel -----------------------------------------------------------


def test_events_of_a_finished_job_end_with_its_final_state(alice: Client, fitted: dict) -> None:
    events = list(alice.stream_events(fitted["job"].id))
    assert events, "no events"
    assert events[-1].json()["state"] == "succeeded"


@pytest.mark.slow  # ~15 s: a worker process must start and load torch before it can be cancelled
def test_cancel_a_running_fit_and_wait_reports_it(alice: Client, fitted: dict) -> None:
    job = alice.fit_uv(fitted["mesh"].id, spectra=SPECTRAL, **{**FIT, "steps": 1_000_000})
    seen: list[str] = []

    async def watch() -> None:
        # Cancel once the job is seen running (or after 30 s queued), from the async client,
        # while the same stream keeps reporting until the final state.
        start = asyncio.get_running_loop().time()
        cancelled = False
        async with AsyncClient(alice.base_url, token=ALICE) as ac:
            async for event in ac.stream_events(job.id):
                seen.append(event.json()["state"])
                waited = asyncio.get_running_loop().time() - start
                if not cancelled and (seen[-1] == "running" or waited > 30):
                    await ac.cancel_job(job.id)
                    cancelled = True

    asyncio.run(asyncio.wait_for(watch(), timeout=120))
    with pytest.raises(JobFailed) as info:
        alice.wait(job.id, timeout=60, poll=0.2)
    assert info.value.job.state == "cancelled"
    assert seen[-1] == "cancelled"
