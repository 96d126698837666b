"""The layered blend (``kernels.blending``): every evaluation path against an independent numpy
reading, its limits (equal priorities give the paper's blend; a high priority wins), its
gradient against finite differences, its storage and a fit that trains it."""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import replace

import numpy as np
import pytest
import torch

from hktex_engine.errors import KernelSetError
from hktex_engine.kernels import blending
from hktex_engine.kernels.hkt import encode_hkt, load_hkt
from hktex_engine.spectra.interpolation import SpectralField
from tests.kernels_support import random_points
from tests.test_kernels import (
    CONFIG,
    assert_extension_member_checked,
    assert_float32_query_paths_match,
    assert_float64_paths_match,
    make_model,
    make_params,
    reference_albedo,
)

LAYERED = replace(CONFIG, blend="layered")


def layered_reference(rho: np.ndarray, kp: dict, k_c: int) -> np.ndarray:
    """The layered rule on the ``K_c`` largest responses, straight from its formula."""
    out = np.zeros((rho.shape[0], 3))
    for p in range(rho.shape[0]):
        top = np.argsort(-rho[p], kind="stable")[:k_c]
        r = rho[p, top]
        omega = r * np.exp(kp["priority"][top])
        share = omega / omega.sum() if omega.sum() > 0 else np.zeros_like(omega)
        mix = min(1.0, r.sum()) * (share[:, None] * kp["colors"][top]).sum(0)
        out[p] = np.clip(kp["base_color"] + mix, 0, 1)
    return out


@pytest.fixture(scope="module")
def layered_case(spectra):
    kp = make_params(spectra, 30, seed=2)
    kp["priority"] = np.random.default_rng(5).uniform(-4, 4, 30)
    face_ids, bary = random_points(spectra, 60, seed=4)
    _, rho = reference_albedo(spectra, kp, CONFIG, face_ids, bary)
    return kp, face_ids, bary, layered_reference(rho, kp, CONFIG.k_blend), rho


def test_every_float64_path_matches_the_numpy_reading(spectra, field64, layered_case):
    kp, face_ids, bary, ref, rho = layered_case
    paper = reference_albedo(spectra, kp, CONFIG, face_ids, bary)[0]
    assert np.abs(ref - paper).max() > 0.05, "priorities must change colours here"
    assert ((rho > 0).sum(axis=1) > 1).mean() > 0.5, "points must have overlapping kernels"
    assert_float64_paths_match(make_model(field64, kp, LAYERED), face_ids, bary, ref)


@pytest.mark.parametrize("fused", [True, False])
def test_float32_query_paths_match(layered_case, spectra, field64, fused, monkeypatch):
    """Candidate tables with the compiled blend (and its torch twin)."""
    kp, face_ids, bary, _, _ = layered_case
    assert_float32_query_paths_match(
        spectra, field64, kp, LAYERED, face_ids, bary, fused, "always", monkeypatch
    )


def test_equal_priorities_are_the_papers_blend(field64, layered_case):
    kp, face_ids, bary, _, _ = layered_case
    flat = dict(kp, priority=np.full(30, 3.7))
    with torch.no_grad():
        paper = make_model(field64, kp, CONFIG).albedo(face_ids, bary)
        got = make_model(field64, flat, LAYERED).albedo(face_ids, bary)
    np.testing.assert_allclose(got.numpy(), paper.numpy(), atol=1e-12)


def test_a_higher_priority_wins_where_kernels_overlap():
    rho = torch.tensor([[1.0, 1.0, 1.0, 0.5]], dtype=torch.float64)
    colors = torch.tensor([[[0.4, 0, 0], [0, 0.4, 0], [0, 0, 0.4], [0.2, 0.2, 0.2]]])
    base = torch.tensor([0.3, 0.3, 0.3], dtype=torch.float64)
    paper = blending.albedo(rho, colors.double(), base, None)
    np.testing.assert_allclose(paper.numpy(), [[0.3 + 0.5 / 3.5] * 3], atol=1e-12)
    prio = torch.tensor([[8.0, -8.0, -8.0, -8.0]], dtype=torch.float64)
    top = blending.albedo(rho, colors.double(), base, prio)
    np.testing.assert_allclose(top.numpy(), [[0.7, 0.3, 0.3]], atol=1e-6)
    none = blending.albedo(torch.zeros_like(rho), colors.double(), base, prio)
    np.testing.assert_allclose(none.numpy(), base[None].numpy())  # nothing covers: a_0


def test_weights_gradient_against_finite_differences():
    g = torch.Generator().manual_seed(3)
    rho = torch.rand((6, 5), generator=g, dtype=torch.float64) * 0.6  # sums above and below 1
    rho[1, 0] = 0.0
    prio = (torch.rand((6, 5), generator=g, dtype=torch.float64) * 8 - 4).requires_grad_(True)
    rho_g = rho.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(blending.weights, (rho_g, prio), eps=1e-6, atol=1e-7)
    # an uncovered point (rho = 0 at the edge of its domain): finite, zero gradients
    zero = torch.zeros((1, 5), dtype=torch.float64, requires_grad=True)
    blending.weights(zero, prio[:1]).sum().backward()
    assert torch.isfinite(zero.grad).all() and torch.isfinite(prio.grad).all()


def test_storage_round_trips_and_versions(field64, layered_case):
    kp = layered_case[0]
    ks = make_model(field64, kp, LAYERED).to_kernelset()
    plain = load_hkt(io.BytesIO(encode_hkt(ks, compact=True)))
    np.testing.assert_allclose(plain.priority, kp["priority"], atol=4e-3)  # float16
    assert plain.kernel_config.blend == "layered"
    payload = encode_hkt(ks, compact=True, quantised=True)
    quant = load_hkt(io.BytesIO(payload))
    order = np.argsort(kp["face_ids"], kind="stable")  # a quantised file sorts by face
    np.testing.assert_allclose(quant.priority, kp["priority"][order], atol=16 / 255 / 2 + 1e-9)
    with zipfile.ZipFile(io.BytesIO(payload)) as zf:
        assert json.loads(zf.read("manifest.json"))["version"] == 6
    with zipfile.ZipFile(io.BytesIO(encode_hkt(ks, compact=True))) as zf:
        assert json.loads(zf.read("manifest.json"))["version"] == 5
    paper = make_model(field64, kp, CONFIG).to_kernelset()
    assert paper.priority is None
    for quantised, version in ((False, 1), (True, 4)):
        with zipfile.ZipFile(io.BytesIO(encode_hkt(paper, True, quantised))) as zf:
            assert json.loads(zf.read("manifest.json"))["version"] == version


def test_storage_refuses_a_blend_its_version_cannot_hold(field64, layered_case):
    kp = layered_case[0]
    ks = make_model(field64, kp, LAYERED).to_kernelset()
    assert_extension_member_checked(ks, "priority", "the layered blend")
    # a version-5 manifest rewritten to claim the paper's blend
    buf = io.BytesIO(encode_hkt(ks, compact=True))
    out = io.BytesIO()
    with zipfile.ZipFile(buf) as src, zipfile.ZipFile(out, "w") as dst:
        for item in src.infolist():
            data = src.read(item)
            if item.filename == "manifest.json":
                data = json.dumps(dict(json.loads(data), blend="paper")).encode()
            dst.writestr(item, data)
    with pytest.raises(KernelSetError, match="version-5 file cannot hold a 'paper' blend"):
        load_hkt(io.BytesIO(out.getvalue()))


def test_a_fit_trains_the_priorities_and_keeps_them_through_density_control():
    """A short layered UV fit (the default preset) with densification: priorities move,
    survive clones, splits and the colour solve, and the written set evaluates as fitted."""
    from hktex_engine.config import fit_params_from
    from hktex_engine.fitting.uv import fit_uv
    from hktex_engine.kernels.model import HeatKernelModel
    from hktex_engine.spectra.grid import compute_spectra
    from tests.test_fit_uv import TINY, two_colour_sphere

    mesh = two_colour_sphere()
    spectra = compute_spectra(mesh, TINY)
    params = fit_params_from(
        {"blend": "layered", "kernels": 60, "steps": 80, "points_per_step": 256, "seed": 3}
    )
    params = replace(params, kernel=replace(params.kernel, k_search=20, k_blend=8))
    result = fit_uv(mesh, spectra, params, eval_points=500)
    ks = result.kernelset
    assert ks.kernel_config.blend == "layered" and ks.priority is not None
    assert any(e["kind"] == "densify" for e in result.density_events)
    assert np.ptp(ks.priority) > 0.1
    back = load_hkt(io.BytesIO(encode_hkt(ks, compact=False)))
    field = SpectralField(spectra, device="cpu", dtype=torch.float32)
    f, b = random_points(spectra, 200, seed=9)
    with torch.no_grad():
        a = HeatKernelModel.from_kernelset(ks, field).albedo(f, b)
        c = HeatKernelModel.from_kernelset(back, field).albedo(f, b)
    np.testing.assert_allclose(a.numpy(), c.numpy(), atol=1e-5)


def test_flat_params_pick_the_blend():
    """``hktex fit --blend`` and the API's ``params.blend`` reach the kernel config."""
    from hktex_engine.config import fit_params_from

    assert fit_params_from({}).kernel.blend == "paper"
    layered = fit_params_from({"blend": "layered", "preset": "later"})
    assert layered.kernel.blend == "layered" and layered.kernel.k_blend == 30
    with pytest.raises(ValueError, match="blend must be one of"):
        fit_params_from({"blend": "multiply"})


@pytest.mark.parametrize(("quantise", "version"), [(False, 5), (True, 6)])
def test_cli_fit_writes_a_layered_set(tmp_path, capsys, quantise, version):
    from hktex_engine.cli import main
    from hktex_engine.evaluation.synthetic import write_textured_obj
    from hktex_engine.spectra.grid import compute_spectra, write_spectra
    from tests.test_fit_uv import TINY, two_colour_arrays, two_colour_sphere

    sdir = write_spectra(compute_spectra(two_colour_sphere(), TINY), tmp_path / "spectra")
    obj = write_textured_obj(tmp_path / "m.obj", *two_colour_arrays())
    out = tmp_path / "l.hkt"
    argv = [str(obj), "-o", str(out), "--spectra", str(sdir), "--kernels", "60"]
    argv += ["--steps", "3", "--eval-points", "300", "--json", "--blend", "layered"]
    assert main(["fit", *argv, *(["--quantise"] if quantise else [])]) == 0
    json.loads(capsys.readouterr().out)
    with zipfile.ZipFile(out) as zf:
        assert json.loads(zf.read("manifest.json"))["version"] == version
    ks = load_hkt(out)
    assert ks.kernel_config.blend == "layered" and ks.priority.shape == (len(ks),)


def test_priorities_wait_for_their_start():
    """``priority_start``: the optimiser leaves the priorities at 0 (the paper's blend) before
    that fraction of the steps, and trains them after it."""
    from hktex_engine.config import fit_params_from
    from hktex_engine.fitting.uv import fit_uv
    from hktex_engine.spectra.grid import compute_spectra
    from tests.test_fit_uv import TINY, two_colour_sphere

    mesh = two_colour_sphere()
    spectra = compute_spectra(mesh, TINY)
    base = {"blend": "layered", "kernels": 40, "steps": 20, "points_per_step": 128, "seed": 2}
    base["densify"] = False
    never = fit_uv(mesh, spectra, fit_params_from({**base, "priority_start": 1.0}), eval_points=300)
    assert np.all(never.kernelset.priority == 0)
    late = fit_uv(mesh, spectra, fit_params_from({**base, "priority_start": 0.5}), eval_points=300)
    moved = np.abs(late.kernelset.priority).max()
    # ten steps at lr_priority: an Adam step is at most (1 - b1) / sqrt(1 - b2) ~ 3.2 lr
    assert 0 < moved <= 10 * 0.02 * 3.2
