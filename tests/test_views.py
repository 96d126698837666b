"""View datasets: writing reference views, loading them back, refusing malformed ones."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from hktex_engine.errors import ViewsError
from tests.demo_support import demo_arrays, require_render

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    from hktex_engine.fitting.views import render_reference_views
    from hktex_engine.geometry.mesh import mesh_from_arrays

    require_render()
    V, F, uv, tex = demo_arrays()
    mesh = mesh_from_arrays(V, F, uv, tex)
    out = tmp_path_factory.mktemp("views") / "ds"
    return render_reference_views(mesh, out, n_views=3, resolution=(20, 16), spp=4)


def _copy(dataset: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "copy"
    shutil.copytree(dataset, dst)
    return dst


def _edit(root: Path, fn) -> None:
    manifest = json.loads((root / "views.json").read_text())
    fn(manifest)
    (root / "views.json").write_text(json.dumps(manifest))


def test_roundtrip(dataset):
    from hktex_engine.fitting.views import load_views

    views = load_views(dataset)
    assert len(views) == 3
    assert views.images.shape == (3, 16, 20, 3)
    assert views.masks.shape == (3, 16, 20) and all(views.has_mask)
    assert 0 < views.masks.mean() < 1
    # background pixels show the white environment, the object is darker
    assert views.images[~views.masks].mean() > 0.95
    assert views.images[views.masks].mean() < views.images[~views.masks].mean()
    sub = views.subset([2, 0])
    assert sub.names == [views.names[2], views.names[0]]


def test_origin_target_camera_equals_to_world(dataset, tmp_path):
    from hktex_engine.fitting.views import load_views
    from hktex_engine.render.mitsuba import look_at

    root = _copy(dataset, tmp_path)
    cam = look_at([0, 0, 5], [0, 0, 0], [0, 1, 0], fov=30)

    def put(m):
        m["views"][0]["camera"] = {"origin": [0, 0, 5], "target": [0, 0, 0], "fov": 30}

    _edit(root, put)
    assert np.allclose(load_views(root).cameras[0].to_world, cam.to_world)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda m: m["views"][1].pop("camera"), "no camera"),
        (lambda m: m["views"][0]["camera"].update(to_world=[[1, 0], [0, 1]]), "4x4"),
        (lambda m: m["views"][0]["camera"].update(fov=0), "fov"),
        (lambda m: m.update(views=[]), "no views"),
        (lambda m: m.update(format="other"), "hktex-views"),
        (lambda m: m.update(width=21), "views.json says"),
        (lambda m: m["views"][2].update(image="nope.png"), "missing"),
    ],
)
def test_bad_manifest(dataset, tmp_path, mutate, message):
    from hktex_engine.fitting.views import load_views

    root = _copy(dataset, tmp_path)
    _edit(root, mutate)
    with pytest.raises(ViewsError, match=message):
        load_views(root)


def test_bad_files(dataset, tmp_path):
    from hktex_engine.fitting.views import load_views

    with pytest.raises(ViewsError, match="does not exist"):
        load_views(tmp_path / "absent")
    root = _copy(dataset, tmp_path)
    m = json.loads((root / "views.json").read_text())
    Image.fromarray(np.zeros((16, 20), np.uint8)).save(root / m["views"][0]["mask"])
    with pytest.raises(ViewsError, match="mask is empty"):
        load_views(root)
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(root / m["views"][0]["mask"])
    with pytest.raises(ViewsError, match="mask size"):
        load_views(root)
    (root / m["views"][0]["mask"]).write_bytes(b"not a png")
    with pytest.raises(ViewsError, match="not a readable image"):
        load_views(root)
    (root / "views.json").write_text("{")
    with pytest.raises(ViewsError, match="not valid JSON"):
        load_views(root)
    (root / "views.json").unlink()
    with pytest.raises(ViewsError, match="no views.json"):
        load_views(root)
