"""``hktex render`` and ``hktex bake`` end to end on tiny files."""

from __future__ import annotations

import json

import numpy as np
import pytest
from PIL import Image

from tests.demo_support import DEMO_CONFIG, demo_arrays, random_kernelset, require_render


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    from hktex_engine.evaluation.synthetic import write_textured_obj
    from hktex_engine.geometry.mesh import load_mesh
    from hktex_engine.kernels.hkt import save_hkt
    from hktex_engine.spectra.grid import compute_spectra, write_spectra

    root = tmp_path_factory.mktemp("cli")
    V, F, uv, tex = demo_arrays()
    obj = write_textured_obj(root / "m.obj", V, F, uv, tex)
    mesh = load_mesh(obj)
    spectra = compute_spectra(mesh, DEMO_CONFIG)
    sdir = write_spectra(spectra, root / "spectra")
    hkt = save_hkt(random_kernelset(spectra, 40), root / "k.hkt")
    return root, obj, sdir, hkt


@pytest.mark.mitsuba
def test_cli_render(files, capsys):
    from hktex_engine.cli import main

    require_render()
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
    bake = ["bake", str(hkt), "--spectra", str(sdir), "--mesh", str(obj), "-o", str(out)]
    argv = [
        *bake,
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
        *bake,
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


@pytest.mark.parametrize("command", ["bake", "fit", "spectra"])
def test_cli_max_vertices_is_one_option_everywhere(files, capsys, command):
    """Every command that reads a mesh file takes the same limit: below the mesh's vertex
    count it refuses in one line (the default admits it: test_cli_bake and the fits)."""
    from hktex_engine.cli import main
    from hktex_engine.geometry.mesh import load_mesh

    root, obj, sdir, hkt = files
    n = load_mesh(obj).n_vertices
    argv = {
        "bake": ["bake", str(hkt), "--spectra", str(sdir), "--mesh", str(obj)],
        "fit": ["fit", str(obj), "--spectra", str(sdir), "--steps", "2", "--kernels", "20"],
        "spectra": ["spectra", str(obj)],
    }[command]
    out = root / f"limit.{command}"
    assert main([*argv, "-o", str(out), "--max-vertices", str(n - 1)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"exceeds the limit of {n - 1}" in err
    assert err.endswith("(raise it with --max-vertices)")
    assert not out.exists()
