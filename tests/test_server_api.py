"""The REST API on a real uvicorn over loopback: uploads, validation, auth and isolation,
hostile inputs (every one a 4xx, and the server keeps serving), cancel and SSE."""

from __future__ import annotations

import io
import json
import zipfile

import httpx
import numpy as np
import pytest
from hktex_server.settings import Settings, is_loopback

from tests.server_support import (
    LiveServer,
    SupervisorInThread,
    add_sleep_job,
    fast_settings,
    migrated,
    wait_for,
)

TOKENS = "tok-alice:alice,tok-bob:bob"
ALICE = {"Authorization": "Bearer tok-alice"}
BOB = {"Authorization": "Bearer tok-bob"}


@pytest.fixture(scope="module")
def mesh_files(tmp_path_factory):
    from PIL import Image

    from hktex_engine.evaluation.synthetic import grid_patch, textured_demo

    root = tmp_path_factory.mktemp("meshes")
    v, f = grid_patch(4, 4)
    obj = root / "patch.obj"
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in v]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    obj.write_text("\n".join(lines) + "\n")
    tv, tf, uvs, tex = textured_demo(subdivisions=1, texture_size=16)
    from hktex_engine.evaluation.synthetic import write_textured_obj

    textured = write_textured_obj(root / "blob.obj", tv, tf, uvs, tex)
    png = root / "blob_albedo.png"
    assert png.is_file()
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(root / "black.png")
    return {"patch": obj, "blob": textured, "png": png, "black": root / "black.png"}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api")
    settings = fast_settings(
        tmp,
        f"sqlite:///{tmp / 'hktex.db'}",
        tokens=TOKENS,
        max_upload_bytes=1_000_000,
        max_archive_bytes=100_000,
        max_batch_points=1000,
        max_jobs_per_owner=5,
        max_vertices=5000,
    )
    with LiveServer(settings) as live:
        live.settings = settings
        live.db = migrated(settings)
        yield live


def client(server, headers=ALICE) -> httpx.Client:
    return httpx.Client(base_url=server.url, headers=headers, timeout=30)


def upload(c: httpx.Client, path, texture=None, name=None):
    files = {"mesh": (name or path.name, path.read_bytes(), "application/octet-stream")}
    if texture is not None:
        files["texture"] = (texture.name, texture.read_bytes(), "image/png")
    return c.post("/v1/meshes", files=files)


def test_health_info_and_auth(server):
    with client(server, headers={}) as c:
        assert c.get("/v1/health").json() == {"status": "ok"}
        assert c.get("/v1/info").status_code == 401
        assert c.get("/v1/meshes", headers={"Authorization": "Bearer nope"}).status_code == 401
        assert c.get("/v1/meshes", headers={"Authorization": "Basic abc"}).status_code == 401
    with client(server) as c:
        info = c.get("/v1/info").json()
        assert info["owner"] == "alice" and info["limits"]["max_batch_points"] == 1000
        assert set(info["queue"]) == {"queued", "running"}


def test_upload_validate_dedup_list_delete(server, mesh_files):
    with client(server) as c:
        r = upload(c, mesh_files["blob"], texture=mesh_files["png"])
        assert r.status_code == 201, r.text
        rec = r.json()
        assert rec["has_texture"] and rec["n_faces"] == 80 and rec["n_vertices"] == 42
        again = upload(c, mesh_files["blob"], texture=mesh_files["png"])
        assert again.status_code == 200 and again.json()["id"] == rec["id"]
        other_tex = upload(c, mesh_files["blob"], texture=mesh_files["black"])
        assert other_tex.status_code == 201 and other_tex.json()["id"] != rec["id"]
        # same geometry, same content hash (keys the spectra cache)
        assert other_tex.json()["content_hash"] == rec["content_hash"]
        ids = [m["id"] for m in c.get("/v1/meshes").json()["items"]]
        assert rec["id"] in ids
        assert c.get(f"/v1/meshes/{rec['id']}").json() == rec
        assert c.delete(f"/v1/meshes/{other_tex.json()['id']}").status_code == 204
        assert c.get(f"/v1/meshes/{other_tex.json()['id']}").status_code == 404


def test_a_glb_with_several_materials_uploads_textured(server, tmp_path):
    """Over REST a GLB carries all its materials (an OBJ arrives without its MTL): two
    primitives, a textured one and a plain colour, upload as one textured mesh."""
    import trimesh
    from PIL import Image

    from hktex_engine.evaluation.synthetic import icosphere

    v, f = icosphere(1)
    scene = trimesh.Scene()
    for part, faces in enumerate((f[: len(f) // 2], f[len(f) // 2 :])):
        split_v = v[faces].reshape(-1, 3)
        uv = np.random.default_rng(part).uniform(0.1, 0.9, (len(split_v), 2))
        image = Image.fromarray(np.full((8, 8, 3), 200, np.uint8)) if part == 0 else None
        material = trimesh.visual.material.PBRMaterial(
            baseColorTexture=image, baseColorFactor=[1.0, 0.5 * part + 0.5, 1.0, 1.0]
        )
        visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
        tri = np.arange(len(split_v)).reshape(-1, 3)
        scene.add_geometry(trimesh.Trimesh(split_v, tri, visual=visual, process=False))
    scene.export(tmp_path / "two.glb")
    with client(server) as c:
        r = upload(c, tmp_path / "two.glb")
        assert r.status_code == 201, r.text
        assert r.json()["has_texture"] and r.json()["n_faces"] == len(f)


def test_concurrent_identical_uploads_get_one_id(server, mesh_files):
    from concurrent.futures import ThreadPoolExecutor

    def send(_):
        with client(server, BOB) as c:
            return upload(c, mesh_files["blob"], name="same.obj")

    with ThreadPoolExecutor(4) as pool:
        answers = list(pool.map(send, range(4)))
    assert {r.status_code for r in answers} <= {200, 201}
    assert [r.status_code for r in answers].count(201) == 1
    assert len({r.json()["id"] for r in answers}) == 1


def test_owner_isolation(server, mesh_files):
    with client(server) as alice, client(server, BOB) as bob:
        mid = upload(alice, mesh_files["patch"]).json()["id"]
        assert bob.get(f"/v1/meshes/{mid}").status_code == 404
        assert bob.delete(f"/v1/meshes/{mid}").status_code == 404
        assert bob.post(f"/v1/meshes/{mid}/spectra", json={}).status_code == 404
        assert mid not in [m["id"] for m in bob.get("/v1/meshes").json()["items"]]
        r = bob.post("/v1/jobs", json={"mesh_id": mid, "task": "fit_uv"})
        assert r.status_code == 404
        spectra = alice.post(f"/v1/meshes/{mid}/spectra", json={"k": 8, "k_iso": 5}).json()
        assert bob.get(f"/v1/spectra/{spectra['id']}").status_code == 404
        jid = add_sleep_job(server.db, owner="alice")
        assert bob.get(f"/v1/jobs/{jid}").status_code == 404
        assert bob.post(f"/v1/jobs/{jid}/cancel").status_code == 404
        assert bob.get(f"/v1/jobs/{jid}/events").status_code == 404
        assert bob.get("/v1/kernelsets/kst_x").status_code == 404
        alice.post(f"/v1/jobs/{jid}/cancel")


def test_spectra_requests_share_one_job(server, mesh_files):
    with client(server) as alice, client(server, BOB) as bob:
        mid = upload(alice, mesh_files["patch"]).json()["id"]
        first = alice.post(f"/v1/meshes/{mid}/spectra", json={"angles": 3, "k": 8, "k_iso": 5})
        assert first.status_code == 202 and first.json()["state"] == "queued"
        second = alice.post(f"/v1/meshes/{mid}/spectra", json={"k": 8, "k_iso": 5, "angles": 3})
        assert second.json()["id"] == first.json()["id"]
        assert second.json()["job_id"] == first.json()["job_id"]
        # bob uploads the same geometry: he shares the spectra record
        bob_mid = upload(bob, mesh_files["patch"]).json()["id"]
        theirs = bob.post(f"/v1/meshes/{bob_mid}/spectra", json={"angles": 3, "k": 8, "k_iso": 5})
        assert theirs.json()["id"] == first.json()["id"]
        bad = alice.post(f"/v1/meshes/{mid}/spectra", json={"anisotropies": [5, 1]})
        assert bad.status_code == 422 and "ascending" in bad.json()["detail"]
        assert alice.post(f"/v1/meshes/{mid}/spectra", json={"k": "x"}).status_code == 422
        assert alice.post(f"/v1/meshes/{mid}/spectra", json={"kk": 3}).status_code == 422


@pytest.mark.parametrize(
    "payload,what",
    [
        (b"\x00\x01garbage" * 100, "binary garbage"),
        (b"v 0 0 0\nv 1 0 0\nf 1 2 3\n", "face indexes a missing vertex"),
        (b"v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n", "NaN vertex"),
        (b"", "empty file"),
        (b"solid x\nendsolid x\n", "empty STL"),
    ],
)
def test_hostile_meshes_are_422(server, payload, what):
    with client(server) as c:
        r = c.post("/v1/meshes", files={"mesh": ("bad.obj", payload, "text/plain")})
        assert r.status_code == 422, (what, r.text)
        assert r.json()["detail"]
        assert c.get("/v1/health").status_code == 200


def test_hostile_uploads(server, mesh_files):
    with client(server) as c:
        big = c.post("/v1/meshes", files={"mesh": ("big.obj", b"v 0 0 0\n" * 200_000)})
        assert big.status_code == 413

        # streamed without Content-Length: the counting stops it all the same
        def chunks():
            yield b'--b\r\nContent-Disposition: form-data; name="mesh"; filename="m.obj"\r\n\r\n'
            for _ in range(200):
                yield b"v 0 0 0\n" * 1000

        r = c.post(
            "/v1/meshes",
            content=chunks(),
            headers={"Content-Type": "multipart/form-data; boundary=b"},
        )
        assert r.status_code == 413
        assert c.post("/v1/meshes", json={"mesh": "x"}).status_code == 415
        assert c.post(
            "/v1/meshes",
            content=b"junk",
            headers={"Content-Type": "multipart/form-data; boundary=zz"},
        ).status_code in (400, 422)
        no_mesh = c.post("/v1/meshes", files={"texture": ("t.png", b"123")})
        assert no_mesh.status_code == 422
        odd = c.post("/v1/meshes", files={"mesh": ("evil.exe", b"v 0 0 0\n")})
        assert odd.status_code == 422
        bad_tex = upload(c, mesh_files["blob"], texture=mesh_files["blob"])
        assert bad_tex.status_code == 422
        too_many = c.post(
            "/v1/meshes", files={"mesh": ("big.obj", _grid_obj(80))}
        )  # 6561 vertices > 5000
        assert too_many.status_code == 422 and "vert" in too_many.json()["detail"].lower()
        assert c.get("/v1/health").status_code == 200


def _grid_obj(n: int) -> bytes:
    from hktex_engine.evaluation.synthetic import grid_patch

    v, f = grid_patch(n, n)
    lines = [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in v] + [
        f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f
    ]
    return ("\n".join(lines) + "\n").encode()


def _zip(members: dict[str, bytes], compression=zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=compression) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def test_hostile_archives(server):
    with client(server) as c:

        def post(data: bytes):
            return c.post("/v1/views", files={"archive": ("v.zip", data, "application/zip")})

        bomb = _zip(
            {"views.json": b"{}", "a.bin": b"\0" * 5_000_000}
        )  # ~5 KB packed, 50x the limit
        assert len(bomb) < 1_000_000
        assert post(bomb).status_code == 413
        assert post(_zip({"../../escape.txt": b"x"})).status_code == 422
        assert post(_zip({"/abs.txt": b"x"})).status_code == 422
        assert post(b"PK\x03\x04 not really a zip").status_code == 422
        not_views = post(_zip({"views.json": b'{"format": "nope"}'}))
        assert not_views.status_code == 422 and "views" in not_views.json()["detail"].lower()
        assert c.get("/v1/health").status_code == 200


def test_hostile_jobs_and_queries(server, mesh_files):
    with client(server) as c:
        mid = upload(c, mesh_files["patch"]).json()["id"]
        assert (
            c.post("/v1/jobs", json={"mesh_id": mid, "task": "fit_uv"}).status_code == 422
        )  # no texture
        assert c.post("/v1/jobs", json={"mesh_id": mid, "task": "sleep"}).status_code == 422
        assert c.post("/v1/jobs", json={"mesh_id": mid, "task": "fit_multiview"}).status_code == 422
        assert c.post("/v1/jobs", json={"mesh_id": mid, "params": {"steps": -1}}).status_code == 422
        assert c.post("/v1/jobs", json={"mesh_id": mid, "params": {"bogus": 1}}).status_code == 422
        bad_blend = {"mesh_id": mid, "params": {"blend": "multiply"}}
        assert c.post("/v1/jobs", json=bad_blend).status_code == 422
        assert (
            c.post(
                "/v1/jobs", content=b"{not json", headers={"Content-Type": "application/json"}
            ).status_code
            == 422
        )
        assert c.post("/v1/jobs", json={"mesh_id": "msh_nope"}).status_code == 404
        q = "/v1/kernelsets/kst_nope/albedo"
        assert c.post(q, json={"face_ids": [0], "barycentrics": [[1, 0, 0]]}).status_code == 404
        assert (
            c.post(q, content=b"NaN", headers={"Content-Type": "application/json"}).status_code
            == 422
        )
        nan = b'{"face_ids": [0], "barycentrics": [[NaN, 0, 1]]}'
        assert (
            c.post(q, content=nan, headers={"Content-Type": "application/json"}).status_code == 422
        )
        assert c.post(q, json={"face_ids": [0]}).status_code == 422
        assert c.post(q, json={"points": [[0, 0]]}).status_code == 422
        assert c.post(q, content=b"x", headers={"Content-Type": "text/plain"}).status_code == 415
        npy = {"Content-Type": "application/x-npy"}
        assert c.post(q, content=b"\x93NUMPY garbage", headers=npy).status_code == 422
        buf = io.BytesIO()
        np.save(buf, np.zeros((3, 5)))
        assert c.post(q, content=buf.getvalue(), headers=npy).status_code == 422
        buf = io.BytesIO()
        np.save(buf, np.array([{"a": 1}], dtype=object), allow_pickle=True)
        assert c.post(q, content=buf.getvalue(), headers=npy).status_code == 422
        buf = io.BytesIO()
        np.save(buf, np.zeros((5000, 4)))
        assert c.post(q, content=buf.getvalue(), headers=npy).status_code == 413
        huge = json.dumps({"points": [[0.0, 0.0, 0.0]] * 5000})
        assert (
            c.post(q, content=huge, headers={"Content-Type": "application/json"}).status_code == 413
        )
        assert c.get("/v1/kernelsets/kst_nope/render?width=99999").status_code == 422
        assert c.get("/v1/health").status_code == 200


def test_job_cap_per_owner(server, mesh_files):
    with client(server, BOB) as bob:
        mid = upload(bob, mesh_files["blob"], texture=mesh_files["png"]).json()["id"]
        ids = [add_sleep_job(server.db, owner="bob") for _ in range(5)]
        r = bob.post("/v1/jobs", json={"mesh_id": mid, "task": "fit_uv"})
        assert r.status_code == 429 and "at most 5" in r.json()["detail"]
        for jid in ids:
            assert bob.post(f"/v1/jobs/{jid}/cancel").json()["state"] == "cancelled"


def test_cancel_and_events_over_http(server):
    db = server.db
    jid = add_sleep_job(db, owner="alice", priority=50, steps=100, seconds=30)
    with client(server) as c, SupervisorInThread(server.settings):
        wait_for(lambda: c.get(f"/v1/jobs/{jid}").json()["progress"]["step"] > 0, 30, "progress")
        events = []
        with c.stream("GET", f"/v1/jobs/{jid}/events") as resp:
            assert resp.headers["content-type"].startswith("text/event-stream")
            name = None
            for line in resp.iter_lines():
                if line.startswith("event:"):
                    name = line.split(":", 1)[1].strip()
                elif line.startswith("data:"):
                    events.append((name, json.loads(line[5:])))
                    if len(events) == 2:
                        assert c.post(f"/v1/jobs/{jid}/cancel").json()["state"] == "cancelling"
                    if name == "end":
                        break
        assert events[0][0] == "progress" and events[-1][0] == "end"
        assert events[-1][1]["state"] == "cancelled"
        steps = [e[1]["progress"]["step"] for e in events if e[0] == "progress"]
        assert steps == sorted(steps)
        listed = c.get("/v1/jobs", params={"state": "cancelled"}).json()["items"]
        assert jid in [j["id"] for j in listed]


def test_bind_policy():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0")
    Settings(host="127.0.0.1").check_bind()
    Settings(host="0.0.0.0", tokens="t:o").check_bind()
    with pytest.raises(ValueError, match="refusing"):
        Settings(host="0.0.0.0").check_bind()
    with pytest.raises(ValueError, match="token:owner"):
        Settings(tokens="justatoken").token_owners()


def test_anonymous_local_owner_without_tokens(tmp_path, mesh_files):
    settings = fast_settings(tmp_path, f"sqlite:///{tmp_path / 'x.db'}")
    with LiveServer(settings) as live, httpx.Client(base_url=live.url) as c:
        assert c.get("/v1/info").json()["owner"] == "local"
        assert upload(c, mesh_files["patch"]).status_code == 201


def test_cli_refuses_public_bind_without_tokens(tmp_path, capsys):
    from hktex_engine.cli import main

    rc = main(["serve", "--host", "0.0.0.0", "--data-dir", str(tmp_path)])
    assert rc == 2
    assert "refusing to bind" in capsys.readouterr().err
