"""The whole path through the service with the real engine: upload -> spectra -> fit ->
query -> download, on a small textured mesh with a tiny grid and few steps.

The colours the service answers are checked against an independent local computation: the
downloaded ``.hkt`` and spectra archive evaluated with the engine's ``AlbedoQuery`` in this
process (so storage, transport and both body formats must all be lossless).
"""

from __future__ import annotations

import io
import zipfile

import httpx
import numpy as np
import pytest

from tests.server_support import LiveServer, fast_settings, wait_for

pytest.importorskip("hktex_engine.fitting.uv")
pytest.importorskip("hktex_engine.kernels.query")

SPECTRA = {"angles": 3, "anisotropies": [1, 5], "k": 16, "k_iso": 8}
PARAMS = {
    "kernels": 24,
    "steps": 12,
    "points_per_step": 128,
    "seed": 1,
    "checkpoint_every": 5,
    "eval_points": 2000,
}


@pytest.fixture(scope="module")
def textured(tmp_path_factory):
    from hktex_engine.evaluation.synthetic import textured_demo, write_textured_obj

    root = tmp_path_factory.mktemp("e2e")
    v, f, uvs, tex = textured_demo(subdivisions=2, texture_size=32)
    obj = write_textured_obj(root / "blob.obj", v, f, uvs, tex)
    return obj, root / "blob_albedo.png"


def test_upload_spectra_fit_query_download(tmp_path, textured):
    from hktex_engine.geometry.sampling import points_from_barycentric, sample_surface
    from hktex_engine.kernels.hkt import load_hkt
    from hktex_engine.kernels.query import AlbedoQuery
    from hktex_engine.spectra.grid import load_spectra

    obj, png = textured
    settings = fast_settings(tmp_path, f"sqlite:///{tmp_path / 'hktex.db'}", workers=1)
    with LiveServer(settings, start_supervisor=True) as live:
        c = httpx.Client(base_url=live.url, timeout=60)
        files = {"mesh": (obj.name, obj.read_bytes()), "texture": (png.name, png.read_bytes())}
        mesh = c.post("/v1/meshes", files=files).json()
        assert mesh["has_texture"]
        job = c.post(
            "/v1/jobs",
            json={"mesh_id": mesh["id"], "task": "fit_uv", "spectra": SPECTRA, "params": PARAMS},
        )
        assert job.status_code == 202, job.text
        job = job.json()
        done = wait_for(
            lambda: (
                (r := c.get(f"/v1/jobs/{job['id']}").json())["state"]
                in ("succeeded", "failed", "cancelled")
                and r
            ),
            300,
            "the fit",
        )
        assert done["state"] == "succeeded", done["error"]
        assert done["progress"]["step"] == done["progress"]["total"] > 0
        # cleaned up by the worker just after it writes the final state (so: soon, not before)
        checkpoints = settings.data_dir / "checkpoints" / job["id"]
        wait_for(lambda: not checkpoints.exists(), 30, "the checkpoints to be removed")
        spectra = c.get(f"/v1/spectra/{done['spectra_id']}").json()
        assert spectra["state"] == "ready" and spectra["summary"]["k"] == SPECTRA["k"]
        # a second request for the same spectra is answered at once
        again = c.post(f"/v1/meshes/{mesh['id']}/spectra", json=SPECTRA)
        assert again.status_code == 200 and again.json()["id"] == spectra["id"]

        ks_id = done["result"]["kernelset_id"]
        ks = c.get(f"/v1/kernelsets/{ks_id}").json()
        assert ks["n_kernels"] > 0 and ks["bytes"] > 0
        # the whole loss curve, though progress was reported at most once a second
        curve = ks["metrics"]["loss_curve"]
        steps = done["progress"]["total"]
        assert len(curve) == min(steps, 200) and curve[-1][0] == steps
        assert all(a[0] < b[0] for a, b in zip(curve, curve[1:], strict=False))
        listed = c.get("/v1/kernelsets").json()["items"]  # lists stay small: no curves
        assert [k["id"] for k in listed] == [ks_id] and "loss_curve" not in listed[0]["metrics"]

        hkt = tmp_path / "k.hkt"
        hkt.write_bytes(c.get(f"/v1/kernelsets/{ks_id}/file").content)
        archive = c.get(f"/v1/spectra/{spectra['id']}/archive")
        assert archive.status_code == 200
        local_dir = tmp_path / "spectra"
        zipfile.ZipFile(io.BytesIO(archive.content)).extractall(local_dir)
        local_spectra = load_spectra(local_dir)
        local = AlbedoQuery(local_spectra, load_hkt(hkt))

        rng = np.random.default_rng(0)
        faces, bary = sample_surface(local_spectra.vertices, local_spectra.faces, 300, rng)
        expected = local.colors(faces, bary)

        by_json = c.post(
            f"/v1/kernelsets/{ks_id}/albedo",
            json={"face_ids": faces.tolist(), "barycentrics": bary.tolist()},
        ).json()
        assert by_json["count"] == 300
        np.testing.assert_allclose(np.asarray(by_json["colors"]), expected, atol=1e-6)

        rows = np.column_stack([faces.astype(np.float64), bary])
        buf = io.BytesIO()
        np.save(buf, rows)
        r = c.post(
            f"/v1/kernelsets/{ks_id}/albedo",
            content=buf.getvalue(),
            headers={"Content-Type": "application/x-npy", "Accept": "application/x-npy"},
        )
        assert r.headers["content-type"] == "application/x-npy"
        by_npy = np.load(io.BytesIO(r.content), allow_pickle=False)
        assert by_npy.shape == (300, 3) and by_npy.dtype == np.float32
        np.testing.assert_array_equal(by_npy, expected)

        # points in file units land on the same surface points
        pts_norm = points_from_barycentric(local_spectra.vertices, local_spectra.faces, faces, bary)
        pts_file = (pts_norm - local_spectra.translation) / local_spectra.scale
        buf = io.BytesIO()
        np.save(buf, pts_file)
        r = c.post(
            f"/v1/kernelsets/{ks_id}/albedo",
            params={"kind": "points"},
            content=buf.getvalue(),
            headers={"Content-Type": "application/x-npy", "Accept": "application/x-npy"},
        )
        np.testing.assert_allclose(np.load(io.BytesIO(r.content)), expected, atol=1e-4)

        png = c.get(f"/v1/kernelsets/{ks_id}/render", params={"width": 24, "height": 16, "spp": 1})
        assert png.status_code == 200, png.text
        assert (
            png.headers["content-type"] == "image/png" and png.content[:8] == b"\x89PNG\r\n\x1a\n"
        )
        assert int.from_bytes(png.content[16:20], "big") == 24  # IHDR width

        bad = c.post(
            f"/v1/kernelsets/{ks_id}/albedo",
            json={"face_ids": [len(local_spectra.faces)], "barycentrics": [[1, 0, 0]]},
        )
        assert bad.status_code == 422 and "out of range" in bad.json()["detail"]
        assert c.get("/v1/health").status_code == 200
        c.close()


@pytest.mark.slow
def test_multiview_fit_through_the_service(tmp_path, textured):
    """Views rendered from the textured mesh, zipped, uploaded, fitted as a multi-view job."""
    from hktex_engine.fitting.views import render_reference_views
    from hktex_engine.geometry.mesh import load_mesh

    obj, png = textured
    views_dir = render_reference_views(
        load_mesh(obj, texture=png), tmp_path / "views", n_views=2, resolution=(32, 32), spp=4
    )
    archive = tmp_path / "views.zip"
    with zipfile.ZipFile(archive, "w") as zf:
        for f in sorted(views_dir.iterdir()):
            zf.write(f, arcname=f"views/{f.name}")
    settings = fast_settings(tmp_path, f"sqlite:///{tmp_path / 'hktex.db'}", workers=1)
    with LiveServer(settings, start_supervisor=True) as live:
        c = httpx.Client(base_url=live.url, timeout=60)
        mesh = c.post("/v1/meshes", files={"mesh": (obj.name, obj.read_bytes())}).json()
        views = c.post("/v1/views", files={"archive": ("v.zip", archive.read_bytes())})
        assert views.status_code == 201, views.text
        assert views.json()["n_files"] == len(list(views_dir.iterdir()))
        body = {
            "mesh_id": mesh["id"],
            "task": "fit_multiview",
            "views_id": views.json()["id"],
            "spectra": SPECTRA,
            "params": {"kernels": 16, "steps": 3, "seed": 0},
        }
        job = c.post("/v1/jobs", json=body)
        assert job.status_code == 202, job.text
        done = wait_for(
            lambda: (
                (r := c.get(f"/v1/jobs/{job.json()['id']}").json())["state"]
                in ("succeeded", "failed", "cancelled")
                and r
            ),
            600,
            "the multi-view fit",
        )
        assert done["state"] == "succeeded", done["error"]
        ks = c.get(f"/v1/kernelsets/{done['result']['kernelset_id']}").json()
        assert ks["n_kernels"] > 0 and ks["manifest"]["task"] == "fit_multiview"
        c.close()
