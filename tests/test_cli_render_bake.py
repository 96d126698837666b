"""``hktex render`` and ``hktex bake`` end to end on tiny files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from hktex_engine.errors import RenderError


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from hktex_engine.config import SpectralConfig
    from hktex_engine.hkt import save_hkt
    from hktex_engine.kernels import KernelSet
    from hktex_engine.mesh import load_mesh
    from hktex_engine.sampling import sample_surface
    from hktex_engine.spectra import compute_spectra, write_spectra
    from hktex_engine.synthetic import textured_demo, write_textured_obj

    root = tmp_path_factory.mktemp("cli")
    V, F, uv, tex = textured_demo(subdivisions=2, texture_size=32)
    obj = write_textured_obj(root / "m.obj", V, F, uv, tex)
    mesh = load_mesh(obj)
    spectra = compute_spectra(
        mesh, SpectralConfig(angles=3, anisotropies=(1.0, 5.0), k=16, k_iso=9)
    )
    sdir = write_spectra(spectra, root / "spectra")
    rng = np.random.default_rng(0)
    n = 40
    f, b = sample_surface(spectra.vertices, spectra.faces, n, rng)
    ks = KernelSet(
        face_ids=f,
        barycentrics=b,
        theta=rng.uniform(0, np.pi, n),
        eta=1 + 99 * rng.random(n),
        threshold=rng.uniform(0.5, 0.9, n),
        sharpness=10 + 40 * rng.random(n),
        colors=rng.uniform(-0.5, 0.5, (n, 3)),
        base_color=np.array([0.5, 0.4, 0.3]),
        mesh_hash=spectra.mesh_hash,
        config_hash=spectra.config_hash,
    )
    hkt = save_hkt(ks, root / "k.hkt")
    return root, obj, sdir, hkt


@pytest.mark.mitsuba
def test_cli_render(files, capsys):
    from hktex_engine import render
    from hktex_engine.cli import main

    try:
        render.ensure_variant()
    except RenderError as exc:
        pytest.skip(f"no Mitsuba AD variant: {exc}")
    root, _, sdir, hkt = files
    out = root / "r.png"
    argv = [
        "render",
        str(hkt),
        "--spectra",
        str(sdir),
        "-o",
        str(out),
        "--width",
        "20",
        "--height",
        "16",
        "--view",
        "45,10",
        "--spp",
        "2",
        "--json",
    ]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["render_seconds"] > 0
    img = np.asarray(Image.open(out))
    assert img.shape == (16, 20, 3)
    assert (img[0, 0] == 255).all()  # the corner sees the white environment
    assert main(["render", str(root / "none.hkt"), "--spectra", str(sdir), "-o", str(out)]) == 2
    assert main(argv[:-1] + ["--view", "a,b"]) == 2


def test_cli_bake(files, capsys):
    from hktex_engine.cli import main

    root, obj, sdir, hkt = files
    out = root / "t.png"
    argv = [
        "bake",
        str(hkt),
        "--spectra",
        str(sdir),
        "--mesh",
        str(obj),
        "-o",
        str(out),
        "--resolution",
        "64",
        "--glb",
        str(root / "t.glb"),
        "--obj",
        str(root / "t.obj"),
        "--json",
    ]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["atlas"] == "mesh" and len(summary["files"]) == 3
    assert np.asarray(Image.open(out)).shape == (64, 64, 3)
    assert (root / "t.glb").stat().st_size > 0 and (root / "t.mtl").is_file()
    vc = [
        "bake",
        str(hkt),
        "--spectra",
        str(sdir),
        "--mesh",
        str(obj),
        "-o",
        str(out),
        "--resolution",
        "16",
        "--obj",
        str(root / "v.obj"),
        "--vertex-colors",
    ]
    assert main(vc) == 0
    first_v = next(
        line for line in (root / "v.obj").read_text().splitlines() if line.startswith("v ")
    )
    assert len(first_v.split()) == 7  # x y z r g b
