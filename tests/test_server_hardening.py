"""Service hardening: strict request types, the job's stage, per-job CPU threads, renders on
any thread, and the storage lifecycle (kernel-set and mesh deletion with shared blobs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import httpx
import pytest
from hktex_server.api import schemas
from hktex_server.storage.db import JobRow, KernelSetRow, MeshRow, SpectraRow, new_id, now
from pydantic import ValidationError

from tests.server_support import LiveServer, fast_settings, migrated

TOKENS = "tok-alice:alice,tok-bob:bob"
ALICE = {"Authorization": "Bearer tok-alice"}
BOB = {"Authorization": "Bearer tok-bob"}


# ---------------------------------------------------------------- 1. strict request models


@pytest.mark.parametrize(
    ("model", "body"),
    [
        (schemas.SpectralConfigIn, {"anisotropies": [False]}),
        (schemas.SpectralConfigIn, {"anisotropies": ["1.0"]}),
        (schemas.SpectralConfigIn, {"angles": "3"}),
        (schemas.SpectralConfigIn, {"k": True}),
        (schemas.FitParamsIn, {"steps": "10"}),
        (schemas.FitParamsIn, {"densify": 1}),
        (schemas.FitParamsIn, {"densify": "true"}),
        (schemas.FitParamsIn, {"lr_colors": True}),
        (schemas.FitParamsIn, {"lr_colors": "0.1"}),
        (schemas.JobCreate, {"mesh_id": "m", "priority": True}),
        (schemas.JobCreate, {"mesh_id": 5}),
        (schemas.JobCreate, {"mesh_id": "m", "params": {"kernels": "16"}}),
        (schemas.AlbedoRequest, {"face_ids": [True], "barycentrics": [[1, 0, 0]]}),
        (schemas.AlbedoRequest, {"face_ids": [0], "barycentrics": [[True, False, False]]}),
        (schemas.AlbedoRequest, {"points": [["1", 0, 0]]}),
    ],
)
def test_lax_coercions_are_refused(model, body) -> None:
    with pytest.raises(ValidationError):
        model.model_validate(body)  # what FastAPI does with a parsed JSON body
    with pytest.raises(ValidationError):
        model.model_validate_json(json.dumps(body))  # the albedo route's path


def test_json_integers_stay_valid_numbers() -> None:
    cfg = schemas.SpectralConfigIn.model_validate_json('{"anisotropies": [1, 5.5], "k": 16}')
    assert cfg.anisotropies == [1.0, 5.5] and all(type(a) is float for a in cfg.anisotropies)
    job = schemas.JobCreate.model_validate(
        {"mesh_id": "m", "params": {"lr_colors": 1, "densify": False}, "spectra": {"angles": 3}}
    )
    assert job.params.lr_colors == 1.0 and job.params.densify is False
    q = schemas.AlbedoRequest.model_validate_json('{"face_ids": [2], "barycentrics": [[1,0,0]]}')
    assert q.barycentrics == [[1.0, 0.0, 0.0]]


# ---------------------------------------------------------------- 2. stage is served


def test_job_record_serves_the_stage() -> None:
    from hktex_server.api.records import job_record
    from hktex_server.jobs.worker_main import progress_record

    progress = progress_record(3, 9, {"stage": "grid", "node": 1})
    row = JobRow(
        id="job_x",
        owner="alice",
        task="spectra",
        state="running",
        priority=0,
        params={},
        attempts=1,
        max_attempts=3,
        cancel_requested=False,
        progress=progress,
        result={},
        created_at=1.0,
        updated_at=1.0,
    )
    record = job_record(row)
    assert record.progress.stage == "grid"
    assert json.loads(record.model_dump_json())["progress"]["stage"] == "grid"


# ---------------------------------------------------------------- 3. threads per job


def test_worker_env_bounds_cpu_threads(tmp_path) -> None:
    from hktex_server.jobs.supervisor import THREAD_VARS, worker_env
    from hktex_server.settings import Settings

    cores = len(os.sched_getaffinity(0))
    s = Settings(data_dir=tmp_path, workers=2 * cores, tokens="secret:alice")
    env = worker_env(s, "cpu", "lease-token")
    assert all(env[v] == "1" for v in THREAD_VARS)  # more slots than cores: one each
    assert "secret" not in env["HKTEX_WORKER_SETTINGS"] and env["CUDA_VISIBLE_DEVICES"] == ""
    assert worker_env(Settings(data_dir=tmp_path, workers=1), "0", "t")["OMP_NUM_THREADS"] == str(
        cores
    )
    env = worker_env(Settings(data_dir=tmp_path, workers=1, job_threads=3), "cpu", "t")
    assert env["OMP_NUM_THREADS"] == env["MKL_NUM_THREADS"] == "3"
    # torch in the job process honours it (read when torch loads)
    out = subprocess.run(
        [sys.executable, "-c", "import torch; print(torch.get_num_threads())"],
        env={**os.environ, **{v: "1" for v in THREAD_VARS}},
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.stdout.strip() == "1", out.stderr


# ---------------------------------------------------------------- 4. renders on any thread

RENDER_ON_THREADS = textwrap.dedent(
    """
    import threading, numpy as np, torch
    from hktex_engine.render import mitsuba as R
    from hktex_engine.errors import RenderError
    from hktex_engine.evaluation.synthetic import icosphere
    try:
        R.ensure_variant()
    except RenderError:
        print("SKIP"); raise SystemExit(0)
    V, F = icosphere(1)
    out = {}
    def work(tag):
        try:
            scene = R.RenderScene(V, F, R.RenderSettings(width=8, height=8, spp=1),
                                  albedo_fn=lambda f, b: torch.full((len(f), 3), 0.5))
            out[tag] = float(np.asarray(scene.render(R.parse_view("30,20", V))).mean())
        except Exception as exc:
            out[tag] = repr(exc)
    threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
    for t in threads: t.start()
    for t in threads: t.join()
    work("main")
    print(repr(out))
    """
)


@pytest.mark.mitsuba
def test_renders_succeed_on_threads_other_than_the_first() -> None:
    # In a child process: a failing Dr.Jit render has corrupted a pytest process before.
    out = subprocess.run(
        [sys.executable, "-c", RENDER_ON_THREADS], capture_output=True, text=True, timeout=300
    )
    if out.stdout.strip() == "SKIP":
        pytest.skip("no Mitsuba variant on this host")
    values = eval(out.stdout.strip().splitlines()[-1])  # a dict literal we printed
    assert all(isinstance(v, float) and v > 0 for v in values.values()), values
    assert len(set(values.values())) == 1, values  # same scene, same seed: same image


# ---------------------------------------------------------------- 5/7. over HTTP


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("hardening")
    settings = fast_settings(tmp, f"sqlite:///{tmp / 'hktex.db'}", tokens=TOKENS)
    with LiveServer(settings) as live:
        live.settings = settings
        live.db = migrated(settings)
        yield live


@pytest.fixture(scope="module")
def patch_obj(tmp_path_factory):
    from hktex_engine.evaluation.synthetic import grid_patch

    v, f = grid_patch(3, 3)
    obj = tmp_path_factory.mktemp("mesh") / "patch.obj"
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
    obj.write_text("\n".join(lines + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]) + "\n")
    return obj


def _client(server, headers) -> httpx.Client:
    return httpx.Client(base_url=server.url, headers=headers, timeout=30)


def _upload(c: httpx.Client, path, name="patch.obj") -> dict:
    r = c.post("/v1/meshes", files={"mesh": (name, path.read_bytes(), "text/plain")})
    assert r.status_code in (200, 201), r.text
    return r.json()


def test_http_refuses_lax_bodies(server, patch_obj) -> None:
    with _client(server, ALICE) as c:
        mesh = _upload(c, patch_obj, "strict.obj")
        r = c.post(f"/v1/meshes/{mesh['id']}/spectra", json={"anisotropies": [False]})
        assert r.status_code == 422, r.text
        r = c.post("/v1/jobs", json={"mesh_id": mesh["id"], "params": {"steps": "10"}})
        assert r.status_code == 422, r.text
        r = c.post(
            "/v1/kernelsets/ks_none/albedo",
            json={"face_ids": [True], "barycentrics": [[1, 0, 0]]},
        )
        assert r.status_code == 422, r.text
        r = c.delete(f"/v1/meshes/{mesh['id']}")
        assert r.status_code == 204


def _add_kernelset(server, owner: str, mesh_id: str, spectra_id: str, content: bytes) -> tuple:
    """A kernel-set row with a content-addressed file, as a finished fit leaves them."""
    tmp = server.settings.data_dir / "tmp" / new_id("t")
    tmp.parent.mkdir(parents=True, exist_ok=True)
    tmp.write_bytes(content)
    from hktex_server.storage.blobs import BlobStore

    rel, _, size = BlobStore(server.settings.data_dir).publish_file(tmp, "kernelsets", ".hkt")
    ks = KernelSetRow(
        id=new_id("ks"),
        owner=owner,
        job_id=None,
        mesh_id=mesh_id,
        spectra_id=spectra_id,
        path=rel,
        bytes=size,
        n_kernels=1,
        metrics={},
        manifest={},
        created_at=now(),
    )
    with server.db.write() as s:
        s.add(ks)
    return ks.id, server.settings.data_dir / rel


def test_delete_kernelset_owner_only_and_shared_files(server, patch_obj) -> None:
    with _client(server, ALICE) as alice, _client(server, BOB) as bob:
        mesh = _upload(alice, patch_obj, "ks.obj")
        a, path = _add_kernelset(server, "alice", mesh["id"], "spc_x", b"same bytes")
        b, path_b = _add_kernelset(server, "alice", mesh["id"], "spc_x", b"same bytes")
        assert path == path_b and path.is_file()
        assert bob.delete(f"/v1/kernelsets/{a}").status_code == 404
        assert alice.get(f"/v1/kernelsets/{a}").status_code == 200
        assert alice.delete(f"/v1/kernelsets/{a}").status_code == 204
        assert alice.get(f"/v1/kernelsets/{a}").status_code == 404
        assert alice.delete(f"/v1/kernelsets/{a}").status_code == 404
        assert path.is_file(), "the file is still another record's"
        assert alice.delete(f"/v1/kernelsets/{b}").status_code == 204
        assert not path.exists()
        assert alice.delete(f"/v1/meshes/{mesh['id']}").status_code == 204


def test_mesh_deletion_rule(server, patch_obj) -> None:
    db, data = server.db, server.settings.data_dir
    with _client(server, ALICE) as alice, _client(server, BOB) as bob:
        mine, theirs = _upload(alice, patch_obj, "life.obj"), _upload(bob, patch_obj, "life.obj")
        spectra_dir = data / "spectra" / "fake_for_test"
        spectra_dir.mkdir(parents=True)
        (spectra_dir / "manifest.json").write_text("{}")
        spectra = SpectraRow(
            id=new_id("spc"),
            mesh_hash=mine["content_hash"],
            config_hash="c" * 64,
            config={},
            state="ready",
            path="spectra/fake_for_test",
            created_at=now(),
            updated_at=now(),
        )
        job = JobRow(
            id=new_id("job"),
            owner="alice",
            task="fit_uv",
            state="running",
            priority=0,
            mesh_id=mine["id"],
            spectra_id=spectra.id,
            params={},
            attempts=1,
            max_attempts=3,
            cancel_requested=False,
            progress={},
            result={},
            created_at=now(),
            updated_at=now(),
        )
        with db.write() as s:
            s.add_all([spectra, job])
        ks, ks_file = _add_kernelset(server, "alice", mine["id"], spectra.id, b"fit of alice")
        r = alice.delete(f"/v1/meshes/{mine['id']}")
        assert r.status_code == 409 and job.id in r.json()["detail"]
        with db.write() as s:
            s.get(JobRow, job.id).state = "succeeded"
        assert alice.delete(f"/v1/meshes/{mine['id']}").status_code == 204
        assert alice.get(f"/v1/kernelsets/{ks}").status_code == 404 and not ks_file.exists()
        assert alice.get(f"/v1/jobs/{job.id}").status_code == 404
        with db.read() as s:
            blob = s.get(MeshRow, theirs["id"]).mesh_blob
            assert s.get(SpectraRow, spectra.id) is not None, "bob's mesh has this geometry"
        assert spectra_dir.is_dir()
        assert (data / blob).is_file(), "the blob is shared with bob's mesh"
        assert bob.get(f"/v1/spectra/{spectra.id}").status_code == 200
        assert bob.delete(f"/v1/meshes/{theirs['id']}").status_code == 204
        with db.read() as s:
            assert s.get(SpectraRow, spectra.id) is None
        assert not spectra_dir.exists()
        assert not list((data / "meshes").rglob("*.obj")), "no row refers to the mesh blob"


def test_corrupt_deflate_stream_is_422_and_leaves_no_temp_dir(server) -> None:
    import io
    import zipfile

    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("views.json", b'{"a": ' + b"1" * 5000 + b"}")
    data = bytearray(buf.getvalue())
    start = 30 + len("views.json")  # local header, then the deflate stream: garble it
    for i in range(start + 2, start + 30):
        data[i] ^= 0x5A
    tmp = server.settings.data_dir / "tmp"
    before = set(tmp.iterdir())
    with _client(server, ALICE) as c:
        r = c.post("/v1/views", files={"archive": ("v.zip", bytes(data), "application/zip")})
        assert r.status_code == 422, r.text
        r = c.post("/v1/views", files={"archive": ("v.zip", b"not a zip", "application/zip")})
        assert r.status_code == 422, r.text
        assert c.get("/v1/health").status_code == 200
    assert set(tmp.iterdir()) <= before, "a temp extraction directory was left behind"


# ---------------------------------------------------------------- 6. validation is killable


def test_validation_runs_in_a_killable_process(patch_obj, tmp_path) -> None:
    import multiprocessing

    from hktex_server.api.validation import (
        InvalidMesh,
        ValidationTimeout,
        validate_mesh,
    )

    from hktex_engine.geometry.mesh import load_mesh

    summary = validate_mesh(patch_obj, None, 5000, "obj", 120)
    mesh = load_mesh(patch_obj)
    assert summary.content_hash == mesh.content_hash
    assert (summary.n_vertices, summary.n_faces) == (mesh.n_vertices, mesh.n_faces)
    with pytest.raises(InvalidMesh) as err:
        validate_mesh(patch_obj, None, 3, "obj", 120)
    assert err.value.input_error and "TooManyVertices" in str(err.value)
    garbage = tmp_path / "garbage.ply"
    garbage.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99999999\n")
    with pytest.raises(InvalidMesh):
        validate_mesh(garbage, None, 5000, "ply", 120)
    with pytest.raises(ValidationTimeout):
        validate_mesh(patch_obj, None, 5000, "obj", 0.0)
    validators = [
        p for p in multiprocessing.active_children() if not p.name.startswith("hktex-compute")
    ]  # the compute workers of a live server in this process are meant to stay
    assert not validators, "a validator outlived its timeout"


def test_upload_validation_timeout_is_422(tmp_path, patch_obj) -> None:
    settings = fast_settings(tmp_path, f"sqlite:///{tmp_path / 'v.db'}", validate_timeout_seconds=0)
    with LiveServer(settings) as live, httpx.Client(base_url=live.url, timeout=30) as c:
        r = c.post("/v1/meshes", files={"mesh": ("p.obj", patch_obj.read_bytes(), "text/plain")})
        assert r.status_code == 422 and "longer than" in r.json()["detail"], r.text


# ---------------------------------------------------------------- 7. shared spectra and cancel


def test_one_owners_cancel_of_shared_spectra_does_not_fail_anothers_fit(tmp_path) -> None:
    from hktex_server.jobs import queue as jobqueue

    settings = fast_settings(tmp_path, f"sqlite:///{tmp_path / 'q.db'}")
    db = migrated(settings)
    spectra = jobqueue.ensure_spectra(db, "alice", "msh_a", "h" * 64, {"k": 4}, "c" * 64, 3)
    with db.write() as s:
        fits = {
            who: jobqueue.enqueue(s, who, "fit_uv", mesh_id=f"msh_{who}", spectra_id=spectra.id).id
            for who in ("alice", "bob")
        }
    jobqueue.request_cancel(db, "alice", spectra.job_id)  # alice stops the spectra job
    counts = jobqueue.reap(db)
    assert counts["spectra_requeued"] == 1 and counts["dependents_failed"] == 1
    with db.read() as s:
        assert s.get(JobRow, fits["alice"]).state == "failed"  # her own cancel: her fit stops
        assert s.get(JobRow, fits["bob"]).state == "queued"
        row = s.get(SpectraRow, spectra.id)
        assert row.state == "queued" and row.job_id != spectra.job_id
        again = s.get(JobRow, row.job_id)
        assert (again.owner, again.task, again.mesh_id) == ("bob", "spectra", "msh_bob")
    db.dispose()


def test_worker_env_never_carries_api_tokens(tmp_path, monkeypatch) -> None:
    """Tokens set in the server's environment must not reach job processes."""
    from hktex_server.jobs.supervisor import worker_env
    from hktex_server.settings import Settings

    monkeypatch.setenv("HKTEX_TOKENS", "secret:alice")
    env = worker_env(Settings(data_dir=tmp_path), "cpu", "t")
    assert "HKTEX_TOKENS" not in env
    assert not any("secret" in value for value in env.values())
