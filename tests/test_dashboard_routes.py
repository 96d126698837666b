"""The dashboard's server side without a browser: the page and offline docs are served from
the package, the list routes are owner-scoped, and the viewer's bake (GLB + kernel, original
and error layers) works on a tiny kernel set; plus the error-map maths."""

from __future__ import annotations

import io
import threading

import httpx
import numpy as np
import pytest
from PIL import Image

from tests.server_support import LiveServer, fast_settings, wait_for

ALICE = {"Authorization": "Bearer tok-alice"}
BOB = {"Authorization": "Bearer tok-bob"}


def test_heat_ramp_and_error_texture() -> None:
    from hktex_engine.render.errormap import error_texture, heat_colors, resample_texture

    ends = heat_colors(np.array([0.0, 1.0, 7.0]))
    assert ends[0].max() < 0.05 and ends[1].min() > 0.7 and np.allclose(ends[1], ends[2])
    ramp = heat_colors(np.linspace(0, 1, 50)).mean(axis=1)
    assert np.all(np.diff(ramp) > -1e-6), "brightness must grow along the ramp"
    tex = np.random.default_rng(0).random((8, 8, 3)).astype(np.float32)
    assert resample_texture(tex, 4).shape == (4, 4, 3)
    heat, rms = error_texture(tex, tex)
    assert rms == 0 and np.allclose(heat, heat_colors(np.zeros(1))[0])
    covered = np.zeros((8, 8), bool)
    covered[:4] = True
    wrong = tex.copy()
    wrong[4:] = 1 - wrong[4:]  # errors only where no triangle is: not surface, not counted
    heat, rms = error_texture(wrong, tex, covered=covered)
    assert rms == 0 and np.allclose(heat[4:], heat[:4].mean(axis=(0, 1)), atol=1e-6)


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dash")
    settings = fast_settings(
        tmp, f"sqlite:///{tmp / 'hktex.db'}", tokens="tok-alice:alice,tok-bob:bob"
    )
    with LiveServer(settings) as server:
        server.settings = settings
        yield server


def _kernelset_for(live, tmp_path) -> str:
    """Upload a textured blob as alice; give it ready spectra and a random kernel set,
    written straight into the service's store and tables (no fit: seconds, not minutes)."""
    from hktex_server.storage.blobs import BlobStore
    from hktex_server.storage.db import Database, KernelSetRow, SpectraRow, new_id, now

    from hktex_engine.evaluation.synthetic import textured_demo, write_textured_obj
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.spectra.grid import SpectraCache
    from tests.demo_support import DEMO_CONFIG, random_kernelset

    # Two subdivisions: at one, 15 % of the blob's UV area lies outside [0, 1], and the bake
    # rightly takes a fresh atlas there (no original / error layers to compare).
    obj = write_textured_obj(tmp_path / "blob.obj", *textured_demo(2, 32))
    png = obj.with_name("blob_albedo.png")
    with httpx.Client(base_url=live.url, headers=ALICE, timeout=60) as c:
        files = {"mesh": ("blob.obj", obj.read_bytes()), "texture": ("t.png", png.read_bytes())}
        mesh = c.post("/v1/meshes", files=files).json()
    store = BlobStore(live.settings.data_dir)
    spectra = SpectraCache(store.root / "spectra").get_or_compute(
        load_mesh(obj, texture=png), DEMO_CONFIG
    )
    tmp_hkt = store.temp_path(".hkt")
    save_hkt(random_kernelset(spectra, 24), tmp_hkt)
    rel, _, size = store.publish_file(tmp_hkt, "kernelsets", ".hkt")
    db = Database(live.settings.resolved_database_url())
    t = now()
    spectra_id, ks_id = new_id("spc"), new_id("kst")
    with db.write() as s:
        s.add(
            SpectraRow(
                id=spectra_id,
                mesh_hash=mesh["content_hash"],
                config_hash=DEMO_CONFIG.key(),
                config=DEMO_CONFIG.to_dict(),
                state="ready",
                path=store.rel(spectra.path),
                created_at=t,
                updated_at=t,
            )
        )
        s.add(
            KernelSetRow(
                id=ks_id,
                owner="alice",
                mesh_id=mesh["id"],
                spectra_id=spectra_id,
                path=rel,
                bytes=size,
                n_kernels=24,
                metrics={"surface_psnr": 12.5},
                manifest={},
                created_at=t,
            )
        )
    db.dispose()
    return ks_id


def test_page_static_and_offline_docs(live) -> None:
    with httpx.Client(base_url=live.url, timeout=30) as c:
        page = c.get("/")
        assert page.status_code == 200 and "text/html" in page.headers["content-type"]
        assert "/static/dashboard.js" in page.text and "model-viewer.min.js" in page.text
        for path in ("/static/dashboard.js", "/static/vendor/model-viewer/model-viewer.min.js"):
            assert c.get(path).status_code == 200
        docs, redoc = c.get("/docs").text, c.get("/redoc").text
        assert "/static/vendor/swagger-ui/swagger-ui-bundle.js" in docs and "cdn" not in docs
        assert (
            "/static/vendor/redoc/redoc.standalone.js" in redoc and "fonts.googleapis" not in redoc
        )
        assert c.get("/static/vendor/redoc/redoc.standalone.js").status_code == 200
        assert "/v1/kernelsets/{kernelset_id}/glb" in c.get("/openapi.json").json()["paths"]


def test_lists_are_owner_scoped_and_bake_serves_viewer_layers(live, tmp_path) -> None:
    ks_id = _kernelset_for(live, tmp_path)
    with (
        httpx.Client(base_url=live.url, headers=ALICE, timeout=120) as alice,
        httpx.Client(base_url=live.url, headers=BOB, timeout=30) as bob,
    ):
        assert [k["id"] for k in alice.get("/v1/kernelsets").json()["items"]] == [ks_id]
        assert len(alice.get("/v1/spectra").json()["items"]) == 1
        assert bob.get("/v1/kernelsets").json()["items"] == []
        assert bob.get("/v1/spectra").json()["items"] == []
        assert bob.get(f"/v1/kernelsets/{ks_id}/bake").status_code == 404
        assert httpx.get(f"{live.url}/v1/kernelsets").status_code == 401

        info = alice.get(f"/v1/kernelsets/{ks_id}/bake", params={"resolution": 256}).json()
        assert info["layers"] == ["kernel", "original", "error"] and info["atlas"] == "mesh"
        assert 0 < info["coverage"] <= 1 and info["error_rms"] > 0
        glb = alice.get(f"/v1/kernelsets/{ks_id}/glb", params={"resolution": 256})
        assert glb.headers["content-type"] == "model/gltf-binary" and glb.content[:4] == b"glTF"
        for layer in info["layers"]:
            r = alice.get(f"/v1/kernelsets/{ks_id}/textures/{layer}", params={"resolution": 256})
            assert r.status_code == 200, r.text
            assert Image.open(io.BytesIO(r.content)).size == (256, 256)
        again = alice.get(f"/v1/kernelsets/{ks_id}/bake", params={"resolution": 256}).json()
        assert again["seconds"] == info["seconds"], "the second look must reuse the bake"
        assert alice.get(f"/v1/kernelsets/{ks_id}/textures/nope").status_code == 422
        assert (
            alice.get(f"/v1/kernelsets/{ks_id}/glb", params={"resolution": 333}).status_code == 422
        )


def test_client_reaches_the_dashboard_routes(live, tmp_path) -> None:
    from hktex_client import BakeInfo, Client, NotFound
    from hktex_server.api.assets import BakeInfo as ServerBakeInfo

    assert set(BakeInfo.model_fields) == set(ServerBakeInfo.model_fields)
    with Client(live.url, token="tok-alice", timeout=120) as alice:
        ks_id = alice.list_kernelsets()[0].id  # the previous test's
        assert alice.list_spectra()[0].state == "ready"
        info = alice.bake(ks_id, resolution=256)
        assert info.layers == ["kernel", "original", "error"] and info.resolution == 256
        glb = alice.download_glb(ks_id, tmp_path / "k.glb", resolution=256)
        assert glb.read_bytes()[:4] == b"glTF"
        assert alice.bake_layer(ks_id, "error", resolution=256)[:4] == b"\x89PNG"
    with Client(live.url, token="tok-bob") as bob, pytest.raises(NotFound):
        bob.bake(ks_id)


def test_bake_runs_in_a_compute_worker_under_the_time_budget(live, monkeypatch) -> None:
    """The bake is a compute-pool task: never run in the API process, one task for identical
    requests at once, and past the time budget the same 503 as a render (worker killed, its
    half-written temp directory removed)."""
    import hktex_engine.render.bake as bake_module

    def not_here(*_a, **_k):
        raise AssertionError("baked in the API process")

    monkeypatch.setattr(bake_module, "bake_texture", not_here)  # workers are other processes
    svc = live.server.config.app.state.svc
    kinds: list[str] = []
    submit = svc.compute.submit

    def spy(owner, kind, payload, cleanup=None):
        kinds.append(kind)
        return submit(owner, kind, payload, cleanup)

    monkeypatch.setattr(svc.compute, "submit", spy)
    tmp = live.settings.data_dir / "tmp"
    with httpx.Client(base_url=live.url, headers=ALICE, timeout=120) as alice:
        ks_id = alice.get("/v1/kernelsets").json()["items"][0]["id"]  # the earlier test's
        monkeypatch.setattr(svc.settings, "compute_timeout_seconds", 0.05)
        slow = alice.get(f"/v1/kernelsets/{ks_id}/bake", params={"resolution": 1024})
        render = alice.get(f"/v1/kernelsets/{ks_id}/render", params={"width": 32, "height": 32})
        assert slow.status_code == 503 and "retry-after" not in slow.headers, slow.text
        assert "ran past its time budget of 0.05 s" in slow.json()["detail"]
        assert render.status_code == 503, render.text
        if "renderer unavailable" not in render.text:  # else no render to compare with
            assert slow.json() == render.json(), "a bake over budget answers as a render does"
            assert "retry-after" not in render.headers
        wait_for(lambda: not any(p.is_dir() for p in tmp.iterdir()), 10, "the temp dir removed")
        monkeypatch.setattr(svc.settings, "compute_timeout_seconds", 120.0)
        kinds.clear()
        answers: list[httpx.Response] = []

        def bake512() -> None:
            params = {"resolution": 512}
            answers.append(
                httpx.get(
                    f"{live.url}/v1/kernelsets/{ks_id}/bake",
                    params=params,
                    headers=ALICE,
                    timeout=120,
                )
            )

        both = [threading.Thread(target=bake512) for _ in range(2)]
        for t in both:
            t.start()
        for t in both:
            t.join(120)
        assert [r.status_code for r in answers] == [200, 200], [r.text for r in answers]
        assert answers[0].json() == answers[1].json() and answers[0].json()["resolution"] == 512
        assert kinds == ["bake"], "identical bakes at once share one compute task"
        assert (
            alice.get(f"/v1/kernelsets/{ks_id}/glb", params={"resolution": 512}).status_code == 200
        )
        assert kinds == ["bake"], "a baked kernel set is read from derived/, not baked again"
